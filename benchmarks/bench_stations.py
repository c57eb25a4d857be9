"""Plates longer than the view measured from their conveyor stations (issue 29, docs/stations.md).

For each seed, three plates of the simulated cell (cylinder R 5000 mm, 3 m wide, convex, at 3 m), each
photographed at conveyor stations whose encoder is up to 4 mm off and which yaw by up to 0.3 deg:

- ``exact``: formed exactly;
- ``dent``: a dent (4-6 mm deep, 250 mm radius) in the middle of an overlap of two stations;
- ``under-bent``: rolled to R 5300 mm along its whole length against its R 5000 mm target.

The plate's length and its stations change with the seed (6 m at 3, 9 m at 4, 12 m at 5, 10.5 m at 6
stations).
Prints one row per plate: length, stations, the radius's error against the plate's true radius (%),
the deviation's 95th percentile and maximum (mm), the dent's own depth where there is one, the verdict
and the inspection's time; then the time of the 4-station plate against one of its stations inspected
alone (one run of each, the plate first in its process: the speed figure is
``benchmarks/bench_stations_speed.py``'s, medians of alternating runs).

    .venv/bin/python benchmarks/bench_stations.py [--size 1224x1024] [--seeds 0 1 2 3]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

from pipeline.parallel import configure_process
from pipeline.run import inspect, warm_up
from pipeline.simulate import CaptureSpec, Dent, PlateSpec, simulate_stations

#: (plate length mm, stations) by seed (cycled).
LAYOUTS = ((6000.0, 3), (9000.0, 4), (12000.0, 5), (10500.0, 6))
#: The view is about this long along the travel at 3 m; the stations are spaced so that both ends of
#: the plate are in view with ~150 mm to spare.
VIEW_MM = 3300.0
RADIUS_MM = 5000.0


def _spacing(length_mm: float, n: int) -> float:
    return (length_mm - VIEW_MM + 300.0) / (n - 1)


def _case(name: str, length: float, n: int, seed: int) -> tuple[PlateSpec, float, float | None]:
    """The plate, its target radius and the dent's depth (None without one)."""
    spacing = _spacing(length, n)
    if name == "dent":
        depth = 4.0 + 2.0 * ((seed * 0.37) % 1.0)
        seam_y = (1 - (n - 1) / 2.0) * spacing - spacing / 2.0  # between stations 0 and 1
        dent = Dent(x_mm=250.0, y_mm=seam_y, radius_mm=250.0, depth_mm=depth)
        return PlateSpec(size_mm=(3000.0, length), dents=(dent,)), RADIUS_MM, depth
    if name == "under-bent":
        return PlateSpec(size_mm=(3000.0, length), radius_mm=5300.0), RADIUS_MM, None
    return PlateSpec(size_mm=(3000.0, length)), RADIUS_MM, None


def _row(name: str, plate: PlateSpec, dent: float | None, doc: dict, n: int, seconds: float) -> str:
    true_r = float(plate.radius_mm or 0.0)
    err = 100.0 * (doc["radius_mm"] - true_r) / true_r
    dev = doc["deviation_mm"]
    dent_txt = f"{dent:5.2f}" if dent is not None else "    -"
    return (
        f"| {name:10s} | {plate.size_mm[1] / 1000:4.1f} | {n} | {err:+7.3f} | {dev['p95']:5.2f} | "
        f"{dev['max_abs']:5.2f} | {dent_txt} | {doc['verdict']:4s} | {seconds:6.1f} |"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--size", default="1224x1024", help="image size WIDTHxHEIGHT")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    parser.add_argument(
        "--work", help="keep the bundles and results here (default: a temporary folder)"
    )
    args = parser.parse_args()
    configure_process()
    warm_up()
    width, height = (int(v) for v in args.size.lower().split("x"))
    capture = CaptureSpec(width=width, height=height)
    with tempfile.TemporaryDirectory(prefix="bench-stations-") as tmp:
        root = Path(args.work or tmp)
        print(f"{width}x{height} px, encoder up to 4 mm off, yaw up to 0.3 deg\n")
        print("| plate      | L m  | N | R err % | p95   | max   | dent  | verdict | time s |")
        print("|---|---|---|---|---|---|---|---|---|")
        speed = None
        for seed in args.seeds:
            length, n = LAYOUTS[seed % len(LAYOUTS)]
            for name in ("exact", "dent", "under-bent"):
                plate, target_r, dent = _case(name, length, n, seed)
                where = root / f"s{seed}-{name}"
                bundles = simulate_stations(
                    where / "in",
                    n_stations=n,
                    spacing_mm=_spacing(length, n),
                    plate=plate,
                    capture=capture,
                    seed=seed,
                )
                target = json.loads((where / "in" / "target.json").read_text())
                target["shape"]["radius_mm"] = target_r
                t = time.perf_counter()
                doc = inspect(bundles, target, out_dir=where / "out").document
                seconds = time.perf_counter() - t
                print(_row(name, plate, dent, doc, n, seconds), flush=True)
                if n == 4 and name == "exact":
                    t = time.perf_counter()
                    inspect(bundles[1], target, out_dir=where / "one")
                    speed = (seconds, time.perf_counter() - t)
        if speed is not None:
            print(
                f"\n4 stations: {speed[0]:.1f} s; one of them alone: {speed[1]:.1f} s; "
                f"ratio {speed[0] / speed[1]:.2f}"
            )


if __name__ == "__main__":
    main()
