"""Photometric normals: per-pixel Lambertian photometric stereo (stage 5 of the method).

:func:`estimate_normals` turns N intensity-normalised images taken under N known distant lights
into a field of unit surface normals and albedo in the left-camera frame, filling the holes (too
few usable samples) by harmonic interpolation and counting them. Under point lights the same
robust kernel runs per pixel from the current surface (:mod:`pipeline.lights.nearfield`).

Modules, one job each:

- :mod:`~pipeline.surface.normals.estimate`: :func:`estimate_normals`, its input checks and the choice of estimator;
- :mod:`~pipeline.surface.normals.lstsq`: Woodham's least squares;
- :mod:`~pipeline.surface.normals.robust`: the robust estimator (shadows, highlights and outliers rejected);
- :mod:`~pipeline.surface.normals.specular`: the specular lobe of glossy plates;
- :mod:`~pipeline.surface.normals.field`: :class:`NormalField`, a fit's status codes, normals facing away;
- :mod:`~pipeline.surface.normals.fill`: harmonic hole filling;
- :mod:`~pipeline.surface.normals.solve3`: the per-pixel 3x3 normal equations (one adjugate solve for all kernels).

References
----------
.. [1] R. J. Woodham, "Photometric method for determining surface orientation from
   multiple images", Optical Engineering 19(1), 1980.
.. [2] B. Shi et al., "A benchmark dataset and evaluation for non-Lambertian and
   uncalibrated photometric stereo" (DiLiGenT), CVPR 2016 / TPAMI 2019: the real
   data the robust estimator is checked on (``tests/realdata.py``).
"""

from .estimate import METHODS, estimate_normals
from .field import NormalField, drop_facing_away
from .robust import (
    COS_MIN,
    OUTLIER_K,
    OUTLIER_K_HIGH,
    ROBUST_ITERATIONS,
    SCALE_FLOOR,
    SHADOW_FRACTION,
    SHADOW_REF_QUANTILE,
    TRIM_TOP_FRACTION,
)
from .solve3 import DEGENERATE_RATIO
from .specular import (
    LOBE_EXPONENTS,
    LOBE_MIN_F,
    LOBE_SEARCH_PIXELS,
    MAX_SPECULAR_TURN_DEG,
    SPECULAR_ITERATIONS,
    SPECULAR_K,
    SPECULAR_WINDOW,
    SpecularFit,
)

__all__ = [
    "COS_MIN",
    "DEGENERATE_RATIO",
    "LOBE_EXPONENTS",
    "LOBE_MIN_F",
    "LOBE_SEARCH_PIXELS",
    "MAX_SPECULAR_TURN_DEG",
    "METHODS",
    "OUTLIER_K",
    "OUTLIER_K_HIGH",
    "ROBUST_ITERATIONS",
    "SCALE_FLOOR",
    "SHADOW_FRACTION",
    "SHADOW_REF_QUANTILE",
    "SPECULAR_ITERATIONS",
    "SPECULAR_K",
    "SPECULAR_WINDOW",
    "TRIM_TOP_FRACTION",
    "NormalField",
    "SpecularFit",
    "drop_facing_away",
    "estimate_normals",
]
