"""From the last frame to the verdict: an acquisition on the simulated demo cell, then its inspection.

Prints per run the acquisition's own time, the inspection's ``timings_s.total`` and
``after_last_frame``: the seconds from the last frame's arrival (the acquisition record's last
frame time) to ``result.json`` written, as the service's acquire job reports it. The inspection
here starts when the bundle is written (no streaming of frames into the pipeline yet).

    .venv/bin/python benchmarks/bench_after_last_frame.py [--size 2448x2048] [--lights 12] [--repeat 3]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

from pipeline.acquisition import acquire, last_frame_lag_s, write_demo_cell
from pipeline.parallel import configure_process
from pipeline.run import inspect, warm_up


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--size", default="2448x2048")
    parser.add_argument("--lights", type=int, default=12)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    configure_process()
    warm_up()
    width, height = (int(v) for v in args.size.lower().split("x"))
    print(f"\n## After the last frame, demo cell {width}x{height}, {args.lights} LEDs\n")
    print("| run | acquire s | inspect total s | after last frame s |")
    print("|---|---|---|---|")
    afters = []
    with tempfile.TemporaryDirectory() as tmp:
        cell = write_demo_cell(Path(tmp) / "cell", n_lights=args.lights, width=width, height=height)
        for i in range(args.repeat):
            t0 = time.monotonic()
            bundle = acquire(cell, plate_id=f"BENCH-{i}", out_dir=Path(tmp) / f"bundle{i}")
            returned = time.monotonic()
            tail = last_frame_lag_s(bundle) or 0.0
            doc = inspect(
                bundle, cell.parent / "target.json", out_dir=Path(tmp) / f"out{i}"
            ).document
            after = time.monotonic() - returned + tail
            afters.append(after)
            print(
                f"| {i + 1} | {returned - t0:.2f} | {doc['timings_s']['total']:.2f} | {after:.2f} |"
            )
    print(f"\nmedian after the last frame: {statistics.median(afters):.2f} s")


if __name__ == "__main__":
    main()
