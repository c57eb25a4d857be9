"""Benchmark of binocular depth: simulated plates at 3 m (depth error, timings, independence of the
working-distance hint) and Middlebury Aloe (bad pixels).

Run: ``.venv/bin/python benchmarks/bench_stereo.py [--sizes 1224 2448] [--seeds 0 1 2]``
Prints tables; no assertions. The depth range passed is what ``pipeline/stages.py`` passes: hint / 2 .. hint * 2,
3500 mm without a hint (the coarse pass searches it all; the fine pass only the plate's span).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the project root, for tests.realdata

from pipeline import simulate
from pipeline.camera import CameraModel, StereoRig
from pipeline.parallel import configure_process
from pipeline.surface.stereo import stereo_depth
from tests.realdata import ALOE

HINTS = (None, 2600.0, 3000.0, 3400.0)


def coarse_range(hint_mm: float | None) -> tuple[float, float]:
    z = 3500.0 if hint_mm is None else hint_mm
    return z / 2.0, z * 2.0


def simulated(sizes: list[int], seeds: list[int]) -> None:
    print(
        "simulated cylinder plate R 5 m, 3 x 3 m at 3 m, default rig (baseline 800 mm, toe-in 10 deg), 16-bit"
    )
    print(
        "depth range: no hint (1750-7000 mm); 'same' = identical depth map for hints 2600/3000/3400 mm and none"
    )
    print(
        f"{'width':>6} {'seed':>4} {'refine':>6} {'search px':>10} {'valid%':>7} {'med err':>8} {'med|err|':>9} "
        f"{'p95|err|':>9} {'coarse':>7} {'rectify':>8} {'match':>6} {'refine':>7} {'resample':>8} {'total s':>8} "
        f"{'same':>5}"
    )
    for width in sizes:
        height = int(round(width * 1024 / 1224))
        rig = simulate.default_rig(width=width, height=height)
        for seed in seeds:
            with tempfile.TemporaryDirectory() as tmp:
                spec = simulate.CaptureSpec(width=width, height=height, n_lights=3)
                simulate.simulate_capture(tmp, capture=spec, seed=seed)
                truth = np.load(Path(tmp) / "truth.npz")
                left = cv2.imread(str(Path(tmp) / "stereo_left.png"), cv2.IMREAD_UNCHANGED)
                right = cv2.imread(str(Path(tmp) / "stereo_right.png"), cv2.IMREAD_UNCHANGED)
            mask, depth_true = truth["mask"], truth["depth_mm"]
            for refine in (True, False):
                runs = []
                for hint in HINTS:
                    z_min, z_max = coarse_range(hint)
                    t0 = time.perf_counter()
                    sd = stereo_depth(
                        left, right, rig, z_min_mm=z_min, z_max_mm=z_max, mask=mask, refine=refine
                    )
                    runs.append((sd, time.perf_counter() - t0))
                same = all(
                    np.array_equal(sd.depth_mm, runs[0][0].depth_mm, equal_nan=True)
                    for sd, _ in runs[1:]
                )
                # timings: the fastest of the runs (the machine is shared; all runs do the same work)
                sd, total = min(runs, key=lambda r: r[1])
                err = (sd.depth_mm - depth_true)[sd.valid]
                t = sd.timings
                lo, hi = sd.search_disparity_px
                print(
                    f"{width:>6} {seed:>4} {refine!s:>6} {f'{lo}..{hi}':>10} {100 * sd.valid.sum() / mask.sum():>7.2f} "
                    f"{np.median(err):>8.3f} {np.median(np.abs(err)):>9.3f} {np.percentile(np.abs(err), 95):>9.2f} "
                    f"{t['coarse']:>7.3f} {t['rectify']:>8.3f} {t['match']:>6.3f} {t['refine']:>7.3f} "
                    f"{t['resample']:>8.3f} {total:>8.3f} {same!s:>5}"
                )


def aloe() -> None:
    if not ALOE.is_dir():
        print(f"Middlebury Aloe not found at {ALOE}")
        return
    left = cv2.imread(str(ALOE / "aloeL.jpg"))
    right = cv2.imread(str(ALOE / "aloeR.jpg"))
    gt = cv2.imread(str(ALOE / "aloeGT.png"), cv2.IMREAD_GRAYSCALE).astype(np.float32)
    h, w = gt.shape
    f, baseline = 1000.0, 100.0  # nominal: the pair is rectified; only disparities are compared
    cam = CameraModel(np.array([[f, 0, 0], [0, f, 0], [0, 0, 1.0]]), np.zeros(5), (w, h))
    rig = StereoRig(cam, cam, np.eye(3), np.array([-baseline, 0.0, 0.0]))
    known = gt > 0
    d_lo, d_hi = gt[known].min(), gt[known].max()
    print(
        f"\nMiddlebury Aloe {w}x{h}, GT disparity {d_lo:.0f}..{d_hi:.0f} px, {known.sum()} known pixels"
    )
    print(
        f"{'refine':>6} {'matched% of known':>18} {'bad>1px % of matched':>21} {'bad>1px % (holes bad)':>22} "
        f"{'bad>0.5px %':>12} {'med|err| px':>12} {'time s':>7}"
    )
    for refine in (False, True):
        t0 = time.perf_counter()
        sd = stereo_depth(
            left,
            right,
            rig,
            z_min_mm=f * baseline / (d_hi + 2),
            z_max_mm=f * baseline / (d_lo - 2),
            refine=refine,
        )
        total = time.perf_counter() - t0
        x0, y0 = sd.disparity_origin_px
        disp = np.full((h, w), np.nan, np.float32)
        hh, ww = sd.disparity_px.shape
        ys, xs = slice(max(0, y0), min(h, y0 + hh)), slice(max(0, x0), min(w, x0 + ww))
        disp[ys, xs] = sd.disparity_px[ys.start - y0 : ys.stop - y0, xs.start - x0 : xs.stop - x0]
        ok = known & np.isfinite(disp)
        err = np.abs(disp - gt)
        print(
            f"{refine!s:>6} {100 * ok.sum() / known.sum():>18.1f} {100 * np.mean(err[ok] > 1):>21.2f} "
            f"{100 * np.mean(~(err[known] <= 1)):>22.2f} {100 * np.mean(err[ok] > 0.5):>12.2f} "
            f"{np.median(err[ok]):>12.3f} {total:>7.2f}"
        )


def main() -> None:
    configure_process()  # the thread policy of the CLI's process, so that timings compare
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--sizes", type=int, nargs="+", default=[1224, 2448])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    args = parser.parse_args()
    # the machine is shared: timings scale with the load (SGBM's tight range is 0.25 s at 2448x2048 when idle)
    print("load average (1, 5, 15 min): " + ", ".join(f"{x:.1f}" for x in os.getloadavg()))
    simulated(args.sizes, args.seeds)
    aloe()


if __name__ == "__main__":
    main()
