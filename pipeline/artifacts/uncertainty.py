"""The per-point uncertainty's artifacts: its values (``uncertainty.npy``) and a map (``uncertainty.png``)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

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
    u = np.where(mask, np.asarray(u_mm, dtype=np.float32), np.nan).astype(np.float32)
    out = Path(out_dir)
    np.save(out / UNCERTAINTY_FILES["uncertainty"], u)
    scaled = np.clip(np.nan_to_num(u, nan=0.0) / (tolerance_mm / 4.0), 0.0, 1.0)
    bgr = cv2.applyColorMap((255 * scaled).astype(np.uint8), cv2.COLORMAP_VIRIDIS)
    bgr[~mask] = NO_DATA_RGB[::-1]
    cv2.imwrite(str(out / UNCERTAINTY_FILES["uncertainty_map"]), bgr)
