"""Plates formed exactly, and real defects: deviation, uncertainty, radius and verdict per cell.

Prints one row per capture: the deviation's p95 and max, the expanded uncertainty U95 (k = 2) and
the test uncertainty ratio, the radius error against its U, the verdict and any warning. The
right verdict is pass for every plate formed exactly and fail for the dent, the under-bent plate
and the bump on the glossy plate (docs/uncertainty.md).

    .venv/bin/python benchmarks/bench_capable.py [--seeds 1 2] [--size 1224x1024] [--cases glare]
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
from pathlib import Path
from typing import Any

from pipeline.parallel import configure_process
from pipeline.run import inspect, warm_up
from pipeline.simulate import (
    CaptureSpec,
    Cutout,
    Dent,
    Floor,
    PlateSpec,
    rail_supports,
    simulate_capture,
)

FLOOR = Floor(gap_mm=400.0, supports=rail_supports((3000.0, 3000.0), 400.0, 3))
LED = {"near_field_mm": 2800.0, "led_mu": 1.0}
#: A glossy coating (a specular lobe half as bright as the diffuse light) under 18 lights.
GLARE = {"n_lights": 18, "specular": 0.5}
GLARE_LEDS = {**GLARE, "near_field_mm": 2800.0, "light_elevation_deg": 30.0, "led_mu": 1.5}
#: (name, PlateSpec keywords, CaptureSpec keywords, target radius or None for the plate's own)
CASES: tuple[tuple[str, dict[str, Any], dict[str, Any], float | None], ...] = (
    ("12 distant lights", {}, {}, None),
    ("3 distant lights", {}, {"n_lights": 3}, None),
    (
        "3 lights, head 4.2 m away",
        {"distance_mm": 4200.0},
        {"n_lights": 3, "working_distance_mm": 4200.0},
        None,
    ),
    (
        "12 lights, head 2.5 m away",
        {"distance_mm": 2500.0},
        {"working_distance_mm": 2500.0},
        None,
    ),
    (
        "12 lights, head 4.2 m away",
        {"distance_mm": 4200.0},
        {"working_distance_mm": 4200.0},
        None,
    ),
    (
        "12 lights, head 3.5 m away",
        {"distance_mm": 3500.0},
        {"working_distance_mm": 3500.0},
        None,
    ),
    (
        "3 lights, head 3.5 m away",
        {"distance_mm": 3500.0},
        {"n_lights": 3, "working_distance_mm": 3500.0},
        None,
    ),
    ("12 LEDs 2.8 m, positions", {}, LED, None),
    ("12 LEDs 2.8 m, nominal directions", {}, {**LED, "manifest_lights": "nominal"}, None),
    ("12 lights written 1 deg off", {}, {"light_error_deg": 1.0}, None),
    (
        "LEDs, floor 400 mm, cut-out",
        {"floor": FLOOR, "cutouts": (Cutout.circle(400.0, -300.0, 260.0),)},
        LED,
        None,
    ),
    ("glare, 18 distant lights", {}, GLARE, None),
    ("glare, 18 LEDs 2.8 m, positions", {}, GLARE_LEDS, None),
    ("glare (broad lobe), 18 LEDs, positions", {}, {**GLARE_LEDS, "shininess": 15.0}, None),
    ("glare (broad lobe), 12 distant lights", {}, {"specular": 0.4, "shininess": 15.0}, None),
    ("sphere R 8000", {"shape": "sphere", "radius_mm": 8000.0}, {}, None),
    ("dent 5 mm (fail)", {"dents": (Dent(-600.0, 300.0, 150.0, 5.0),)}, {}, None),
    ("under-bent R 5250 against R 5000 (fail)", {"radius_mm": 5250.0}, {}, 5000.0),
    (
        "bump 2.8 mm, glare, 18 LEDs (fail)",
        {"dents": (Dent(400.0, -300.0, 250.0, -2.8),)},
        GLARE_LEDS,
        None,
    ),
    (
        "dent 6 mm, broad lobe, 12 distant lights (fail)",
        {"dents": (Dent(-600.0, 300.0, 150.0, 6.0),)},
        {"specular": 0.4, "shininess": 15.0},
        None,
    ),
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--size", default="1224x1024")
    parser.add_argument(
        "--cases",
        nargs="+",
        default=None,
        help="run only the captures whose name contains one of these",
    )
    args = parser.parse_args()
    configure_process()
    warm_up()
    width, height = (int(v) for v in args.size.lower().split("x"))
    print(f"\n## Plates formed exactly and real defects, {width}x{height}, tolerance 2 mm\n")
    print(
        "| capture | seed | deviation p95 / max mm | U95 mm (tol/U) | radius error % (U %) | verdict | warnings |"
    )
    print("|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for name, plate_kw, capture_kw, target_radius in CASES:
            if args.cases is not None and not any(c in name for c in args.cases):
                continue
            for seed in args.seeds:
                bundle = simulate_capture(
                    Path(tmp) / f"{len(name)}-{seed}",
                    plate=PlateSpec(**plate_kw),
                    capture=CaptureSpec(width=width, height=height, **capture_kw),
                    seed=seed,
                )
                target = Path(bundle / "target.json")
                if target_radius is not None:
                    import json

                    doc = json.loads(target.read_text())
                    doc["shape"]["radius_mm"] = target_radius
                    target = Path(tmp) / "target.json"
                    target.write_text(json.dumps(doc))
                r = inspect(bundle, target, out_dir=bundle / "out").document
                shutil.rmtree(bundle)  # a 2448x2048 bundle is ~0.4 GB: one at a time on the disk
                _row(name, seed, r)


def _row(name: str, seed: int, r: dict[str, Any]) -> None:
    u, dev = r["uncertainty"], r["deviation_mm"]
    radius = "-"
    if r["radius_error_pct"] is not None and u["radius_mm"] is not None:
        radius = f"{r['radius_error_pct']:+.3f} ({100 * u['radius_mm'] / r['radius_mm']:.3f})"
    said = "; ".join(w.split(":")[0][:60] for w in r.get("warnings") or []) or "-"
    print(
        f"| {name} | {seed} | {dev['p95']:.3f} / {dev['max_abs']:.2f} | {u['deviation_mm']:.3f} "
        f"({r['tolerance_mm'] / u['deviation_mm']:.0f}) | {radius} | {r['verdict']} | {said} |"
    )


if __name__ == "__main__":
    main()
