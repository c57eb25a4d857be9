"""Checks of the artifact writers' arguments."""

from __future__ import annotations

import math

import numpy as np
import numpy.typing as npt


def check_mask(mask: npt.ArrayLike, shape: tuple[int, ...]) -> npt.NDArray[np.bool_]:
    """A bool mask of ``shape``; ValueError otherwise."""
    m = np.asarray(mask)
    if m.dtype != bool:
        raise ValueError(f"mask: expected a bool array, got {m.dtype}")
    if m.shape != tuple(shape):
        raise ValueError(f"mask: expected shape {tuple(shape)}, got {m.shape}")
    return m


def check_positive(name: str, value: object) -> None:
    """ValueError naming ``name`` unless ``value`` is a positive finite number."""
    if not (
        isinstance(value, (int, float, np.floating, np.integer))
        and math.isfinite(value)
        and value > 0
    ):
        raise ValueError(f"{name}: expected a positive finite number of mm, got {value!r}")
