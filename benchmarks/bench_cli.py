"""What the command line costs beyond the inspection: ``plate-inspect inspect`` wall time minus the
result's own ``timings_s.total`` (interpreter start-up, imports, the kernels' warm-up, writing and
exiting), for this tree and another commit's, on the same capture, runs interleaved.

Each run is a fresh process running the tree's own console script entry (``python -c 'from
pipeline.cli import run; run()' inspect ...`` here, ``main`` in 59f1066: its pyproject.toml's) in the
tree's own folder, in this environment, after one untimed run per
tree (a fresh worktree compiles its numba kernels into its own cache, as an install does). Prints
every run and the medians; the speed issue's acceptance is the overhead's median at most the older
commit's.

    .venv/bin/python benchmarks/bench_cli.py [--against 59f1066] [--repeat 7] [--size 1224x1024]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import statistics
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path

from bench_pipeline import PLATES, ROOT, _worktree

from pipeline.simulate import CaptureSpec, simulate_capture


def entry(tree: Path) -> str:
    """What the tree's console script ``plate-inspect`` runs (its pyproject.toml's
    ``[project.scripts]``), as a ``python -c`` program: each tree's own command line."""
    scripts = tomllib.loads((tree / "pyproject.toml").read_text())["project"]["scripts"]
    module, function = scripts["plate-inspect"].split(":")
    return f"import sys; from {module} import {function}; sys.exit({function}())"


def _one(tree: Path, bundle: Path, out: Path) -> tuple[float, float]:
    """Wall time of one ``inspect`` process in ``tree`` and its result's ``timings_s.total``."""
    target = str(bundle / "target.json")
    t0 = time.perf_counter()
    done = subprocess.run(
        [
            sys.executable,
            "-c",
            entry(tree),
            "inspect",
            str(bundle),
            "--target",
            target,
            "--out",
            str(out),
        ],
        cwd=tree,
        capture_output=True,
        text=True,
        check=False,
    )
    wall = time.perf_counter() - t0
    if done.returncode != 0:
        raise RuntimeError(f"{tree}: inspect exited {done.returncode}:\n{done.stderr[-2000:]}")
    total = float(json.loads((out / "result.json").read_text())["timings_s"]["total"])
    return wall, total


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--against", default="59f1066", help="the other commit (default 59f1066)")
    parser.add_argument("--repeat", type=int, default=7)
    parser.add_argument("--size", default="1224x1024", help="WIDTHxHEIGHT")
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.lower().split("x"))
    with tempfile.TemporaryDirectory(prefix="bench-cli-") as tmp, contextlib.ExitStack() as stack:
        bundle = simulate_capture(
            Path(tmp) / "bundle",
            plate=PLATES[0][1],
            capture=CaptureSpec(n_lights=12, width=width, height=height),
            seed=7,
        )
        trees = {"now": ROOT, args.against: stack.enter_context(_worktree(args.against))}
        runs: dict[str, list[tuple[float, float]]] = {key: [] for key in trees}
        for key, tree in trees.items():  # a fresh worktree compiles its kernels into its own cache
            _one(tree, bundle, Path(tmp) / f"out-warm-{key}")
        print(f"\n## CLI beyond the inspection, {width}x{height}, 12 lights\n")
        print("| run | tree | wall s | timings_s.total s | wall - total s |")
        print("|---|---|---|---|---|")
        for i in range(args.repeat):
            for key, tree in trees.items():
                wall, total = _one(tree, bundle, Path(tmp) / f"out-{i}-{key}")
                runs[key].append((wall, total))
                print(f"| {i + 1} | {key} | {wall:.2f} | {total:.2f} | {wall - total:.2f} |")
        print("\n| tree | median wall s | median total s | median wall - total s |")
        print("|---|---|---|---|")
        for key, rows in runs.items():
            wall = statistics.median(w for w, _ in rows)
            total = statistics.median(t for _, t in rows)
            over = statistics.median(w - t for w, t in rows)
            print(f"| {key} | {wall:.2f} | {total:.2f} | {over:.2f} |")


if __name__ == "__main__":
    main()
