"""The per-point uncertainty's artifacts: its values (``uncertainty.npy``) and a map (``uncertainty.png``)."""

from __future__ import annotations

import functools
from pathlib import Path

import cv2
import numba
import numpy as np
import numpy.typing as npt

from ..io.png import write_rgb
from .checks import check_positive
from .colours import NO_DATA_RGB

#: File names of the per-point expanded uncertainty (float32 mm, NaN where not judged) and its map.
UNCERTAINTY_FILES = {"uncertainty": "uncertainty.npy", "uncertainty_map": "uncertainty.png"}


def write_uncertainty(
    out_dir: str | Path, u_mm: np.ndarray, mask: np.ndarray, *, tolerance_mm: float
) -> None:
    """Write the per-point expanded uncertainty (k = 2) and its map into ``out_dir``.

    Parameters
    ----------
    out_dir : str or Path
        Folder of the inspection's artifacts (:data:`UNCERTAINTY_FILES` are written there).
    u_mm : (H, W) float
        Expanded uncertainty per point, mm.
    mask : (H, W) bool
        Judged points (the others are saved as NaN and drawn in the no-data colour).
    tolerance_mm : float
        The map's scale runs from 0 (dark blue) to a quarter of the tolerance (yellow): a point drawn
        at the top of the scale is measured too coarsely for a capable judgement (tolerance / U < 4).
    """
    check_positive("tolerance_mm", tolerance_mm)
    mask = np.ascontiguousarray(mask, dtype=bool)
    u = np.empty(mask.shape, np.float32)
    rgb = np.empty((*mask.shape, 3), np.uint8)
    _levels(
        np.ascontiguousarray(u_mm, dtype=np.float32),
        mask,
        np.float32(tolerance_mm / 4.0),
        _viridis_rgb(),
        np.asarray(NO_DATA_RGB, np.uint8),
        u,
        rgb,
    )
    out = Path(out_dir)
    np.save(out / UNCERTAINTY_FILES["uncertainty"], u)
    write_rgb(out / UNCERTAINTY_FILES["uncertainty_map"], rgb)


@functools.cache
def _viridis_rgb() -> npt.NDArray[np.uint8]:
    """OpenCV's viridis colour map as a table (256, 3) of RGB, level by level (``cv2.applyColorMap`` is
    this table, in BGR, applied to each pixel)."""
    ramp = np.arange(256, dtype=np.uint8).reshape(1, 256)
    return np.ascontiguousarray(cv2.applyColorMap(ramp, cv2.COLORMAP_VIRIDIS)[0, :, ::-1])


@numba.njit(nogil=True, cache=True)
def _levels(
    u_mm: npt.NDArray[np.float32],
    mask: npt.NDArray[np.bool_],
    top: np.float32,
    lut: npt.NDArray[np.uint8],
    no_data: npt.NDArray[np.uint8],
    u: npt.NDArray[np.float32],
    rgb: npt.NDArray[np.uint8],
) -> None:  # pragma: no cover - compiled
    """u = the uncertainty on the mask (NaN elsewhere) and ``rgb`` its map: the colour ``lut`` (256, 3) at
    the 0..255 level (255 at ``top`` and beyond; the level in float32 as ``np.nan_to_num``, ``/``,
    ``np.clip`` and ``255 *`` give it), ``no_data`` off the mask, in one pass; single-threaded (an
    artifact writer's thread)."""
    h, w = mask.shape
    big = np.finfo(np.float32).max
    zero, one, full = np.float32(0.0), np.float32(1.0), np.float32(255.0)
    for i in range(h):
        for j in range(w):
            v = u_mm[i, j] if mask[i, j] else np.float32(np.nan)
            u[i, j] = v
            if np.isnan(v):
                x = zero
            elif v == np.inf:
                x = big
            elif v == -np.inf:
                x = -big
            else:
                x = v
            if mask[i, j]:
                level = np.uint8(full * min(max(x / top, zero), one))
                rgb[i, j, 0], rgb[i, j, 1], rgb[i, j, 2] = (
                    lut[level, 0],
                    lut[level, 1],
                    lut[level, 2],
                )
            else:
                rgb[i, j, 0], rgb[i, j, 1], rgb[i, j, 2] = no_data[0], no_data[1], no_data[2]
