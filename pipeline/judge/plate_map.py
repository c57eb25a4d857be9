"""The deviation map in the plate's own frame: mm on both axes, the frame the defects are given in.

``deviation.png`` is the camera's view of the plate (pixels, perspective). An operator marks the
plate, and a defect table gives positions, in the target's frame (target.json: origin at the
target's centre, ``x`` along its first side, ``y`` along its second, ``z`` towards the cameras).
:func:`plate_map` resamples the measured surface's per-vertex deviation (``surface.ply``) onto a
regular grid of that frame: each vertex is moved into the target frame by the registration
(``details.json``'s ``T_cam_target``) and the deviations are averaged in square cells of
``x, y``. A cell without a vertex is NaN (off the plate, a hole, an excluded region).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from pipeline.artifacts.ply import read_surface_ply

#: Cells along the longer side of the map by default (a 3 m plate: 12.5 mm cells).
DEFAULT_CELLS = 240


@dataclass(frozen=True)
class PlateMap:
    """Mean deviation in square cells of the target frame's ``(x, y)`` plane.

    Attributes
    ----------
    x0_mm, y0_mm : float, the target-frame coordinates of the corner of cell ``[0, 0]`` (its
        smallest ``x`` and ``y``), mm.
    cell_mm : float, the cells' side, mm.
    deviation_mm : (ny, nx) float, mean signed deviation of the vertices in each cell, mm (row
        ``j`` holds ``y`` in ``[y0 + j cell, y0 + (j + 1) cell)``); NaN where no vertex fell.
    """

    x0_mm: float
    y0_mm: float
    cell_mm: float
    deviation_mm: npt.NDArray[np.float64]

    @property
    def extent_mm(self) -> tuple[float, float, float, float]:
        """``(x_min, x_max, y_min, y_max)`` of the grid, mm."""
        ny, nx = self.deviation_mm.shape
        return (
            self.x0_mm,
            self.x0_mm + nx * self.cell_mm,
            self.y0_mm,
            self.y0_mm + ny * self.cell_mm,
        )

    def value_at(self, x_mm: float, y_mm: float) -> float:
        """The cell's deviation at a target-frame point, mm; NaN off the grid or in an empty cell."""
        i = math.floor((x_mm - self.x0_mm) / self.cell_mm)
        j = math.floor((y_mm - self.y0_mm) / self.cell_mm)
        ny, nx = self.deviation_mm.shape
        if not (0 <= i < nx and 0 <= j < ny):
            return math.nan
        return float(self.deviation_mm[j, i])


def to_target_frame(
    points_cam_mm: npt.ArrayLike, T_cam_target: npt.ArrayLike
) -> npt.NDArray[np.float64]:
    """Camera-frame points (N, 3) into the target frame: ``R^T (p - t)`` for ``T = [R t]``.

    Raises
    ------
    ValueError
        ``T_cam_target`` not a finite (4, 4) matrix, or points not (N, 3).
    """
    T = np.asarray(T_cam_target, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"T_cam_target: expected a finite (4, 4) matrix, got shape {T.shape}")
    p = np.asarray(points_cam_mm, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points_cam_mm: expected shape (N, 3), got {p.shape}")
    out: npt.NDArray[np.float64] = (p - T[:3, 3]) @ T[:3, :3]
    return out


def to_camera_frame(
    points_target_mm: npt.ArrayLike, T_cam_target: npt.ArrayLike
) -> npt.NDArray[np.float64]:
    """Target-frame points (N, 3) into the camera frame: ``R p + t``."""
    T = np.asarray(T_cam_target, dtype=np.float64)
    p = np.atleast_2d(np.asarray(points_target_mm, dtype=np.float64))
    out: npt.NDArray[np.float64] = p @ T[:3, :3].T + T[:3, 3]
    return out


def plate_map(
    vertices_cam_mm: npt.ArrayLike,
    deviation_mm: npt.ArrayLike,
    T_cam_target: npt.ArrayLike,
    *,
    cells: int = DEFAULT_CELLS,
) -> PlateMap:
    """Average the per-vertex deviation in square cells of the target frame (module docstring).

    Parameters
    ----------
    vertices_cam_mm : (V, 3) float, the measured surface's vertices, left camera frame, mm.
    deviation_mm : (V,) float, their signed deviation, mm (NaN: none).
    T_cam_target : (4, 4) float, target frame to camera frame (details.json).
    cells : int >= 2, cells along the longer side of the vertices' extent.

    Raises
    ------
    ValueError
        Shapes that do not match, ``cells`` below 2, or no vertex with a finite deviation.
    """
    if cells < 2:
        raise ValueError(f"cells: expected >= 2, got {cells}")
    xyz = to_target_frame(vertices_cam_mm, T_cam_target)
    dev = np.asarray(deviation_mm, dtype=np.float64).ravel()
    if dev.shape[0] != xyz.shape[0]:
        raise ValueError(
            f"deviation_mm: expected one value per vertex ({xyz.shape[0]}), got {dev.shape[0]}"
        )
    ok = np.isfinite(dev) & np.all(np.isfinite(xyz), axis=1)
    if not ok.any():
        raise ValueError("deviation_mm: expected at least one vertex with a finite deviation")
    x, y, d = xyz[ok, 0], xyz[ok, 1], dev[ok]
    span = max(float(np.ptp(x)), float(np.ptp(y)), 1e-6)
    cell = _round_cell(span / cells)
    x0 = math.floor(float(x.min()) / cell) * cell
    y0 = math.floor(float(y.min()) / cell) * cell
    nx = math.floor((float(x.max()) - x0) / cell) + 1
    ny = math.floor((float(y.max()) - y0) / cell) + 1
    flat = ((y - y0) // cell).astype(np.intp) * nx + ((x - x0) // cell).astype(np.intp)
    total = np.bincount(flat, weights=d, minlength=nx * ny)
    count = np.bincount(flat, minlength=nx * ny)
    mean = np.divide(total, count, out=np.full(nx * ny, np.nan), where=count > 0)
    return PlateMap(x0_mm=x0, y0_mm=y0, cell_mm=cell, deviation_mm=mean.reshape(ny, nx))


def _round_cell(cell_mm: float) -> float:
    """A readable cell size at or above ``cell_mm``: 1, 2, 2.5 or 5 times a power of ten, mm.

    Two inspections of one plate then share cell edges (both grids start at a multiple of it), so
    their maps can be subtracted cell by cell."""
    power = 10.0 ** math.floor(math.log10(cell_mm))
    return next(m * power for m in (1.0, 2.0, 2.5, 5.0, 10.0) if m * power >= cell_mm * (1 - 1e-9))


def load_plate_map(artifact_dir: Path, *, cells: int = DEFAULT_CELLS) -> PlateMap:
    """The plate map of an inspection's artifact folder (surface.ply, details.json).

    Raises
    ------
    ValueError
        A file is missing or unreadable (naming it), or as :func:`plate_map`.
    """
    artifact_dir = Path(artifact_dir)
    details_path = artifact_dir / "details.json"
    surface_path = artifact_dir / "surface.ply"
    for path in (details_path, surface_path):
        if not path.is_file():
            raise ValueError(f"{path.name}: not found among the inspection's artifacts")
    try:
        T = json.loads(details_path.read_text())["T_cam_target"]
    except (json.JSONDecodeError, KeyError) as err:
        raise ValueError(f"details.json: T_cam_target: not readable: {err}") from err
    vertices, _faces, deviation = read_surface_ply(surface_path)
    return plate_map(vertices, deviation, T, cells=cells)
