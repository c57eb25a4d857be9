"""Load-time benchmark of capture bundles (folder and zip) at full camera size.

Run: .venv/bin/python benchmarks/bench_io.py [--width 2448 --height 2048 --lights 12]
Prints a table: bundle kind, threads, seconds (best of 3).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
import zipfile
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "pipeline"))
from bundles import write_bundle, zip_folder

from pipeline.io import load_capture
from pipeline.parallel import configure_process


def main() -> None:
    configure_process()  # the thread policy of the CLI's process, so that timings compare
    ap = argparse.ArgumentParser()
    ap.add_argument("--width", type=int, default=2448)
    ap.add_argument("--height", type=int, default=2048)
    ap.add_argument("--lights", type=int, default=12)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        t0 = time.perf_counter()
        folder = write_bundle(
            tmp,
            n_lights=args.lights,
            width=args.width,
            height=args.height,
            with_dark=False,
            with_stereo=False,
        )
        stored = tmp / "stored.zip"
        with zipfile.ZipFile(stored, "w", compression=zipfile.ZIP_STORED) as zf:
            for f in sorted(folder.iterdir()):
                zf.write(f, f.name)
        deflated = zip_folder(folder, tmp / "deflated.zip")
        print(
            f"wrote {args.lights} x {args.width}x{args.height} 16-bit PNGs in {time.perf_counter() - t0:.1f} s "
            f"({sum(f.stat().st_size for f in folder.iterdir()) / 1e6:.0f} MB)"
        )

        # The floor: plain cv2.imread of the same files, one thread.
        pngs = sorted(folder.glob("ps_*.png"))
        best = min(
            _timed(lambda: [cv2.imread(str(p), cv2.IMREAD_UNCHANGED) for p in pngs])
            for _ in range(args.repeat)
        )
        print(f"{'bundle':<14}{'threads':>8}{'seconds':>10}")
        print(f"{'cv2.imread':<14}{1:>8}{best:>10.3f}")
        for kind, path in (("folder", folder), ("zip stored", stored), ("zip deflated", deflated)):
            for workers in (1, 2):
                best = min(
                    _timed(lambda: load_capture(path, workers=workers)) for _ in range(args.repeat)
                )
                print(f"{kind:<14}{workers:>8}{best:>10.3f}")
        cap = load_capture(folder)
        print(f"images {cap.images.shape} {cap.images.dtype}, max {float(np.max(cap.images)):.0f}")


def _timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


if __name__ == "__main__":
    main()
