"""The registered stations resampled onto one grid: the whole plate as one measured surface.

The grid is square over the x and y of the *plate frame* (station 0's camera frame moved along the
travel to the middle of the plate's stations: a camera frame over the plate's middle), one cell a
station's median pixel footprint. Each cell holds a point of the measured surface: for each station
that sees it, the point of that station's surface whose x and y are the cell's, found by following the
station's pixel rays (project the cell at a height, read the station's surface there, take its height,
again: a fixed point that contracts by the ray's slope times the surface's, :data:`STEPS` steps from a
quadric start). Where stations overlap, their points are averaged with weights that fall to zero at each
station's image frame (feathering), so a seam leaves no step.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .register import StationView

#: Fixed-point steps of the resampling.
STEPS = 3
#: A cell is kept where the resampled point lies within this share of a cell of its centre.
CONVERGED_CELLS = 0.1


@dataclass(frozen=True)
class Footprint:
    """Where one station's pixels land on the grid (for resampling any per-pixel map of it).

    Attributes
    ----------
    rows, cols : slice
        The grid window the station covers.
    u, v : (h, w) float32
        The station's pixel of each cell of the window (NaN where it has no point).
    weight : (h, w) float64
        The cell's feathering weight for this station (0 where it has no point).
    """

    rows: slice
    cols: slice
    u: np.ndarray
    v: np.ndarray
    weight: np.ndarray


@dataclass(frozen=True)
class Mosaic:
    """The whole plate on one grid.

    Attributes
    ----------
    points : (H, W, 3) float64
        Measured points, mm, plate frame (NaN off the plate).
    mask : (H, W) bool
    cell_mm : float
        The grid's step, mm.
    frame : (4, 4) float64
        Maps station 0's camera frame into the plate frame.
    footprints : list of Footprint
        Each station's share of the grid.
    """

    points: np.ndarray
    mask: np.ndarray
    cell_mm: float
    frame: np.ndarray
    footprints: list[Footprint]

    def resample(self, maps: list[np.ndarray], *, squared: bool = False) -> np.ndarray:
        """Per-pixel maps of the stations (each on its own grid) blended onto the mosaic.

        ``squared``: blend the squares and return the root (a standard uncertainty). NaN off the plate.
        """
        total = np.zeros(self.mask.shape)
        weights = np.zeros(self.mask.shape)
        for fp, m in zip(self.footprints, maps, strict=True):
            src = np.asarray(m, np.float32)
            got = cv2.remap(
                src,
                np.nan_to_num(fp.u, nan=-1.0),
                np.nan_to_num(fp.v, nan=-1.0),
                cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=np.nan,
            ).astype(np.float64)
            w = np.where(np.isfinite(got), fp.weight, 0.0)
            val = got**2 if squared else got
            total[fp.rows, fp.cols] += w * np.nan_to_num(val)
            weights[fp.rows, fp.cols] += w
        with np.errstate(invalid="ignore", divide="ignore"):
            out = total / weights
        out = np.sqrt(out) if squared else out
        blended: np.ndarray = np.where(self.mask & (weights > 0), out, np.nan)
        return blended

    def blend_constants(self, values: list[float]) -> np.ndarray:
        """One value per station blended onto the mosaic as :meth:`resample` blends squares (root mean
        square by the stations' weights); NaN off the plate."""
        total = np.zeros(self.mask.shape)
        weights = np.zeros(self.mask.shape)
        for fp, value in zip(self.footprints, values, strict=True):
            total[fp.rows, fp.cols] += fp.weight * value**2
            weights[fp.rows, fp.cols] += fp.weight
        with np.errstate(invalid="ignore", divide="ignore"):
            out = np.sqrt(total / weights)
        blended: np.ndarray = np.where(self.mask & (weights > 0), out, np.nan)
        return blended


def build_mosaic(
    views: list[StationView], poses: list[np.ndarray], travel_mm: list[float]
) -> Mosaic:
    """The stations, registered by ``poses`` (station k's camera frame into station 0's), on one grid.

    Parameters
    ----------
    views : list of StationView
    poses : list of (4, 4) float64
    travel_mm : list of float
        Refined travels (the plate frame sits over the middle of the first and last).

    Returns
    -------
    Mosaic
    """
    direction = views[0].direction
    frame = np.eye(4)
    frame[:3, 3] = direction * 0.5 * (travel_mm[0] + travel_mm[-1])
    cell = float(np.median([v.footprint_mm for v in views]))
    to_plate = [frame @ g for g in poses]
    lo, hi = _extent(views, to_plate)
    x0, y0 = lo - 2 * cell
    width = int(np.ceil((hi[0] - lo[0]) / cell)) + 5
    height = int(np.ceil((hi[1] - lo[1]) / cell)) + 5
    total = np.zeros((height, width, 3))
    weights = np.zeros((height, width))
    footprints = []
    for view, pose in zip(views, to_plate, strict=True):
        fp, pts = _resample(view, pose, (x0, y0), cell, (height, width))
        # pts is 0 where the weight is (no point): the weighted sum without selecting the cells
        pts *= fp.weight[..., None]
        total[fp.rows, fp.cols] += pts
        weights[fp.rows, fp.cols] += fp.weight
        footprints.append(fp)
    mask = weights > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        total /= weights[..., None]  # in place: the grid is the size of the whole plate
    total[~mask] = np.nan
    return Mosaic(points=total, mask=mask, cell_mm=cell, frame=frame, footprints=footprints)


def _extent(views: list[StationView], poses: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Lowest and highest (x, y) of every station's points in the plate frame, mm."""
    los, his = [], []
    for view, pose in zip(views, poses, strict=True):
        pts = view.points[::4, ::4][view.mask[::4, ::4]] @ pose[:3, :3].T + pose[:3, 3]
        los.append(pts[:, :2].min(axis=0))
        his.append(pts[:, :2].max(axis=0))
    return np.min(los, axis=0), np.max(his, axis=0)


def _resample(
    view: StationView,
    pose: np.ndarray,
    origin: tuple[float, float],
    cell: float,
    shape: tuple[int, int],
) -> tuple[Footprint, np.ndarray]:
    """One station's surface at the cells of its window (see the module docstring): its footprint and
    its points (h, w, 3), plate frame, 0 where it has none (its weight is 0 there)."""
    sub = view.points[::4, ::4][view.mask[::4, ::4]] @ pose[:3, :3].T + pose[:3, 3]
    c0 = max(int(np.floor((sub[:, 0].min() - origin[0]) / cell)) - 2, 0)
    c1 = min(int(np.ceil((sub[:, 0].max() - origin[0]) / cell)) + 3, shape[1])
    r0 = max(int(np.floor((sub[:, 1].min() - origin[1]) / cell)) - 2, 0)
    r1 = min(int(np.ceil((sub[:, 1].max() - origin[1]) / cell)) + 3, shape[0])
    xs = origin[0] + cell * np.arange(c0, c1)
    ys = origin[1] + cell * np.arange(r0, r1)
    gx, gy = (g.astype(np.float32) for g in np.meshgrid(xs, ys))
    z = _quadric(sub, gx, gy).astype(np.float32)
    to_station = np.linalg.inv(pose)[:3].astype(np.float32)
    src = view.points.astype(np.float32)
    h, w = view.shape
    fx, fy, cx, cy = (
        np.float32(v) for v in (view.K[0, 0], view.K[1, 1], view.K[0, 2], view.K[1, 2])
    )
    u = v = np.zeros_like(gx)
    got = np.full((*gx.shape, 3), np.nan, np.float32)
    xyz = np.stack([gx, gy, z], axis=-1)
    a, b, c, d = (np.float32(x) for x in pose[2])
    for _ in range(STEPS):
        xyz[..., 2] = z
        cam = cv2.transform(xyz, to_station)
        with np.errstate(invalid="ignore", divide="ignore"):
            inv_z = 1.0 / cam[..., 2]
            u = fx * cam[..., 0] * inv_z + cx
            v = fy * cam[..., 1] * inv_z + cy
        got = cv2.remap(
            src,
            np.nan_to_num(u, nan=-1.0),
            np.nan_to_num(v, nan=-1.0),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=np.nan,
        )
        height = a * got[..., 0] + b * got[..., 1] + c * got[..., 2] + d
        np.copyto(z, height, where=np.isfinite(height))
    # the last points in float64 (the sums of the overlaps are made in float64)
    pts = cv2.transform(got.astype(np.float64), pose[:3])
    miss = np.hypot(pts[..., 0] - gx, pts[..., 1] - gy)
    ok = np.isfinite(miss) & (miss < CONVERGED_CELLS * cell)
    pts[~ok] = 0.0
    # feathering: the distance (px) to the station's image frame
    frame_px = np.minimum(np.minimum(u, w - 1 - u), np.minimum(v, h - 1 - v)).astype(np.float64)
    weight = np.where(ok, np.clip(frame_px, 0.0, None) + 1e-3, 0.0)
    fp = Footprint(
        rows=slice(r0, r1),
        cols=slice(c0, c1),
        u=np.where(ok, u, np.nan).astype(np.float32),
        v=np.where(ok, v, np.nan).astype(np.float32),
        weight=weight,
    )
    return fp, pts


def _quadric(pts: np.ndarray, gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """A quadric height z(x, y) fitted to points (M, 3), evaluated at (gx, gy)."""
    x, y = pts[:, 0], pts[:, 1]
    mx, my = float(x.mean()), float(y.mean())
    s = float(max(np.ptp(x), np.ptp(y), 1.0))

    def design(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        a, b = (a - mx) / s, (b - my) / s
        return np.stack([np.ones_like(a), a, b, a * a, a * b, b * b], axis=-1)

    coef, *_ = np.linalg.lstsq(design(x, y), pts[:, 2], rcond=None)
    c0, c1, c2, c3, c4, c5 = (np.float32(c) for c in coef)
    a = (gx - np.float32(mx)) / np.float32(s)
    b = (gy - np.float32(my)) / np.float32(s)
    z: np.ndarray = c0 + a * (c1 + c3 * a + c4 * b) + b * (c2 + c5 * b)
    return z
