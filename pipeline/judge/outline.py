"""The target's outline on the measured plate: a point beyond it has no target surface to deviate from.

A plane, cylinder or sphere target is the plate of ``size_mm``: its extent projected on the target
frame's xy plane (:mod:`pipeline.judge.target_geometry`). Registered to the measured plate, that
rectangle lies centred on the plate's footprint and along its sides
(:func:`pipeline.judge.registration.register_to_target`), so a measured point whose target-frame x or y
lies beyond the rectangle is not on the target's plate: it is the surroundings measured as plate (the top
of a rail or block continuing the plate's surface past its edge, where no depth or outline test can tell
them apart), or a plate larger than its target. Either way the target has no surface there, and the
point is left out of the judgement, by where it lies, never by its deviation. A mesh target's deviation
is already undefined outside the mesh's footprint (:func:`pipeline.judge.deviation.deviation_map`).

A footprint smaller than the target (a plate partly out of view, an opening at its edge) is centred on
itself and never reaches the outline: nothing is left out.
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
import numpy.typing as npt

from pipeline.io import Target

from .registration import Registration
from .target_geometry import check_target


def beyond_outline(
    points_mm: npt.ArrayLike, mask: npt.ArrayLike, target: Target, registration: Registration
) -> np.ndarray:
    """The mask's pixels whose point lies beyond the registered target's outline.

    Parameters
    ----------
    points_mm : (H, W, 3) array_like of float
        Surface points, left-camera frame, mm.
    mask : (H, W) bool
        The pixels to test (the others are False in the result).
    target : pipeline.io.Target
    registration : Registration
        From :func:`pipeline.judge.registration.register_to_target`.

    Returns
    -------
    (H, W) bool
        True where ``|x| > size_mm[0] / 2`` or ``|y| > size_mm[1] / 2`` in the target frame (plane,
        cylinder, sphere); all False for a mesh target.
    """
    tgt = check_target(target)
    m = np.asarray(mask, dtype=bool)
    pts = np.asarray(points_mm, dtype=np.float64)
    if pts.shape != (*m.shape, 3):
        raise ValueError(
            f"points_mm: expected shape {(*m.shape, 3)} for a {m.shape} mask, got {pts.shape}"
        )
    out = np.zeros(m.shape, bool)
    if tgt.shape == "mesh" or not m.any():
        return out
    T = np.ascontiguousarray(registration.T_cam_target, dtype=np.float64)
    half_x, half_y = (float(s) / 2 for s in tgt.size_mm)
    _beyond(np.ascontiguousarray(pts), np.ascontiguousarray(m), T, half_x, half_y, out)
    return out


@numba.njit(nogil=True, cache=True)
def _beyond(
    pts: npt.NDArray[Any],
    mask: npt.NDArray[Any],
    T: npt.NDArray[Any],
    half_x: float,
    half_y: float,
    out: npt.NDArray[Any],
) -> None:  # pragma: no cover - compiled
    """:func:`beyond_outline`'s test in one pass over the mask: a point's target-frame x and y,
    ``R^T (p - t)`` with ``T = [R t]``, against the half sizes; single-threaded (the judging thread)."""
    h, w = mask.shape
    for i in range(h):
        for j in range(w):
            if not mask[i, j]:
                continue
            dx = pts[i, j, 0] - T[0, 3]
            dy = pts[i, j, 1] - T[1, 3]
            dz = pts[i, j, 2] - T[2, 3]
            x = T[0, 0] * dx + T[1, 0] * dy + T[2, 0] * dz
            y = T[0, 1] * dx + T[1, 1] * dy + T[2, 1] * dz
            out[i, j] = abs(x) > half_x or abs(y) > half_y
