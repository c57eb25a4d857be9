"""The simulated binocular head: the default rig, the rays of its raw pixels, and its sensor's counts."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from ..camera import CameraModel, StereoRig

# Reference head: fx = 900 px at 1224 px width (a 3000 mm plate at 3000 mm fills ~74 % of the width).
_FX_PER_WIDTH_PX = 900.0 / 1224.0
#: Baseline of the head (mm): the right camera's centre lies this far along the left camera's +x.
BASELINE_MM = 800.0
_TOE_IN_DEG = 10.0
#: Fixed-point iterations of cv2.undistortPoints: 10 reach 5e-13 px re-projection error on the default
#: rig's lenses (5: 7e-7 px); a count-only criterion skips the per-point error check (3x faster).
_UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT, 12, 0.0)


def rot_x(a: float) -> np.ndarray:
    """Rotation by ``a`` rad about x."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> np.ndarray:
    """Rotation by ``a`` rad about y."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> np.ndarray:
    """Rotation by ``a`` rad about z."""
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def default_rig(*, width: int = 1224, height: int = 1024) -> StereoRig:
    """The simulated binocular head.

    The left camera is the reference; it looks along +z at a plate ~3000 mm away and covers a
    field of ``width * 3000 / fx`` x ``height * 3000 / fx`` mm there (4080 x 3413 mm at any
    resolution, since ``fx = 900 * width / 1224`` px). The right camera sits 800 mm along +x,
    toed in by 10 deg (plus small residual rotations) so both cameras see the plate.

    Parameters
    ----------
    width, height : int
        Image size in pixels (both cameras), at least 64 each.

    Returns
    -------
    StereoRig
        ``X_right = R @ X_left + T`` (mm), as ``cv2.stereoCalibrate`` gives it. Distortion
        ``k1 k2 p1 p2 k3`` ~ ``(-0.08, 0.05, 4e-4, -3e-4, 0)`` (left), slightly different right.
    """
    if not (isinstance(width, (int, np.integer)) and isinstance(height, (int, np.integer))):
        raise TypeError(
            f"width, height: expected integers, got {type(width).__name__}, {type(height).__name__}"
        )
    if width < 64 or height < 64:
        raise ValueError(f"width, height: expected at least 64 x 64 pixels, got {width} x {height}")
    s = width / 1224.0
    fx = _FX_PER_WIDTH_PX * width
    K_left = np.array(
        [
            [fx, 0.0, (width - 1) / 2 + 3.2 * s],
            [0.0, fx, (height - 1) / 2 - 2.1 * s],
            [0.0, 0.0, 1.0],
        ]
    )
    K_right = np.array(
        [
            [fx * 1.004, 0.0, (width - 1) / 2 - 2.5 * s],
            [0.0, fx * 1.004, (height - 1) / 2 + 1.8 * s],
            [0.0, 0.0, 1.0],
        ]
    )
    left = CameraModel(K_left, np.array([-0.08, 0.05, 4e-4, -3e-4, 0.0]), (width, height))
    right = CameraModel(K_right, np.array([-0.075, 0.045, -3e-4, 2e-4, 0.0]), (width, height))
    # Rows of R are the right camera's axes in the left frame; its optical axis turns towards -x.
    R = rot_x(math.radians(0.25)) @ rot_z(math.radians(-0.15)) @ rot_y(math.radians(_TOE_IN_DEG))
    centre_right = np.array([BASELINE_MM, 0.0, 0.0])
    T = -R @ centre_right
    return StereoRig(left, right, R, T)


def raw_pixel_rays(camera: CameraModel) -> np.ndarray:
    """Rays ``(x, y, 1)`` of the raw (distorted) pixel centres, (H, W, 3) float64, camera frame."""
    w, h = camera.image_size
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pts = np.stack([u, v], axis=-1).reshape(-1, 1, 2)
    xy = cv2.undistortPoints(
        pts, camera.K, camera.dist, None, np.eye(3), np.eye(3), _UNDISTORT_CRITERIA
    )
    rays = np.empty((h, w, 3), dtype=np.float64)
    rays[..., :2] = xy.reshape(h, w, 2)
    rays[..., 2] = 1.0
    return rays


def quantise(frac: np.ndarray, bit_depth: int) -> np.ndarray:
    """Fractions of full scale -> counts, rounded, saturated at 0 and full scale (sensor behaviour)."""
    full = float(2**bit_depth - 1)
    counts = np.clip(np.rint(frac * full), 0.0, full)
    return counts.astype(np.uint8 if bit_depth == 8 else np.uint16)


def write_png(path: Path, image: np.ndarray) -> None:
    """Write an image as PNG; OSError naming the path if OpenCV cannot."""
    if not cv2.imwrite(str(path), image):
        raise OSError(f"{path}: could not write the image")
