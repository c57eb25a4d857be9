"""Binocular depth: simulated plates at 3 m against the simulator's truth, Middlebury Aloe, bad input."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.camera import CameraModel, StereoRig
from pipeline.stereo import StereoDepth, stereo_depth

DATA = Path(__file__).resolve().parents[2] / ".." / "shared" / "data"
ALOE = DATA / "middlebury_aloe"

simulate = pytest.importorskip("pipeline.simulate", reason="pipeline/simulate.py (the simulator) is not there yet")


def _capture(tmp_path: Path, *, width: int, seed: int, plate=None):
    height = int(round(width * 1024 / 1224))
    spec = simulate.CaptureSpec(width=width, height=height, n_lights=3)
    kwargs = {} if plate is None else {"plate": plate}
    simulate.simulate_capture(tmp_path, capture=spec, seed=seed, **kwargs)
    truth = np.load(tmp_path / "truth.npz")
    left = cv2.imread(str(tmp_path / "stereo_left.png"), cv2.IMREAD_UNCHANGED)
    right = cv2.imread(str(tmp_path / "stereo_right.png"), cv2.IMREAD_UNCHANGED)
    return simulate.default_rig(width=width, height=height), left, right, truth["depth_mm"], truth["mask"]


@pytest.fixture(scope="module")
def plate_3m(tmp_path_factory):
    # the simulator's default cell: cylinder R 5 m, 3 x 3 m plate at 3 m, 16-bit, 1224 x 1024, fx 900 px,
    # baseline 800 mm toed in 10 deg; 1 mm of depth at 3 m is 0.08 px of disparity here
    return _capture(tmp_path_factory.mktemp("plate3m"), width=1224, seed=3)


def test_plate_at_3m_median_depth_error_within_1mm(plate_3m):
    rig, left, right, depth_true, mask = plate_3m
    sd = stereo_depth(left, right, rig, z_min_mm=2500.0, z_max_mm=3500.0, mask=mask)
    assert isinstance(sd, StereoDepth)
    assert sd.depth_mm.shape == mask.shape and sd.depth_mm.dtype == np.float32
    np.testing.assert_array_equal(sd.valid, np.isfinite(sd.depth_mm))
    assert not np.any(sd.valid & ~mask)  # nothing outside the plate
    err = (sd.depth_mm - depth_true)[sd.valid]
    # issue 4: median depth error <= 1 mm over the plate (measured 0.63-0.67 mm over seeds 0-3; the absolute
    # error, not only the signed median, which is ~0.01 mm after the sub-pixel refinement)
    assert np.median(np.abs(err)) <= 1.0
    assert abs(np.median(err)) <= 0.3
    # holes: only the plate's rim (blocks straddling its edge) and a few rejected matches (measured ~1.5 %)
    assert sd.valid.sum() >= 0.95 * mask.sum()
    # no wild matches kept: 99.9 % of the valid pixels within 10 mm (0.8 px of disparity)
    assert np.mean(np.abs(err) <= 10.0) >= 0.999


def test_without_refinement_sgbm_alone_is_coarser(plate_3m):
    rig, left, right, depth_true, mask = plate_3m
    sd = stereo_depth(left, right, rig, z_min_mm=2500.0, z_max_mm=3500.0, mask=mask, refine=False)
    err = (sd.depth_mm - depth_true)[sd.valid]
    # SGBM's own 1/16 px parabola: ~1.3 mm median error here (pixel locking); kept as a diagnostic option
    assert 0.8 < np.median(np.abs(err)) < 3.0


def test_holes_are_not_invented(tmp_path):
    rig, left, right, depth_true, mask = _capture(tmp_path, width=612, seed=5)
    # wipe the texture from a band of the right image: the plate seen there cannot be matched
    blank = right.copy()
    blank[:, 250:330] = int(np.median(right[mask]))
    sd = stereo_depth(left, blank, rig, z_min_mm=2500.0, z_max_mm=3500.0, mask=mask)
    ok = sd.valid
    err = np.abs(sd.depth_mm - depth_true)
    # depths kept are real measurements: fx 450 px -> 1 px of disparity is ~25 mm at 3 m. SGM's smoothness
    # term propagates disparities into the blank band and the ZNCC check rejects most of them: measured 99.6 %
    # within 25 mm (99.2 % without the check); the few left sit at the band's borders where half a window is textured
    assert np.mean(err[ok] <= 25.0) >= 0.99
    # and there are holes where the right camera saw no texture (a band ~80 px wide of 612)
    assert ok.sum() <= 0.95 * mask.sum()


def test_eight_bit_and_float_inputs_agree(tmp_path):
    rig, left, right, depth_true, mask = _capture(tmp_path, width=612, seed=6)
    a = stereo_depth(left, right, rig, z_min_mm=2500.0, z_max_mm=3500.0, mask=mask)
    b = stereo_depth(left.astype(np.float32) * 3.0 + 100.0, right.astype(np.float32) * 3.0 + 100.0, rig,
                     z_min_mm=2500.0, z_max_mm=3500.0, mask=mask)
    # the percentile scaling removes gain and offset: identical input up to float rounding
    both = a.valid & b.valid
    assert both.sum() >= 0.99 * a.valid.sum()
    assert np.median(np.abs(a.depth_mm[both] - b.depth_mm[both])) < 0.05


# --------------------------------------------------------------------------- real data


def test_middlebury_aloe_bad_pixel_share():
    if not ALOE.is_dir():
        pytest.skip(f"Middlebury Aloe not found at {ALOE}")
    left = cv2.imread(str(ALOE / "aloeL.jpg"))
    right = cv2.imread(str(ALOE / "aloeR.jpg"))
    gt = cv2.imread(str(ALOE / "aloeGT.png"), cv2.IMREAD_GRAYSCALE).astype(np.float32)
    # half resolution keeps the test quick (the benchmark runs the full size); GT halved, 0 = unknown kept
    left = cv2.resize(left, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    right = cv2.resize(right, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    gt = cv2.resize(gt, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_NEAREST) / 2.0
    h, w = gt.shape
    # already rectified: an ideal rig with the principal point at pixel (0, 0) makes the rectified grid the image grid
    f, baseline = 1000.0, 100.0
    cam = CameraModel(np.array([[f, 0, 0], [0, f, 0], [0, 0, 1.0]]), np.zeros(5), (w, h))
    rig = StereoRig(cam, cam, np.eye(3), np.array([-baseline, 0.0, 0.0]))
    known = gt > 0
    d_lo, d_hi = gt[known].min(), gt[known].max()
    sd = stereo_depth(left, right, rig, z_min_mm=f * baseline / (d_hi + 2), z_max_mm=f * baseline / (d_lo - 2), refine=False)
    x0, y0 = sd.disparity_origin_px
    disp = np.full((h, w), np.nan, np.float32)
    hh, ww = sd.disparity_px.shape
    ys, xs = slice(max(0, y0), min(h, y0 + hh)), slice(max(0, x0), min(w, x0 + ww))
    disp[ys, xs] = sd.disparity_px[ys.start - y0 : ys.stop - y0, xs.start - x0 : xs.stop - x0]
    ok = known & np.isfinite(disp)
    bad = np.abs(disp - gt)[ok] > 1.0
    # measured: 4.6 % of the matched pixels off by > 1 px, 86 % of the known pixels matched (the rest are holes:
    # occlusions, the left border, rejected matches). SGBM on Middlebury 2006 typically has 5-15 % bad pixels;
    # the bounds leave room for JPEG/OpenCV-version differences but catch a broken geometry (shift, sign, scale)
    assert bad.mean() < 0.08
    assert ok.sum() / known.sum() > 0.75


# --------------------------------------------------------------------------- bad input


def _small_rig(width=160, height=128, T=(-800.0, 0.0, 0.0)):
    cam = CameraModel(np.array([[150.0, 0, 80], [0, 150.0, 64], [0, 0, 1]]), np.zeros(5), (width, height))
    return StereoRig(cam, cam, np.eye(3), np.array(T))


@pytest.mark.parametrize(
    "change, exc, match",
    [
        ({"left_raw": np.zeros((100, 160))}, ValueError, r"left_raw: expected shape \(128, 160\) to match"),
        ({"right_raw": np.zeros((128, 160, 2))}, ValueError, r"right_raw: expected an \(H, W\) or \(H, W, 3\) image"),
        ({"left_raw": np.full((128, 160), np.nan)}, ValueError, r"left_raw: expected finite pixel values"),
        ({"z_min_mm": 3000.0, "z_max_mm": 2000.0}, ValueError, r"expected 0 < z_min_mm < z_max_mm"),
        ({"z_min_mm": -1.0}, ValueError, r"expected 0 < z_min_mm < z_max_mm"),
        ({"mask": np.ones((128, 160), np.uint8)}, ValueError, r"mask: expected a \(128, 160\) bool array"),
        ({"mask": np.zeros((128, 160), bool)}, ValueError, r"mask: expected at least one True pixel"),
        ({"rig": _small_rig(T=(0.0, -800.0, 0.0))}, ValueError, r"rig.T: expected a horizontal baseline"),
        ({"rig": "calibration.json"}, TypeError, r"rig: expected a StereoRig"),
    ],
)
def test_bad_input_is_refused(change, exc, match):
    args = {
        "left_raw": np.zeros((128, 160), np.uint8),
        "right_raw": np.zeros((128, 160), np.uint8),
        "rig": _small_rig(),
        "z_min_mm": 2000.0,
        "z_max_mm": 4000.0,
    }
    args.update(change)
    left, right, rig = args.pop("left_raw"), args.pop("right_raw"), args.pop("rig")
    with pytest.raises(exc, match=match):
        stereo_depth(left, right, rig, **args)
