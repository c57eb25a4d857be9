"""Binocular metric depth (stage 3 of the method): :func:`stereo_depth` and what it is made of.

Modules, one job each:

- :mod:`~pipeline.surface.stereo.depth`: :func:`stereo_depth`, the two passes (coarse range, fine match),
  triangulation and the depth on the left undistorted grid;
- :mod:`~pipeline.surface.stereo.matching`: the rig's rectification and one rectify-and-match pass (SGBM);
- :mod:`~pipeline.surface.stereo.refine`: sub-pixel refinement and the correlation check of a disparity map.
"""

from .depth import (
    COARSE_FACTOR,
    COARSE_MIN_MATCHES,
    COARSE_PERCENTILES,
    FINE_MARGIN_PX,
    RANGE_MARGIN_PX,
    StereoDepth,
    stereo_depth,
)
from .matching import BLOCK_SIZE, LR_MAX_DIFF_PX, RECTIFY_INTERPOLATION, rectification
from .refine import (
    MIN_ZNCC,
    REFINE_ITERATIONS,
    REFINE_MAX_STEP_PX,
    REFINE_SIGMA_PX,
    match_correlation,
    refine_disparity,
)

__all__ = [
    "BLOCK_SIZE",
    "COARSE_FACTOR",
    "COARSE_MIN_MATCHES",
    "COARSE_PERCENTILES",
    "FINE_MARGIN_PX",
    "LR_MAX_DIFF_PX",
    "MIN_ZNCC",
    "RANGE_MARGIN_PX",
    "RECTIFY_INTERPOLATION",
    "REFINE_ITERATIONS",
    "REFINE_MAX_STEP_PX",
    "REFINE_SIGMA_PX",
    "StereoDepth",
    "match_correlation",
    "rectification",
    "refine_disparity",
    "stereo_depth",
]
