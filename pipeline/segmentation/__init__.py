"""The plate among its surroundings (stage 4 of the method): which pixels of the left undistorted grid see the plate.

Brightness alone cannot tell a plate from a shop floor, supports or a conveyor that the same lights
make as bright; geometry can. The stereo pair puts the plate and everything around it at depths
hundreds of millimetres apart, so the plate is found as the near, smooth sheet of the stereo depth:

1. *Candidates* (:func:`candidate_mask`): pixels that are not dark (their brightness -- the pipeline
   gives the brightest photometric sample once the brightest 30 % are set aside, so that a glossy
   conveyor's highlights do not light it -- at least ``dark_fraction`` of the image's bright level). A dark conveyor is excluded here; a lit floor
   is not. This is also the region the stereo pair should be matched over.
2. *Surface*: a smooth surface, inverse depth ``1/z`` as a polynomial in the normalised image
   coordinates ``(x, y) = K^-1 (u, v, 1)`` (exact for a plane; a curved plate at 3 m is within a few
   millimetres at degree 4), is fitted robustly to the stereo depth. The fit starts on the nearest
   candidates (the plate lies above the floor and the supports) and grows: each round keeps the
   largest connected set of candidates within ``depth_band_mm`` of the current surface and refits.
3. *Plate*: the largest 8-connected set of candidates whose stereo depth lies within the band, less
   the parts narrower than ``support_width_mm`` whose depth leaves the smooth surface: supports that
   reach out beside the plate at its depth (a rail under its edge). Such a part that rounds the plate's
   outline out instead of reaching out of it (the concavity it leaves beside it well under its reach
   beyond the rest's convex hull, a reach no longer than the opening's radius: a corner, which the
   opening cuts off, bent off the surface) is the plate's own and stays (:func:`~pipeline.segmentation.classify.outline_corners`). Where a support
   met the plate, the edge band is widened to a quarter of that width.
4. *Holes stay holes*: a region enclosed by the plate is filled only if at most a quarter of it shows
   depth off the plate or darkness, and it is a small dropout (at most ``max_dropout_mm2``) or, given
   photometric normals, its normals follow the fitted surface (median within ``DROPOUT_NORMAL_DEG``);
   anything showing what lies behind is an opening and stays out of the mask, as does a larger
   unmatched area without agreeing normals. Nothing is ever filled across a depth step: a filled
   region has no stereo depth of its own (see :meth:`Segmentation.stereo_prior`).
5. *The rim*: pixels the stereo pair could not match next to the plate (its matching windows
   straddle the edge) are added only where darkness bounds them within ``reach_px`` (a dark
   background makes the edge sharp); next to a lit floor they stay out (there the unmatched strip is
   mostly the floor hidden from the right camera).
5b. *The outline beside lit surroundings*: the stereo matcher carries the plate's depth up to
   ``OUTLINE_REACH_PX`` onto what lies beside it; next to darkness the candidates bound it, next to
   lit surroundings (a dark conveyor under a broad glare lobe) the glare-free brightness (the brightest
   of the darkest quarter of the samples, which a broad lobe lights least) does: where most lit pixels
   within reach outside are darker than ``OUTLINE_ALBEDO_RATIO`` times the plate just inside (its
   local mean, or its brighter steel: the paint beside a rust patch), the region's pixels near the
   outline nearer their brightness than the plate's (its mean, or its darker steel) are surroundings,
   as far as the comparison sees them (surroundings matched at their own depth within the depth band
   reach beyond the matcher's reach) (:mod:`~pipeline.segmentation.outline`; they join the edge band).
6. *Edge band*: the plate's pixels within ``edge_px`` of its boundary (outline and openings; the
   image frame does not count) mix plate and surroundings in the photometric images; they are
   excluded from the mask and counted. Given photometric normals, pixels a little further in whose
   normal leaves the fitted surface's by more than ``EDGE_NORMAL_DEG`` join the band (the stereo
   matcher smears the plate's depth a few pixels onto what lies beside it).
7. *Surroundings step*: along the boundary, the depth of what lies beside the plate relative to the
   plate's surface, for telling segmentation artefacts at the edge from real edge defects
   (:func:`pipeline.judge.verdict.judge`).

Without a usable stereo depth (no pair, or too little matched) the plate is the largest candidate
component with small holes filled (the dark-background case), and the result says so.

Modules, one job each: :mod:`~pipeline.segmentation.candidates` (step 1),
:mod:`~pipeline.segmentation.surface` (step 2: the smooth surface and its geometry),
:mod:`~pipeline.segmentation.classify` (steps 3-5 and 7 on the depth's grid),
:mod:`~pipeline.segmentation.outline` (step 5b), :mod:`~pipeline.segmentation.edge_band` (step 6 and
the result), :mod:`~pipeline.segmentation.segment`
(:func:`segment_plate`, and the brightness-only fallback), :mod:`~pipeline.segmentation.plain` (plain
scenes that need no segmentation), :mod:`~pipeline.segmentation.result` (:class:`Segmentation`),
:mod:`~pipeline.segmentation.checks` (input checks).

Conventions: images ``[row, col]``, pixel ``(u, v) = (col, row)``; depth ``z`` in mm along the left
camera's optical axis on the left undistorted grid (``X = z K^-1 (u, v, 1)``), NaN where unmatched;
areas in mm^2 on the fitted surface.
"""

from .candidates import DARK_FRACTION, DARK_SPECK_PX, candidate_mask
from .classify import (
    DROPOUT_MAX_OFF_SHARE,
    DROPOUT_NORMAL_DEG,
    PROTRUSION_RESIDUAL_MM,
    PROTRUSION_SHARE,
    SUPPORT_WIDTH_MM,
)
from .edge_band import EDGE_NORMAL_DEG, EDGE_NORMAL_ZONE_PX
from .outline import OUTLINE_ALBEDO_RATIO, OUTLINE_REACH_PX
from .plain import (
    PLAIN_LIT_SHARE,
    PLAIN_MARGIN_PX,
    PLAIN_OFF_SURFACE_SHARE,
    PLAIN_OPENING_SHARE,
    PLAIN_SUPPORT_MIN_WIDTH_MM,
    plain_depth,
    plain_outline,
)
from .result import Segmentation
from .segment import EDGE_PX, MAX_DROPOUT_MM2, MIN_MATCHED_SHARE, segment_plate
from .surface import DEPTH_BAND_MM, FIT_SAMPLES, SEED_SHARE, SURFACE_DEGREE

__all__ = [
    "DARK_FRACTION",
    "DARK_SPECK_PX",
    "DEPTH_BAND_MM",
    "DROPOUT_MAX_OFF_SHARE",
    "DROPOUT_NORMAL_DEG",
    "EDGE_NORMAL_DEG",
    "EDGE_NORMAL_ZONE_PX",
    "EDGE_PX",
    "FIT_SAMPLES",
    "MAX_DROPOUT_MM2",
    "MIN_MATCHED_SHARE",
    "OUTLINE_ALBEDO_RATIO",
    "OUTLINE_REACH_PX",
    "PLAIN_LIT_SHARE",
    "PLAIN_MARGIN_PX",
    "PLAIN_OFF_SURFACE_SHARE",
    "PLAIN_OPENING_SHARE",
    "PLAIN_SUPPORT_MIN_WIDTH_MM",
    "PROTRUSION_RESIDUAL_MM",
    "PROTRUSION_SHARE",
    "SEED_SHARE",
    "SUPPORT_WIDTH_MM",
    "SURFACE_DEGREE",
    "Segmentation",
    "candidate_mask",
    "plain_depth",
    "plain_outline",
    "segment_plate",
]
