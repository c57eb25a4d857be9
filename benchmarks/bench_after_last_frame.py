"""From the last frame to the verdict: an acquisition on the simulated demo cell, then its inspection.

Prints per run the acquisition's own time, the inspection's ``timings_s.total``, its verdict and
deviation (the demo cell's plate is formed exactly: the right verdict is pass) and
``after_last_frame``: the seconds from the last frame's arrival (the acquisition record's last
frame time) to ``result.json`` written, as the service's acquire job reports it. As in the job, the
inspection starts when the bundle is written and takes the frames from memory, each folded as it
arrived (:mod:`pipeline.acquisition.streaming`; ``--unfolded``: kept only; ``--decode``: reads the written files
again, as before frames were handed over).

    .venv/bin/python benchmarks/bench_after_last_frame.py [--size 2448x2048] [--lights 12] [--repeat 3] [--decode] [--unfolded]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from pipeline.acquisition import StreamedFrames, acquire, last_frame_time, write_demo_cell
from pipeline.parallel import configure_process
from pipeline.run import inspect, warm_up


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--size", default="2448x2048")
    parser.add_argument("--lights", type=int, default=12)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--decode", action="store_true", help="decode the written files again")
    parser.add_argument(
        "--unfolded",
        action="store_true",
        help="frames kept in memory only, not folded as they arrive (as before pipeline.acquisition.streaming)",
    )
    args = parser.parse_args()
    configure_process()
    warm_up()
    width, height = (int(v) for v in args.size.lower().split("x"))
    print(f"\n## After the last frame, demo cell {width}x{height}, {args.lights} LEDs\n")
    print(
        "| run | acquire s | inspect total s | after last frame s | verdict | radius error % | deviation RMS / max mm |"
    )
    print("|---|---|---|---|---|---|---|")
    afters = []
    with tempfile.TemporaryDirectory() as tmp:
        cell = write_demo_cell(Path(tmp) / "cell", n_lights=args.lights, width=width, height=height)
        for i in range(args.repeat):
            t0 = time.monotonic()
            frames: dict[str, np.ndarray] = {} if args.unfolded else StreamedFrames.for_cell(cell)
            bundle = acquire(
                cell, plate_id=f"BENCH-{i}", out_dir=Path(tmp) / f"bundle{i}", frames=frames
            )
            returned = time.monotonic()
            last_frame_at = last_frame_time(bundle, returned) or returned
            doc = inspect(
                bundle,
                cell.parent / "target.json",
                out_dir=Path(tmp) / f"out{i}",
                frames=None if args.decode else frames,
            ).document
            after = time.monotonic() - last_frame_at
            afters.append(after)
            dev = doc["deviation_mm"]
            print(
                f"| {i + 1} | {returned - t0:.2f} | {doc['timings_s']['total']:.2f} | {after:.2f} | "
                f"{doc['verdict']} | {doc['radius_error_pct']:+.3f} | {dev['rms']:.2f} / {dev['max_abs']:.2f} |"
            )
    print(f"\nmedian after the last frame: {statistics.median(afters):.2f} s")


if __name__ == "__main__":
    main()
