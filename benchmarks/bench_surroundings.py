"""The plate among its surroundings: a lit floor, supports, cut-outs, a dark background.

Prints one table: for each scene, the right verdict, then per seed the radius error against the
target, the verdict, the deviation RMS / max, the measured area against the target's and how many
edge regions were left out as segmentation artefacts.

    .venv/bin/python benchmarks/bench_surroundings.py [--size 1224x1024] [--seeds 0 1] [--scenes corner]

Bundles are rendered once into a temporary folder; only ``inspect`` is timed.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

from pipeline.parallel import configure_process
from pipeline.run import inspect
from pipeline.simulate import (
    CaptureSpec,
    Cutout,
    Dent,
    Floor,
    PlateSpec,
    rail_supports,
    simulate_capture,
)

FLOOR = Floor(gap_mm=300.0, supports=rail_supports((3000.0, 3000.0), 300.0, 3))
#: rails over a dark floor: only their bright tops are lit, and they join the plate's brightness mask
DARK_FLOOR = Floor(
    gap_mm=300.0, albedo=0.03, texture=0.0, supports=rail_supports((3000.0, 3000.0), 300.0, 3)
)
CUT = (Cutout.circle(400.0, -300.0, 260.0),)
#: a corner bent 30 mm towards the cameras (a forming defect: the plate fails)
BENT_CORNER = (Dent(x_mm=-1500.0, y_mm=-1500.0, radius_mm=150.0, depth_mm=-30.0),)
#: another corner bent 20 mm away from the cameras, over a wider radius
DOWN_CORNER = (Dent(x_mm=-1500.0, y_mm=1500.0, radius_mm=300.0, depth_mm=20.0),)
NEAR = dict(near_field_mm=2800.0, light_elevation_deg=30.0, led_mu=1.5)
#: name, plate, target radius (mm), capture options, right verdict
SCENES = (
    ("lit floor, rails", PlateSpec(floor=FLOOR), 5000.0, {}, "pass"),
    ("dark floor, rails", PlateSpec(floor=DARK_FLOOR), 5000.0, {}, "pass"),
    ("lit floor, 520 mm cut-out", PlateSpec(cutouts=CUT, floor=FLOOR), 5000.0, {}, "pass"),
    ("dark background, cut-out", PlateSpec(cutouts=CUT), 5000.0, {}, "pass"),
    ("under-bent R4600, lit floor", PlateSpec(radius_mm=4600.0, floor=FLOOR), 5000.0, {}, "fail"),
    ("bent corner, dark background", PlateSpec(dents=BENT_CORNER), 5000.0, {}, "fail"),
    ("bent corner, lit floor", PlateSpec(dents=BENT_CORNER, floor=FLOOR), 5000.0, {}, "fail"),
    ("corner bent down, lit floor", PlateSpec(dents=DOWN_CORNER, floor=FLOOR), 5000.0, {}, "fail"),
    ("LEDs, lit floor, cut-out", PlateSpec(cutouts=CUT, floor=FLOOR), 5000.0, NEAR, "pass"),
    (
        "concave R3500, floor 400 mm",
        PlateSpec(
            convex=False,
            radius_mm=3500.0,
            floor=Floor(gap_mm=400.0, supports=rail_supports((3000.0, 3000.0), 400.0, 3)),
        ),
        3500.0,
        {},
        "pass",
    ),
)


def main() -> None:
    configure_process()  # the thread policy of the CLI's process, so that timings compare
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", default="1224x1024", help="image size WIDTHxHEIGHT px")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument(
        "--scenes", nargs="+", default=None, help="only the scenes whose name contains one of these"
    )
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    print(f"\n## The plate among its surroundings ({width}x{height}, seeds {args.seeds})\n")
    print(
        "Each cell: radius error against the target, verdict, deviation RMS / max, measured area / target "
        "area, edge regions left out. Time: median inspect, s.\n"
    )
    print("| scene | right | result per seed | time s |")
    print("|---|---|---|---|")
    with tempfile.TemporaryDirectory(prefix="bench-surroundings-") as tmp:
        root = Path(tmp)
        warm = False
        for name, plate, radius, capture, right in SCENES:
            if args.scenes and not any(part in name for part in args.scenes):
                continue
            cells, times = [], []
            for seed in args.seeds:
                bundle = simulate_capture(
                    root / f"{len(times)}-{name[:10].replace(' ', '_')}-{seed}",
                    plate=plate,
                    capture=CaptureSpec(width=width, height=height, **capture),
                    seed=200 + seed,
                )
                target = {
                    "format": "plate-target/1",
                    "shape": {"type": "cylinder", "radius_mm": radius},
                    "size_mm": [3000.0, 3000.0],
                    "tolerance_mm": 2.0,
                }
                if not warm:
                    inspect(bundle, target, out_dir=root / "warm")
                    warm = True
                t = time.perf_counter()
                doc = inspect(bundle, target, out_dir=bundle / "out").document
                times.append(time.perf_counter() - t)
                details = json.loads((bundle / "out" / "details.json").read_text())
                ratio = details["segmentation"]["area_ratio"]
                cells.append(
                    f"{doc['radius_error_pct']:+.3f} % {doc['verdict']} ({doc['deviation_mm']['rms']:.2f} / "
                    f"{doc['deviation_mm']['max_abs']:.1f} mm, area {ratio:.3f}, "
                    f"{len(details['excluded_regions'])} left out)"
                )
            print(
                f"| {name} | {right} | "
                + "<br>".join(cells)
                + f" | {statistics.median(times):.1f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
