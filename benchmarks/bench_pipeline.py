"""The source paper's experiment (Fig. 8/9) on the simulated cell, and per-stage timings.

Prints two tables:
1. radius error and run time against the number of light directions
   (3, 6, 12, 18, 24, 30, 36) on cylinders of several radii, convex and concave;
2. per-stage timings of ``pipeline.run.inspect`` at 1224x1024 and 2448x2048
   (12 lights, best of ``--repeat`` runs, interpreter start-up excluded).

    .venv/bin/python benchmarks/bench_pipeline.py [--seeds 0 1] [--repeat 3] [--quick]

Bundles are rendered once into a temporary folder; only ``inspect`` is timed.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

from pipeline.parallel import configure_process
from pipeline.run import STAGES, inspect
from pipeline.simulate import CaptureSpec, PlateSpec, simulate_capture

LIGHTS = (3, 6, 12, 18, 24, 30, 36)
PLATES = (
    ("R5000 convex", PlateSpec(shape="cylinder", radius_mm=5000.0, convex=True)),
    (
        "R3000 concave",
        PlateSpec(shape="cylinder", radius_mm=3000.0, convex=False, tilt_deg=(-2.0, 3.0)),
    ),
    (
        "R12000 convex",
        PlateSpec(shape="cylinder", radius_mm=12000.0, convex=True, in_plane_deg=15.0),
    ),
)


def lights_table(root: Path, seeds: list[int], lights: tuple[int, ...]) -> None:
    print(
        "\n## Radius error against the number of lights (1224x1024, 16-bit, 0.4 % noise, stereo)\n"
    )
    print(
        "| lights | "
        + " | ".join(f"{name} err %" for name, _ in PLATES)
        + " | mean abs err % | inspect s |"
    )
    print("|---" * (len(PLATES) + 3) + "|")
    for n in lights:
        errs, times, cells = [], [], []
        for name, plate in PLATES:
            per_plate = []
            for seed in seeds:
                bundle = simulate_capture(
                    root / f"l{n}-{name.replace(' ', '')}-{seed}",
                    plate=plate,
                    capture=CaptureSpec(n_lights=n),
                    seed=1000 + seed,
                )
                t = time.perf_counter()
                doc = inspect(bundle, bundle / "target.json", out_dir=bundle / "out").document
                times.append(time.perf_counter() - t)
                per_plate.append(doc["radius_error_pct"])
            errs += [abs(e) for e in per_plate]
            cells.append(" / ".join(f"{e:+.3f}" for e in per_plate))
        print(
            f"| {n} | "
            + " | ".join(cells)
            + f" | {statistics.mean(errs):.3f} | {statistics.median(times):.2f} |"
        )


def timing_table(root: Path, sizes: list[tuple[int, int]], repeat: int) -> None:
    print(
        "\n## Per-stage timings, 12 lights, cylinder R5000 "
        f"(run with the best total of {repeat}, seconds)\n"
    )
    print(
        "Stages overlap (stereo beside normals, curvature beside deviation): they do not add up to the total.\n"
    )
    print("| size | " + " | ".join(STAGES) + " | total | median total | worst total |")
    print("|---" * (len(STAGES) + 4) + "|")
    for width, height in sizes:
        bundle = simulate_capture(
            root / f"t{width}",
            plate=PLATES[0][1],
            capture=CaptureSpec(n_lights=12, width=width, height=height),
            seed=7,
        )
        inspect(
            bundle, bundle / "target.json", out_dir=bundle / "out"
        )  # warm-up: numba loads (or compiles) its kernels
        runs = [
            inspect(bundle, bundle / "target.json", out_dir=bundle / "out").document["timings_s"]
            for _ in range(repeat)
        ]
        best = min(runs, key=lambda t: t["total"])
        totals = [t["total"] for t in runs]
        print(
            f"| {width}x{height} | "
            + " | ".join(f"{best.get(s, 0.0):.3f}" for s in STAGES)
            + f" | {best['total']:.2f} | {statistics.median(totals):.2f} | {max(totals):.2f} |"
        )


def main() -> None:
    configure_process()  # the thread policy of the CLI's process, so that timings compare
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument(
        "--quick", action="store_true", help="3, 12 and 36 lights, one seed, 1224x1024 only"
    )
    parser.add_argument("--only", choices=["timing", "lights"], help="print one of the two tables")
    args = parser.parse_args()
    lights = (3, 12, 36) if args.quick else LIGHTS
    seeds = args.seeds[:1] if args.quick else args.seeds
    sizes = [(1224, 1024)] if args.quick else [(1224, 1024), (2448, 2048)]
    with tempfile.TemporaryDirectory() as tmp:
        if args.only != "lights":
            timing_table(Path(tmp), sizes, args.repeat)
        if args.only != "timing":
            lights_table(Path(tmp), seeds, lights)


if __name__ == "__main__":
    main()
