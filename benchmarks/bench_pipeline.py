"""The source paper's experiment (Fig. 8/9) on the simulated cell, and per-stage timings.

Prints two tables:
1. radius error and run time against the number of light directions
   (3, 6, 12, 18, 24, 30, 36) on cylinders of several radii, convex and concave;
2. per-stage timings of ``pipeline.run.inspect`` at 1224x1024 and 2448x2048 for an ideal cell,
   a near-field LED cell (positions given, and nominal directions only) and a glossy cell
   (12 lights, median of ``--repeat`` runs, each in a fresh process after the CLI's warm-up);
   with ``--against REV`` the same captures are inspected by that commit's tree too (a temporary
   git worktree, run in this environment, runs interleaved), and the table gives the ratio of the
   median totals, so that a regression shows as a ratio on whatever machine it runs. By default a
   run times its process's first inspection (the command line's case); ``--in-process N`` times the
   N-th in a row instead (a service's steady state: a tree without ``pipeline.parallel``'s heap
   policy, such as 59f1066, pays for paging its memory in on its first). ``--bare`` runs each process as
   a script that only imports ``pipeline.run`` and calls ``inspect`` (no process policy set before it,
   no warm-up; with ``--in-process 1`` its first call loads the compiled kernels).

    .venv/bin/python benchmarks/bench_pipeline.py --only timing --against 59f1066 [--repeat 3] [--in-process 4]
    .venv/bin/python benchmarks/bench_pipeline.py [--seeds 0 1] [--repeat 3] [--quick]

Bundles are rendered once into a temporary folder by this tree's simulator; only ``inspect`` is
timed (an older tree that refuses a capture, e.g. point lights before it knew them, shows "crash").
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

from pipeline.parallel import configure_process
from pipeline.run import STAGES, inspect
from pipeline.simulate import CaptureSpec, PlateSpec, simulate_capture

ROOT = Path(__file__).resolve().parents[1]

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


#: The cells the timing table measures: (name, CaptureSpec keyword arguments).
CELLS = (
    ("ideal", {}),
    ("LED positions", {"near_field_mm": 2800.0, "led_mu": 1.0}),
    ("LED nominal", {"near_field_mm": 2800.0, "led_mu": 1.0, "manifest_lights": "nominal"}),
    ("glossy", {"specular": 0.4}),
)

#: Run in a child process whose working directory is the tree to time (its ``pipeline`` is then the
#: one imported): set that tree's own process policy (a tree without ``pipeline/parallel.py``, such as
#: 59f1066, has none: this environment's editable install would otherwise hand it this tree's), warm
#: up as that tree's CLI does, inspect every bundle once, print the timings.
RUNNER = """
import json, sys, time
from pathlib import Path
bare = sys.argv[2] == "bare"  # a script that imports the pipeline and calls inspect(), nothing else
if Path("pipeline/parallel.py").exists() and not bare:  # the tree's own process policy; an older tree has none
    from pipeline.parallel import configure_process
    configure_process()
import pipeline.run as run
if hasattr(run, "warm_up") and not bare:
    run.warm_up()
out = {}
inspections = int(sys.argv[1])  # per bundle in this process: the last one's timings are kept
for bundle in sys.argv[3:]:
    b = Path(bundle)
    try:
        for _ in range(inspections):
            t = time.perf_counter()
            doc = run.inspect(b, b / "target.json", out_dir=b.parent / (b.name + "-out")).document
        dev = doc["deviation_mm"] or {}
        out[bundle] = dict(doc["timings_s"], wall=time.perf_counter() - t,
                           dev_p95=dev.get("p95", float("nan")), dev_max=dev.get("max_abs", float("nan")))
    except Exception as err:
        out[bundle] = {"crash": type(err).__name__}
