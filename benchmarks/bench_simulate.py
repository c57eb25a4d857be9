"""Simulator timings and truth checks at full size.

Run: ``.venv/bin/python benchmarks/bench_simulate.py [--sizes 1224x1024 2448x2048] [--boards]``

Prints one row per size: render time of a capture bundle (12 lights + stereo pair + truth),
the median / p95 angular error of plain least-squares normals recovered from the rendered
images (dark-subtracted, undistorted, divided by e_k; plate interior, no grazing light), the
left/right texture correlation at truth correspondences, and optionally the board-pair time.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
from scipy.ndimage import map_coordinates

from pipeline.io import load_capture
from pipeline.parallel import configure_process
from pipeline.simulate import (
    CaptureSpec,
    Dent,
    PlateSpec,
    default_rig,
    render_calibration_pairs,
    simulate_capture,
)


def _angles_deg(a, b):
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1)))


def _check(bundle: Path, rig) -> tuple[float, float, float]:
    cap = load_capture(bundle)
    with np.load(bundle / "truth.npz") as z:
        normals, mask, depth = z["normals"], z["mask"], z["depth_mm"]
    h, w = mask.shape
    imgs = cap.images - cap.dark[None]
    und = (
        np.stack([rig.left.undistort_image(im) for im in imgs]) / cap.light_intensity[:, None, None]
    )
    b, *_ = np.linalg.lstsq(cap.light_dirs, und.reshape(len(imgs), -1), rcond=None)
    n = b.T.reshape(h, w, 3)
    inner = cv2.erode(mask.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    ndotl = np.einsum("hwc,kc->hwk", np.nan_to_num(normals), cap.light_dirs)
    valid = inner & np.all(ndotl > 0.05, axis=-1)
    err = _angles_deg(n[valid], normals[valid])

    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(rig.left.K).T
    pts = (depth[..., None] * rays)[inner][::7]
    uvl = rig.left.project(pts)
    uvr = rig.right.project(pts @ rig.R.T + rig.T)
    left = map_coordinates(cap.stereo_left.astype(np.float64), [uvl[:, 1], uvl[:, 0]], order=1)
    right = map_coordinates(cap.stereo_right.astype(np.float64), [uvr[:, 1], uvr[:, 0]], order=1)
    return (
        float(np.median(err)),
        float(np.percentile(err, 95)),
        float(np.corrcoef(left, right)[0, 1]),
    )


def main() -> None:
    configure_process()  # the thread policy of the CLI's process, so that timings compare
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="+", default=["1224x1024", "2448x2048"])
    parser.add_argument(
        "--boards", action="store_true", help="also time 12 calibration pairs per size"
    )
    parser.add_argument("--keep", type=Path, default=None, help="write bundles under this folder")
    args = parser.parse_args()

    plates = {
        "cylinder R5000": PlateSpec(),
        "sphere R8000 concave + dents": PlateSpec(
            shape="sphere",
            radius_mm=8000.0,
            convex=False,
            in_plane_deg=20.0,
            dents=(Dent(400.0, -300.0, 250.0, 6.0), Dent(-600.0, 500.0, 180.0, -4.0)),
        ),
        "saddle R6000/9000": PlateSpec(shape="saddle", radius_mm=6000.0, radius2_mm=9000.0),
    }
    print(
        f"{'size':>10} {'plate':<30} {'render s':>9} {'median deg':>11} {'p95 deg':>8} {'L/R corr':>9} {'boards s':>9}"
    )
    with tempfile.TemporaryDirectory() as tmp:
        root = args.keep or Path(tmp)
        for size in args.sizes:
            w, h = (int(v) for v in size.lower().split("x"))
            rig = default_rig(width=w, height=h)
            board_s = ""
            if args.boards:
                t0 = time.perf_counter()
                render_calibration_pairs(root / f"boards_{size}", rig=rig, n_pairs=12)
                board_s = f"{time.perf_counter() - t0:9.2f}"
            for name, plate in plates.items():
                out = root / f"{size}_{name.split()[0]}"
                t0 = time.perf_counter()
                simulate_capture(out, plate=plate, capture=CaptureSpec(width=w, height=h), seed=11)
                render_s = time.perf_counter() - t0
                med, p95, corr = _check(out, rig)
                print(
                    f"{size:>10} {name:<30} {render_s:9.2f} {med:11.3f} {p95:8.3f} {corr:9.4f} {board_s:>9}"
                )
                board_s = ""


if __name__ == "__main__":
    main()
