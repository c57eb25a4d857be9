"""Checkerboard pairs of the simulated head, for the stereo calibration (Zhang 2000).

Each pair shows one board pose in both cameras, fully inside both images, rendered through each
camera's K and distortion (raw pixels undistorted to rays, intersected with the board plane, the
checker box-filtered over the pixel footprint), then Gaussian blur, additive Gaussian noise and 8-bit
quantisation.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from ..camera import StereoRig
from .rig import default_rig, quantise, raw_pixel_rays, rot_x, rot_y, rot_z, write_png
from .texture import smooth_noise

#: Calibration boards are seen within 50 deg of head-on by both cameras.
_BOARD_MIN_COS = math.cos(math.radians(50.0))


def _board_pose(
    rng: np.random.Generator, distance_mm: tuple[float, float]
) -> tuple[np.ndarray, np.ndarray]:
    """A random board pose: R_cam_board (3, 3), centre t (3,) mm, board facing the camera."""
    rx, ry = rng.uniform(-np.radians(35), np.radians(35), 2)
    rz = rng.uniform(-np.radians(12), np.radians(12))
    R = rot_x(rx) @ rot_y(ry) @ rot_z(rz)
    z = rng.uniform(*distance_mm)
    xn, yn = rng.uniform(-0.45, 0.45), rng.uniform(-0.35, 0.35)
    return R, np.array([xn * z, yn * z, z])


def _board_view(
    rays: np.ndarray,
    R_cb: np.ndarray,
    t_cb: np.ndarray,
    squares: tuple[int, int],
    square_mm: float,
    margin_sq: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """Grey image (H, W) float32 in [0, 1] of an area-antialiased board; ``t_cb`` = board centre."""
    h, w = rays.shape[:2]
    nb = R_cb[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (nb @ t_cb) / (rays @ nb)
    pts = s[..., None] * rays - t_cb
    q = pts @ R_cb  # board frame, mm, origin at the board centre
    a = q[..., 0] / square_mm + squares[0] / 2  # squares, 0 .. n_cols along the board
    b = q[..., 1] / square_mm + squares[1] / 2
    front = np.isfinite(s) & (s > 0)
    a = np.where(front, a, -1e3)
    b = np.where(front, b, -1e3)
    # Pixel footprint in squares (box filter width) from the local derivatives.
    wa = np.abs(np.gradient(a, axis=1)) + np.abs(np.gradient(a, axis=0))
    wb = np.abs(np.gradient(b, axis=1)) + np.abs(np.gradient(b, axis=0))
    wa = np.clip(wa, 1e-3, None)
    wb = np.clip(wb, 1e-3, None)

    def box_square_wave(x: np.ndarray, width: np.ndarray) -> np.ndarray:
        d = np.arcsin(np.sin(np.pi * x)) / np.pi  # signed distance to the nearest edge, squares
        wave: np.ndarray = np.clip(2.0 * d / width, -1.0, 1.0)
        return wave

    def box_inside(x: np.ndarray, lo: float, hi: float, width: np.ndarray) -> np.ndarray:
        inside: np.ndarray = np.clip(0.5 + np.minimum(x - lo, hi - x) / width, 0.0, 1.0)
        return inside

    checker = box_square_wave(a, wa) * box_square_wave(b, wb)
    black, white = 0.08, 0.85
    grid_val = 0.5 * (black + white) - 0.5 * (white - black) * checker
    in_grid = box_inside(a, 0, squares[0], wa) * box_inside(b, 0, squares[1], wb)
    in_board = box_inside(a, -margin_sq, squares[0] + margin_sq, wa) * box_inside(
        b, -margin_sq, squares[1] + margin_sq, wb
    )
    background = 0.3 + 0.08 * smooth_noise(rng, (h, w), 5)
    board = in_grid * grid_val + (1.0 - in_grid) * white
    img = in_board * board + (1.0 - in_board) * background
    # Uneven illumination: brighter in the middle of the image.
    yy, xx = np.mgrid[0:h, 0:w]
    r2 = ((xx - w / 2) / (w / 2)) ** 2 + ((yy - h / 2) / (h / 2)) ** 2
    shaded: np.ndarray = (img * (1.0 - 0.12 * r2)).astype(np.float32)
    return shaded


def render_calibration_pairs(
    out_dir: str | Path,
    *,
    rig: StereoRig | None = None,
    n_pairs: int = 12,
    inner_corners: tuple[int, int] = (9, 6),
    square_mm: float = 100.0,
    seed: int = 0,
    blur_px: float = 0.7,
    noise: float = 0.01,
) -> list[Path]:
    """Render checkerboard pairs of the binocular head for calibration (Zhang 2000; see the module docstring).

    Parameters
    ----------
    out_dir : str or Path
        Created if missing.
    rig : StereoRig or None
        None: :func:`default_rig` (1224 x 1024).
    n_pairs : int
        Number of pairs, >= 1.
    inner_corners : (int, int)
        Inner corners (columns, rows) as ``cv2.findChessboardCorners`` counts them.
    square_mm : float
        Side of one square, mm. The board has a white border of 0.6 square around the squares.
    seed : int
    blur_px : float
        Std of the Gaussian blur (optics), pixels; 0 for none.
    noise : float
        Std of the sensor noise, fraction of full scale (255).

    Returns
    -------
    list of Path
        ``[left01.png, right01.png, left02.png, right02.png, ...]`` in ``out_dir`` (names as
        ``plate-inspect calibrate`` expects). ``out_dir/board_truth.npz`` holds the true poses:
        ``R_cam_board`` (P, 3, 3), ``t_cam_board`` (P, 3) mm (left frame; board frame origin at the
        board centre, x along the columns), ``object_points`` (C, 3) mm of the inner corners in
        the board frame in ``findChessboardCorners`` row-major order up to the board's symmetry.

    Raises
    ------
    ValueError
        Bad options, or no pose fitting both images found (board too large for the field).
    """
    rig = _check_arguments(rig, n_pairs, inner_corners, square_mm, blur_px, noise)
    cols, rows = (int(v) for v in inner_corners)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    squares = (cols + 1, rows + 1)
    margin_sq = 0.6
    w = rig.image_size[0]
    # Distances at which the board spans roughly 35 .. 60 % of the image width.
    board_w = (squares[0] + 2 * margin_sq) * square_mm
    fx = rig.left.K[0, 0]
    dist_range = (fx * board_w / (0.60 * w), fx * board_w / (0.35 * w))
    outline = _board_outline(squares, margin_sq, square_mm)
    rays_l = raw_pixel_rays(rig.left)
    rays_r = raw_pixel_rays(rig.right)
    digits = max(2, len(str(n_pairs)))
    paths: list[Path] = []
    Rs, ts = [], []
    for i in range(n_pairs):
        R_lb, t_lb = _pose_in_both(rng, rig, outline, dist_range)
        if R_lb is None or t_lb is None:
            raise ValueError(
                f"square_mm: no board pose of {squares[0]} x {squares[1]} squares of {square_mm} mm fits both images"
            )
        Rs.append(R_lb)
        ts.append(t_lb)
        R_rb, t_rb = rig.R @ R_lb, rig.R @ t_lb + rig.T
        for side, rays, Rc, tc in (("left", rays_l, R_lb, t_lb), ("right", rays_r, R_rb, t_rb)):
            img = _board_view(rays, Rc, tc, squares, square_mm, margin_sq, rng)
            paths.append(
                _write_view(out / f"{side}{i + 1:0{digits}d}.png", img, blur_px, noise, rng)
            )
    gx, gy = np.meshgrid(
        np.arange(1, cols + 1) - squares[0] / 2, np.arange(1, rows + 1) - squares[1] / 2
    )
    obj = np.stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)], axis=1) * square_mm
    np.savez(
        out / "board_truth.npz",
        R_cam_board=np.array(Rs),
        t_cam_board=np.array(ts),
        object_points=obj,
    )
    return paths


def _write_view(
    path: Path, img: np.ndarray, blur_px: float, noise: float, rng: np.random.Generator
) -> Path:
    """A board view as the camera records it (blurred, noisy, 8-bit), written to ``path``; returns ``path``."""
    if blur_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_px)
    img = img + np.float32(noise) * rng.standard_normal(img.shape, np.float32)
    write_png(path, quantise(img, 8))
    return path


def _check_arguments(
    rig: StereoRig | None,
    n_pairs: int,
    inner_corners: tuple[int, int],
    square_mm: float,
    blur_px: float,
    noise: float,
) -> StereoRig:
    """The arguments of :func:`render_calibration_pairs` checked; returns the rig (the default one for None)."""
    if rig is None:
        rig = default_rig()
    elif not isinstance(rig, StereoRig):
        raise TypeError(f"rig: expected a StereoRig or None, got {type(rig).__name__}")
    if not isinstance(n_pairs, (int, np.integer)) or n_pairs < 1:
        raise ValueError(f"n_pairs: expected an integer >= 1, got {n_pairs}")
    cols, rows = (int(v) for v in inner_corners)
    if len(tuple(inner_corners)) != 2 or cols < 2 or rows < 2:
        raise ValueError(f"inner_corners: expected (columns, rows) >= 2 each, got {inner_corners}")
    if not (math.isfinite(square_mm) and square_mm > 0):
        raise ValueError(f"square_mm: expected > 0, got {square_mm}")
    if not (math.isfinite(blur_px) and blur_px >= 0):
        raise ValueError(f"blur_px: expected >= 0, got {blur_px}")
    if not (math.isfinite(noise) and noise >= 0):
        raise ValueError(f"noise: expected >= 0, got {noise}")
    return rig


def _board_outline(squares: tuple[int, int], margin_sq: float, square_mm: float) -> np.ndarray:
    """The board's outline (its white border included), (36, 3) points in the board frame, mm: densified so
    that distortion cannot push an edge out between corners."""
    half = np.array([squares[0] / 2 + margin_sq, squares[1] / 2 + margin_sq]) * square_mm
    outline = np.array(
        [
            [-half[0], -half[1], 0],
            [half[0], -half[1], 0],
            [half[0], half[1], 0],
            [-half[0], half[1], 0],
        ]
    )
    edge = np.linspace(0, 1, 9)[:, None]
    return np.concatenate(
        [outline[i] + edge * (outline[(i + 1) % 4] - outline[i]) for i in range(4)]
    )


def _pose_in_both(
    rng: np.random.Generator, rig: StereoRig, outline: np.ndarray, dist_range: tuple[float, float]
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """A random board pose (R, t in the left frame) whose outline both cameras see whole, within 50 deg of
    head-on and 4 % of the width inside the image; (None, None) if 2000 draws found none."""
    w, h = rig.image_size
    margin_px = 0.04 * w
    for _ in range(2000):
        R_lb, t_lb = _board_pose(rng, dist_range)
        R_rb = rig.R @ R_lb
        t_rb = rig.R @ t_lb + rig.T
        ok = True
        for cam, Rc, tc in ((rig.left, R_lb, t_lb), (rig.right, R_rb, t_rb)):
            pc = outline @ Rc.T + tc
            # In front, facing the camera, and seen within 50 deg of head-on (oblique views of
            # the right camera, toed in and 800 mm aside, would otherwise defeat the detector).
            if np.any(pc[:, 2] <= 0) or (Rc[:, 2] @ tc) / np.linalg.norm(tc) < _BOARD_MIN_COS:
                ok = False
                break
            uv = cam.project(pc)
            if (
                np.any(uv < margin_px)
                or np.any(uv[:, 0] > w - 1 - margin_px)
                or np.any(uv[:, 1] > h - 1 - margin_px)
            ):
                ok = False
                break
        if ok:
            return R_lb, t_lb
    return None, None
