"""Radius error and verdict under the lights of a real cell: distant, near-field LEDs, bumped, glare.

Prints one table: for each kind of capture (cylinder R 5000 mm over 3 x 3 m at 3 m, perfect, so
the right verdict is PASS), the radius error, deviation RMS / p95 / max, verdict and run time of
``plate-inspect inspect`` on the simulated cell, over several seeds.

    .venv/bin/python benchmarks/bench_lights.py [--size 1224x1024] [--seeds 0 1 2] [--before DIR]

``--before DIR`` runs the same bundles with another checkout of the project (e.g. a ``git worktree``
of an older commit) in a subprocess and prints its figures beside (a crash shows as ``crash``).
Bundles are rendered once into a temporary folder; only ``inspect`` is timed.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from pipeline.parallel import configure_process
from pipeline.run import inspect
from pipeline.simulate import CaptureSpec, PlateSpec, simulate_capture

#: 12 LEDs on the gantry 2.8 m above the plate, 30 deg from the optical axis seen from its centre.
NEAR = dict(near_field_mm=2800.0, light_elevation_deg=30.0, led_mu=1.5)
CASES = (
    ("distant lights, known", dict()),
    ("near-field, positions given", dict(NEAR)),
    ("near-field, nominal directions", dict(NEAR, manifest_lights="nominal")),
    ("distant, written 1 deg off", dict(light_error_deg=1.0)),
    ("glare, 18 distant lights", dict(n_lights=18, specular=0.5)),
    ("glare, 18 LEDs, nominal", dict(NEAR, n_lights=18, specular=0.5, manifest_lights="nominal")),
    ("glare, 18 LEDs, positions", dict(NEAR, n_lights=18, specular=0.5)),
    (
        "near-field, nominal directions 1 deg off",
        dict(NEAR, manifest_lights="nominal", light_error_deg=1.0),
    ),
    (
        "glare, 18 LEDs, nominal 1 deg off",
        dict(NEAR, n_lights=18, specular=0.5, manifest_lights="nominal", light_error_deg=1.0),
    ),
    (
        "glare, 18 distant lights, written 1 deg off",
        dict(n_lights=18, specular=0.5, light_error_deg=1.0),
    ),
    (
        "glare (broad lobe), 18 LEDs, positions",
        dict(NEAR, n_lights=18, specular=0.5, shininess=15.0),
    ),
    (
        "glare (broad lobe), 18 LEDs, nominal",
        dict(NEAR, n_lights=18, specular=0.5, shininess=15.0, manifest_lights="nominal"),
    ),
    (
        "glare (broad lobe), 12 distant lights",
        dict(specular=0.4, shininess=15.0),
    ),
    (
        "glare (broad lobe), 12 distant lights, written 1 deg off",
        dict(specular=0.4, shininess=15.0, light_error_deg=1.0),
    ),
)

_BEFORE = """
import json, sys
from pipeline.run import inspect
try:
    d = inspect(sys.argv[1], sys.argv[1] + "/target.json", out_dir=sys.argv[2]).document
    print(json.dumps({"radius_error_pct": d["radius_error_pct"], "rms": d["deviation_mm"]["rms"],
                      "p95": d["deviation_mm"]["p95"], "max": d["deviation_mm"]["max_abs"],
                      "verdict": d["verdict"]}))
except Exception as exc:  # the old code's crash is the figure
    print(json.dumps({"crash": type(exc).__name__}))
"""


def _after(bundle: Path) -> tuple[dict, float]:
    t = time.perf_counter()
    d = inspect(bundle, bundle / "target.json", out_dir=bundle / "after").document
    return {
        "radius_error_pct": d["radius_error_pct"],
        "rms": d["deviation_mm"]["rms"],
        "p95": d["deviation_mm"]["p95"],
        "max": d["deviation_mm"]["max_abs"],
        "verdict": d["verdict"],
    }, time.perf_counter() - t


def _before(bundle: Path, checkout: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=str(checkout))
    out = subprocess.run(
        [sys.executable, "-c", _BEFORE, str(bundle), str(bundle / "before")],
        env=env,
        capture_output=True,
        text=True,
        cwd=checkout,
    )
    lines = out.stdout.strip().splitlines()
    return json.loads(lines[-1]) if lines else {"crash": f"exit {out.returncode}"}


def _cell(r: dict) -> str:
    if "crash" in r:
        return f"crash ({r['crash']})"
    return (
        f"{r['radius_error_pct']:+.3f} % {r['verdict']} "
        f"({r['rms']:.2f} / {r['p95']:.2f} / {r['max']:.2f} mm)"
    )


def main() -> None:
    configure_process()  # the thread policy of the CLI's process, so that timings compare
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", default="1224x1024", help="image size WIDTHxHEIGHT px")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument(
        "--before", type=Path, default=None, help="another checkout to compare with"
    )
    parser.add_argument(
        "--only", default=None, help="comma-separated case numbers (1-based) to run"
    )
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    cases = CASES if args.only is None else [CASES[int(i) - 1] for i in args.only.split(",")]

    inspect_warm = None
    print(
        f"\n## Lights of a real cell: cylinder R5000 convex, 3 x 3 m at 3 m, {width}x{height}, seeds "
        f"{args.seeds}\n"
    )
    print(
        "Each cell: radius error, verdict (right: pass), deviation RMS / p95 / max. Time: median inspect, s.\n"
    )
    head = (
        "| capture | "
        + ("before | " if args.before else "")
        + "after | max abs radius err % | time s |"
    )
    print(head)
    print("|---" * (head.count("|") - 1) + "|")
    with tempfile.TemporaryDirectory(prefix="bench-lights-") as tmp:
        root = Path(tmp)
        for name, spec in cases:
            befores, afters, times, errs = [], [], [], []
            for seed in args.seeds:
                bundle = simulate_capture(
                    root / f"{name[:12].replace(' ', '_')}-{seed}",
                    plate=PlateSpec(),
                    capture=CaptureSpec(width=width, height=height, **spec),
                    seed=100 + seed,
                )
                if inspect_warm is None:  # load the compiled kernels once, outside the timings
                    inspect(bundle, bundle / "target.json", out_dir=root / "warm")
                    inspect_warm = True
                if args.before:
                    befores.append(_cell(_before(bundle, args.before)))
                after, seconds = _after(bundle)
                afters.append(_cell(after))
                errs.append(abs(after["radius_error_pct"]))
                times.append(seconds)
            row = f"| {name} | " + ("<br>".join(befores) + " | " if args.before else "")
            print(
                row
                + "<br>".join(afters)
                + f" | {max(errs):.3f} | {statistics.median(times):.1f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
