"""The speed of a plate measured at stations (issue 29, docs/stations.md): a 9 m plate at 4 stations
(1224x1024, the simulated cell, seed 1 of bench_stations.py) against one of its stations inspected
alone, and the time from the last frame to the verdict of an acquired plate.

- **in-process**: after ``warm_up()``, the 4-station inspection and the one-station inspection
  alternate ``--repeat`` times; the median of each and the ratio of the medians.
- **CLI**: ``plate-inspect inspect`` in a fresh process each (alternating, ``--repeat`` pairs): the
  median ``timings_s.total`` of each (the process's own start and warm-up not counted, as
  ``timings_s`` never counts them) and of the processes' wall time, and their ratios.
- **acquire**: the demo cell's simulated conveyor at 4 stations (1224x1024), acquired, then
  inspected; alternately with the stations reconstructed as they arrive
  (:class:`pipeline.run.EarlyStations` fed by ``station_done``, as ``plate-inspect acquire
  --target --result`` and the service do) and only after the acquisition. Prints the medians of
  ``after_last_frame`` (seconds from the last frame's arrival to result.json, as the service reports
  it) and of the acquisition's own time. The simulated cameras render the plate on the CPU, the
  early reconstruction's competitor for the 2 cores; a real cell mostly waits on its conveyor
  and cameras.

The machine's load average is printed before and after: timings on a shared machine are noisy.

    .venv/bin/python benchmarks/bench_stations_speed.py [--repeat 5] [--no-cli] [--no-acquire]
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

from pipeline.acquisition import acquire_stations, last_frame_lag_s, write_demo_cell
from pipeline.parallel import configure_process
from pipeline.run import inspect, warm_up
from pipeline.simulate import CaptureSpec, PlateSpec, simulate_stations

LENGTH_MM, STATIONS, SEED = 9000.0, 4, 1
#: As benchmarks/bench_stations.py: both ends of the plate in view with ~150 mm to spare.
SPACING_MM = (LENGTH_MM - 3300.0 + 300.0) / (STATIONS - 1)


def _load() -> str:
    one, five, _ = os.getloadavg()
    return f"load average {one:.2f} (1 min), {five:.2f} (5 min), {os.cpu_count()} CPUs"


def _plate(root: Path) -> tuple[list[Path], Path]:
    bundles = simulate_stations(
        root / "in",
        n_stations=STATIONS,
        spacing_mm=SPACING_MM,
        plate=PlateSpec(size_mm=(3000.0, LENGTH_MM)),
        capture=CaptureSpec(width=1224, height=1024),
        seed=SEED,
    )
    return bundles, root / "in" / "target.json"


def _ratio(name: str, four: list[float], one: list[float]) -> None:
    a, b = statistics.median(four), statistics.median(one)
    print(
        f"{name}: 4 stations {a:.2f} s (runs {', '.join(f'{t:.2f}' for t in four)}), one station "
        f"{b:.2f} s (runs {', '.join(f'{t:.2f}' for t in one)}): ratio of medians {a / b:.2f}"
    )


def in_process(bundles: list[Path], target: Path, root: Path, repeat: int) -> None:
    four, one = [], []
    for _ in range(repeat):
        t = time.perf_counter()
        inspect(bundles, target, out_dir=root / "four")
        four.append(time.perf_counter() - t)
        t = time.perf_counter()
        inspect(bundles[1], target, out_dir=root / "one")
        one.append(time.perf_counter() - t)
    _ratio("in-process", four, one)


def cli(bundles: list[Path], target: Path, root: Path, repeat: int) -> None:
    totals: dict[str, list[float]] = {"four": [], "one": []}
    walls: dict[str, list[float]] = {"four": [], "one": []}
    for _ in range(repeat):
        for name, given in (("four", bundles), ("one", bundles[1:2])):
            out = root / f"cli-{name}"
            argv = [sys.executable, "-m", "pipeline.cli", "inspect", *map(str, given)]
            t = time.perf_counter()
            subprocess.run(
                [*argv, "--target", str(target), "--out", str(out)],
                check=True,
                stdout=subprocess.DEVNULL,
            )
            walls[name].append(time.perf_counter() - t)
            doc = json.loads((out / "result.json").read_text())
            totals[name].append(doc["timings_s"]["total"])
    _ratio("CLI timings_s.total", totals["four"], totals["one"])
    _ratio("CLI process wall time", walls["four"], walls["one"])


def acquired(root: Path, repeat: int) -> None:
    from pipeline.run import EarlyStations

    cell = write_demo_cell(root / "cell", width=1224, height=1024, stations=STATIONS)
    target = root / "cell" / "target.json"
    after: dict[str, list[float]] = {"as they arrive": [], "after the acquisition": []}
    took: dict[str, list[float]] = {"as they arrive": [], "after the acquisition": []}
    for i in range(repeat):
        for name in after:
            stations = root / f"acq-{i}-{name[:5]}"
            t0 = time.monotonic()
            with EarlyStations(target, stations) as early:
                hook = early.station_done if name == "as they arrive" else None
                bundles = acquire_stations(cell, f"BENCH-{i}", stations, station_done=hook)
                returned = time.monotonic()
                inspect(
                    bundles,
                    target,
                    out_dir=stations.with_name(stations.name + "-out"),
                    early=early if hook else None,
                )
            tail = last_frame_lag_s(bundles[-1]) or 0.0
            after[name].append(time.monotonic() - returned + tail)
            took[name].append(returned - t0)
    for name in after:
        print(
            f"acquired, reconstructed {name}: after the last frame {statistics.median(after[name]):.2f} s "
            f"(runs {', '.join(f'{t:.2f}' for t in after[name])}); acquisition "
            f"{statistics.median(took[name]):.2f} s"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--no-cli", action="store_true")
    parser.add_argument("--no-acquire", action="store_true")
    args = parser.parse_args()
    configure_process()
    warm_up()
    print(_load())
    with tempfile.TemporaryDirectory(prefix="bench-stations-speed-") as tmp:
        root = Path(tmp)
        bundles, target = _plate(root)
        print(
            f"a {LENGTH_MM / 1000:g} m plate at {STATIONS} stations, 1224x1024, against station 1 alone"
        )
        in_process(bundles, target, root, args.repeat)
        if not args.no_cli:
            cli(bundles, target, root, args.repeat)
        if not args.no_acquire:
            acquired(root, args.repeat)
    print(_load())


if __name__ == "__main__":
    main()
