"""A roll-bending campaign through the REST API, each pass measured by the real pipeline.

Run from the project root:  .venv/bin/python benchmarks/bench_forming_api.py [--plates 8] [--seed 0]
                            [--width 1224 --height 1024 --lights 12] [--case "batch yield"]

The path issue 14's acceptance takes: a machine (``PUT /machines``), each plate's target with its
material (``PUT /plates/{id}/target``), then per pass ``GET /plates/{id}/advice``, the pass rolled
against the hidden physics of ``pipeline.forming.campaign`` (``TruePlate``: yield factor, compliance
2 mm/MN, 0.1 mm displacement scatter), and a simulated inspection of the formed radius with the pass
as its ``process``, run by the job code (``app.jobs.execute_inspection``) on a fresh SQLite data
directory: the pipeline renders and measures the plate, and the advice reads the measured radius from
the database. Prints each plate's passes (setting, formed radius, measured radius, verdict) and a
summary: passes, plates told ``reverse``, plates over-bent (their true radius past the verdict's band
on the tight side), the pipeline's radius error. ``--case`` takes the plates and the hidden physics
of one of issue 27's stress cases (``pipeline.forming.campaign.STRESS``: "batch yield", "new grade",
"geometry 3 % short", ...) instead of the model's mixed batch.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from fastapi.testclient import TestClient

from app.jobs import execute_inspection
from app.main import create_app
from app.settings import Settings
from pipeline.forming.advice import curvature_band, target_curvature
from pipeline.forming.campaign import STRESS, TruePhysics, TruePlate, random_batch, stress_plates
from pipeline.forming.records import Machine

TOKEN = "bench-token-0123456789"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
MACHINE = {
    "kind": "three-roll-pyramid",
    "bottom_roll_spacing_mm": 1400,
    "bottom_roll_diameter_mm": 420,
    "top_roll_diameter_mm": 500,
}


def put_target(client: TestClient, plate_id: str, target) -> None:
    body = {
        "format": "plate-target/1",
        "shape": {"type": "cylinder", "radius_mm": target.radius_mm},
        "size_mm": [target.width_mm, target.length_mm],
        "tolerance_mm": target.tolerance_mm,
        "material": dataclasses.asdict(target.material),
    }
    r = client.put(f"/api/v1/plates/{plate_id}/target", json=body, headers=AUTH)
    r.raise_for_status()


def inspect_pass(client, settings, plate_id, displacement_mm, radius_mm, seed, sim) -> dict:
    """A simulated inspection of the formed radius with its pass; run to the end; its document."""
    r = client.post(
        f"/api/v1/plates/{plate_id}/inspections/simulated",
        json={
            **sim,
            "radius_mm": radius_mm,
            "seed": seed,
            "process": {
                "method": "roll-bending",
                "machine_id": "R3-01",
                "top_roll_displacement_mm": displacement_mm,
            },
        },
        headers=AUTH,
    )
    r.raise_for_status()
    inspection_id = r.json()["id"]
    state = client.app.state
    execute_inspection(
        inspection_id,
        settings=settings,
        session_factory=state.session_factory,
        storage=state.storage,
    )
    return client.get(f"/api/v1/inspections/{inspection_id}").json()


def roll_plate(client, settings, sim_plate, machine, physics, rng, sim, max_passes):
    """Roll one plate as advised until done or reverse: (passes, final action, rows, radius errors,
    over-bent)."""
    plate_id, target = sim_plate.record.plate_id, sim_plate.record.target
    put_target(client, plate_id, target)
    truth = TruePlate(sim_plate, machine, physics)
    band_hi = target_curvature(target) + physics.verdict_band * curvature_band(target)
    rows, errors, over = [], [], False
    while True:
        advice = client.get(
            f"/api/v1/plates/{plate_id}/advice", params={"machine_id": "R3-01"}
        ).json()
        d = advice["top_roll_displacement_mm"]
        if advice["action"] != "bend" or len(rows) >= max_passes or d is None:
            return len(rows), advice["action"], rows, errors, over
        k = truth.roll(d, rng)
        over |= k > band_hi
        formed = target.surface_radius_mm(1.0 / k)
        body = inspect_pass(client, settings, plate_id, d, formed, int(rng.integers(1 << 30)), sim)
        if body["status"] != "done":
            raise SystemExit(
                f"{plate_id}: inspection {body['id']} {body['status']}: {body['error']}"
            )
        measured = body["result"]["radius_mm"]
        errors.append(100.0 * (measured - formed) / formed)
        rows.append(f"{d:.1f} mm: {formed:.0f} / {measured:.0f} {body['verdict']}")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--plates", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--width", type=int, default=1224)
    ap.add_argument("--height", type=int, default=1024)
    ap.add_argument("--lights", type=int, default=12)
    ap.add_argument("--max-passes", type=int, default=6)
    ap.add_argument(
        "--case",
        default=None,
        help="a stress case (a part of its name in STRESS): its plates and physics",
    )
    args = ap.parse_args()
    sim = {"width": args.width, "height": args.height, "n_lights": args.lights}
    machine = Machine.from_dict("R3-01", MACHINE)
    if args.case is None:
        physics = TruePhysics()
        plates = random_batch(args.plates, np.random.default_rng(args.seed))
    else:
        name = next(n for n in STRESS if args.case in n)
        over, kind = STRESS[name]
        physics = TruePhysics(**over)
        plates = stress_plates(kind, args.plates, args.seed)
        print(f"stress case {name!r}, seed {args.seed}\n")
    rng = np.random.default_rng(args.seed + 100)
    with tempfile.TemporaryDirectory() as tmp:
        settings = Settings(data_dir=Path(tmp), api_token=TOKEN)
        app = create_app(settings)
        t0 = time.perf_counter()
        try:
            with TestClient(app) as client:
                client.put("/api/v1/machines/R3-01", json=MACHINE, headers=AUTH).raise_for_status()
                print(
                    "| plate | t mm | target R mm | yield x | passes | final | setting: formed / measured R mm |"
                )
                print("|---|---|---|---|---|---|---|")
                outcomes, errors = [], []
                for p in plates:
                    n, final, rows, errs, over = roll_plate(
                        client, settings, p, machine, physics, rng, sim, args.max_passes
                    )
                    outcomes.append((n, final, over))
                    errors += errs
                    tg = p.record.target
                    print(
                        f"| {p.record.plate_id} | {tg.material.thickness_mm:g} | {tg.radius_mm:.0f} "
                        f"| {p.yield_factor:.3f} | {n} | {final} | {'; '.join(rows)} |",
                        flush=True,
                    )
        finally:
            app.state.engine.dispose()
    passes = [n for n, _, _ in outcomes]
    print(
        f"\npasses {dict(sorted(collections.Counter(passes).items()))}, mean after the first plate "
        f"{np.mean(passes[1:]):.2f}, done {sum(f == 'done' for _, f, _ in outcomes)}, "
        f"reverse {sum(f == 'reverse' for _, f, _ in outcomes)}, over-bent "
        f"{sum(o for _, _, o in outcomes)}; pipeline radius error "
        f"mean {np.mean(errors):+.3f} %, max abs {np.max(np.abs(errors)):.3f} % over {len(errors)} "
        f"inspections; {time.perf_counter() - t0:.0f} s"
    )


if __name__ == "__main__":
    main()
