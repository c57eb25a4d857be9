"""depth.npy: the measured depth (float32 mm, NaN off the plate)."""

from __future__ import annotations

import os

import numpy as np
import numpy.typing as npt


def save_depth(path: str | os.PathLike[str], depth_mm: npt.ArrayLike) -> None:
    """Save a depth map as ``.npy`` float32, NaN where there is no depth.

    Parameters
    ----------
    path : str or Path
        Written as given (no suffix is appended).
    depth_mm : (H, W) float
        Depth along the left camera's z axis, mm; NaN outside the measured area.

    Raises
    ------
    ValueError
        Not 2-D, or holding infinite values.
    """
    depth = np.asarray(depth_mm)
    if depth.ndim != 2 or not np.issubdtype(depth.dtype, np.floating):
        raise ValueError(
            f"depth_mm: expected a float array of shape (H, W), got {depth.dtype} {depth.shape}"
        )
    if np.isinf(depth).any():
        raise ValueError(
            f"depth_mm: expected finite values or NaN, got {int(np.isinf(depth).sum())} infinite"
        )
    with open(path, "wb") as fh:
        np.save(fh, depth.astype(np.float32), allow_pickle=False)
