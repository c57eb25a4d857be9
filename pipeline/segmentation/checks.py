"""Checks of the segmentation's inputs (images on the left undistorted grid, the camera matrix)."""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

from .. import camera


def check_image(
    name: str, value: npt.ArrayLike, shape: tuple[int, int] | None = None
) -> np.ndarray:
    """A real-valued (H, W) image (of ``shape`` when given); ValueError naming ``name`` otherwise."""
    arr = np.asarray(value)
    if arr.ndim != 2:
        raise ValueError(f"{name}: expected an (H, W) array, got shape {arr.shape}")
    if shape is not None and arr.shape != shape:
        raise ValueError(f"{name}: expected shape {shape} to match brightness, got {arr.shape}")
    if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
        raise ValueError(f"{name}: expected real numbers, got dtype {arr.dtype}")
    return arr


def check_bool_image(name: str, value: npt.ArrayLike, shape: tuple[int, int]) -> np.ndarray:
    """A bool image of ``shape``; ValueError naming ``name`` otherwise."""
    arr = np.asarray(value)
    if arr.dtype != np.bool_ or arr.shape != shape:
        raise ValueError(
            f"{name}: expected a bool array of shape {shape}, got {arr.dtype} {arr.shape}"
        )
    return arr


def check_camera_matrix(K: npt.ArrayLike) -> np.ndarray:
    """The camera matrix argument checked (:func:`pipeline.camera.check_camera_matrix`)."""
    return camera.check_camera_matrix(K, "camera_matrix")