print("TIMINGS " + json.dumps(out))
"""


def _run_tree(
    tree: Path, bundles: list[Path], inspections: int = 1, bare: bool = False
) -> dict[str, dict[str, float]]:
    """Inspect ``bundles`` with the code of ``tree`` in a child process, each ``inspections`` times in
    a row; timings per bundle (its last inspection's). ``bare``: the child neither sets the process
    policy nor warms up, and inherits none of this process's (a script that calls ``inspect``)."""
    env = dict(os.environ)
    if bare:
        env.pop("OMP_WAIT_POLICY", None)  # set by this process's configure_process
    done = subprocess.run(
        [
            sys.executable,
            "-c",
            RUNNER,
            str(inspections),
            "bare" if bare else "cli",
            *map(str, bundles),
        ],
        cwd=tree,
        env=env,
        capture_output=True,
        text=True,
        check=False,
    )
    line = next((ln for ln in done.stdout.splitlines() if ln.startswith("TIMINGS ")), None)
    if line is None:
        raise RuntimeError(f"{tree}: the runner printed no timings:\n{done.stderr[-2000:]}")
    timings: dict[str, dict[str, float]] = json.loads(line[len("TIMINGS ") :])
    return timings


def timing_table(
    root: Path,
    sizes: list[tuple[int, int]],
    repeat: int,
    against: str | None,
    cells: list[str] | None = None,
    inspections: int = 1,
    bare: bool = False,
) -> None:
    """Per-stage medians of ``repeat`` runs of each cell and size; with ``against``, the same captures
    timed with that commit's tree (a temporary worktree), runs interleaved, and the ratio of the
    medians of ``total``. Each run inspects a capture ``inspections`` times in its process and keeps
    the last."""
    bundles = [
        (
            name,
            (w, h),
            simulate_capture(
                root / f"{name.replace(' ', '-')}-{w}",
                plate=PLATES[0][1],
                capture=CaptureSpec(n_lights=12, width=w, height=h, **kwargs),  # type: ignore[arg-type]  # the cells' keywords are CaptureSpec's
                seed=7,
            ),
        )
        for w, h in sizes
        for name, kwargs in CELLS
        if cells is None or name in cells
    ]
    paths = [b for _, _, b in bundles]
    trees = {"now": ROOT}
    with contextlib.ExitStack() as stack:
        if against is not None:
            trees[against] = stack.enter_context(_worktree(against))
        runs: dict[str, list[dict[str, dict[str, float]]]] = {k: [] for k in trees}
        for _ in range(repeat):
            for key, tree in trees.items():
                runs[key].append(_run_tree(tree, paths, inspections, bare))
    which = "" if inspections == 1 else f", each the last of {inspections} in its process"
    if bare:
        which += ", called as a bare script: no process policy, no warm-up"
    print(
        f"\n## Per-stage timings, 12 lights, cylinder R5000 (median of {repeat} runs{which}, seconds)\n"
    )
    print(
        "Stages overlap (stereo beside normals, curvature beside deviation): they do not add up.\n"
    )
    extra = [f"{against} total", "ratio"] if against else []
    print("| cell | size | " + " | ".join(STAGES) + " | total | " + " | ".join(extra) + " |")
    print("|---" * (len(STAGES) + 3 + len(extra)) + "|")
    for name, (w, h), bundle in bundles:
        now = [r[str(bundle)] for r in runs["now"]]
        cells = [_median(now, s) for s in (*STAGES, "total")]
        row = f"| {name} | {w}x{h} | " + " | ".join(cells)
        if against:
            before = [r[str(bundle)] for r in runs[against]]
            ratio = _ratio(now, before)
            row += f" | {_median(before, 'total')} | {ratio}"
        print(row + " |")
        if against:
            stages = [_median(before, s) for s in (*STAGES, "total")]
            print(f"| {name}, {against} | {w}x{h} | " + " | ".join(stages) + " | | |")
    _deviation_table(bundles, runs, against)


def _deviation_table(
    bundles: list[tuple[str, tuple[int, int], Path]],
    runs: dict[str, list[dict[str, dict[str, float]]]],
    against: str | None,
) -> None:
    """The plate (a cylinder formed exactly) as each tree measured it: deviation p95 / max, mm."""
    print("\n## The same plates formed exactly: deviation p95 / max, mm (right: pass, near 0)\n")
    trees = ["now", *([against] if against else [])]
    print("| cell | size | " + " | ".join(trees) + " |")
    print("|---" * (2 + len(trees)) + "|")
    for name, (w, h), bundle in bundles:
        cells = []
        for key in trees:
            first = runs[key][0][str(bundle)]
            cells.append(
                f"crash ({first['crash']})"
                if "crash" in first
                else f"{first['dev_p95']:.3f} / {first['dev_max']:.2f}"
            )
        print(f"| {name} | {w}x{h} | " + " | ".join(cells) + " |")


def _median(runs: list[dict[str, float]], key: str) -> str:
    if any("crash" in r for r in runs):
        return f"crash ({runs[0].get('crash', '')})"
    values = [r[key] for r in runs if key in r]
    return f"{statistics.median(values):.3f}" if values else "-"


def _ratio(now: list[dict[str, float]], before: list[dict[str, float]]) -> str:
    if any("crash" in r for r in now + before):
        return "-"
    ratio = statistics.median(a["total"] for a in now) / statistics.median(
        b["total"] for b in before
    )
    return f"{ratio:.2f}"


@contextlib.contextmanager
def _worktree(rev: str) -> Iterator[Path]:
    """A temporary detached worktree of ``rev`` (removed afterwards)."""
    with tempfile.TemporaryDirectory(prefix="bench-against-") as tmp:
        tree = Path(tmp) / "tree"
        subprocess.run(
            ["git", "worktree", "add", "--detach", str(tree), rev],
            cwd=ROOT,
            check=True,
            capture_output=True,
        )
        try:
            yield tree
        finally:
            subprocess.run(
                ["git", "worktree", "remove", "--force", str(tree)], cwd=ROOT, check=False
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
    parser.add_argument(
        "--against",
        metavar="REV",
        help="time the same captures with this commit's tree too (e.g. 59f1066), runs interleaved",
    )
    parser.add_argument(
        "--sizes", nargs="+", default=None, help="timing sizes WIDTHxHEIGHT (default both)"
    )
    parser.add_argument(
        "--in-process",
        type=int,
        default=1,
        metavar="N",
        help="inspect each capture N times in each process and time the last (steady state: a "
        "tree's first inspection of a process may pay for its memory; default 1, the first)",
    )
    parser.add_argument(
        "--bare",
        action="store_true",
        help="each process only imports pipeline.run and calls inspect(): no process policy set "
        "before, no warm-up (a script's or a notebook's call; default: the command line's start-up)",
    )
    parser.add_argument(
        "--cells",
        nargs="+",
        default=None,
        help=f"timing cells (default all: {[c for c, _ in CELLS]})",
    )
    args = parser.parse_args()
    lights = (3, 12, 36) if args.quick else LIGHTS
    seeds = args.seeds[:1] if args.quick else args.seeds
    sizes = [(1224, 1024)] if args.quick else [(1224, 1024), (2448, 2048)]
    if args.sizes:
        sizes = [(int(a), int(b)) for a, b in (v.lower().split("x") for v in args.sizes)]
    with tempfile.TemporaryDirectory() as tmp:
        if args.only != "lights":
            timing_table(
                Path(tmp), sizes, args.repeat, args.against, args.cells, args.in_process, args.bare
            )
        if args.only != "timing":
            lights_table(Path(tmp), seeds, lights)


if __name__ == "__main__":
    main()
