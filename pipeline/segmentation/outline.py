"""Step 5b: the outline where the stereo depth cannot draw it, at the brightness step between the plate and
lit surroundings.

The stereo matcher's correlation window straddles the plate's edge and gives its outer pixels the plate's
depth (foreground fattening): next to darkness the candidates bound the plate there, but next to
surroundings lit well enough to be candidates (a conveyor under a broad glare lobe beside a plate's dim
edge, bench_lights case 11) nothing did, and the plate reached up to ``OUTLINE_REACH_PX`` onto them, with
their flat normals bending the measured edge. Where the conveyor is matched at its own depth, within the
depth band of the plate's surface (38 mm below the plate's edge against a 50 mm band), the plate reaches
further still. There the plate and what lies beside it still differ in the glare-free brightness (the
brightest of the darkest quarter of the samples, which the lobe lights least,
:attr:`pipeline.preprocess.Preprocessed.glare_free`) mostly by their albedos.

The plate's reference lies ``reach_px`` to ``2 reach_px`` inside the outline, over a box of ``4
reach_px + 1`` px. Where most of the lit pixels within reach outside are darker than
``OUTLINE_ALBEDO_RATIO`` times the plate's reference (no painted or rusty steel is that much darker than
the steel beside it), the region's pixels nearer the outside's brightness than the plate's level, and
joined to the outside through such pixels, are surroundings. Two references are used, and what either
finds is cut: the plate's local mean (ratio and level; within ``reach_px`` of the outline), and its two
classes (:func:`_plate_classes`: the brighter, the paint beside a rust patch, for the ratio, as its
derivation says, the darkest steel against the brightest; the darker, the rust, for the level; within
``2 reach_px`` steps, the box's half width, as far as the comparison sees lit pixels outside). Elsewhere
(a lit floor as bright as the plate, a plate's own unmatched rim) nothing changes and the depth alone
draws the outline.

The local mean alone read a rust patch lining the edge as the plate: the glare-lit dark conveyor
(albedo 0.05-0.07) reads ~0.4 of the rust (0.25-0.45) even in the darkest samples, at or over the ratio,
so 124 px of conveyor stayed in the mask on bench_lights case 13 seed -39; and a conveyor matched at its
own depth 19 px beyond the plate (case 14 seed -29 at 2448x2048) was beyond its reach, with conveyor in
its reference zone. The classes tell both apart as long as some paint lies within the box along the
edge. The local mean is kept beside them: its level (the midpoint to the outside) takes a few rust
pixels at the step into the edge band, and the fusion of the glossy LED cells was measured with those
masks (docs/figures.md).

Limits: a rust patch that lines the edge over every box's reference (no brighter steel within ``2
reach_px`` along and inside it) is not told from a glare-lit conveyor, and the depth's outline stays
there; surroundings matched within the depth band further than ``2 reach_px`` onto them are not
examined.
"""

from __future__ import annotations

import cv2
import numpy as np

from .classify import grow_within

#: How far (px, at the depth's own resolution) the stereo matcher may carry the plate's depth onto what lies
#: beside it: its correlation window (Gaussian, std REFINE_SIGMA_PX = 3 px, to 3 std) and half the SGBM block
#: (BLOCK_SIZE = 5): 9 + 2 px.
OUTLINE_REACH_PX = 11
#: A lit pixel just outside whose glare-free brightness is below this share of the plate's just inside is not
#: plate: painted and rusty steel's albedos span 0.25-0.7 (see candidates.DARK_FRACTION), 0.25 / 0.7.
OUTLINE_ALBEDO_RATIO = 0.36


def _local_mean(values: np.ndarray, where: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean of ``values`` over ``where`` in a ``size`` box around each pixel, and the share of the box in ``where``."""
    w = where.astype(np.float32)
    share = cv2.blur(w, (size, size), borderType=cv2.BORDER_CONSTANT)
    total = cv2.blur(values * w, (size, size), borderType=cv2.BORDER_CONSTANT)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(share > 0, total / np.maximum(share, 1e-12), np.nan)
    return mean.astype(np.float32), share


def _plate_classes(
    b: np.ndarray, core: np.ndarray, mean: np.ndarray, size: int
) -> tuple[np.ndarray, np.ndarray]:
    """The plate's brighter and darker brightness classes over ``core`` in a ``size`` box around each
    pixel (``mean``: the core's local mean).

    The brighter class is the mean of the core's pixels at or above the local mean (the paint beside a rust
    patch, the plate beside surroundings the depth band let into the core); a pixel whose box holds no core
    takes the brighter class of the boxes around it. The darker class is the mean of the pixels below the
    mean of those that may be steel beside it (not under ``OUTLINE_ALBEDO_RATIO`` of the brighter class): a
    rust patch beside paint, the plate's own texture on a plate of one coating.
    """
    with np.errstate(invalid="ignore"):
        bright, _ = _local_mean(b, core & (b >= mean), size)
        steel = core & (b >= OUTLINE_ALBEDO_RATIO * bright)
        steel_mean, _ = _local_mean(b, steel, size)
        dark, _ = _local_mean(b, steel & (b < steel_mean), size)
    known = np.isfinite(bright)
    bright = np.where(known, bright, _local_mean(np.nan_to_num(bright), known, size)[0])
    return bright, np.where(np.isnan(dark), steel_mean, dark)


def _nearer_outside(
    b: np.ndarray,
    ring: np.ndarray,
    ring_share: np.ndarray,
    reference: np.ndarray,
    level: np.ndarray,
    in_share: np.ndarray,
    size: int,
) -> np.ndarray:
    """Pixels nearer in brightness to the lit surroundings (``ring``; ``ring_share`` its share of each
    ``size`` box) in their box than to the plate's ``level``, where most of those surroundings are darker
    than ``OUTLINE_ALBEDO_RATIO`` times the plate's ``reference`` (no painted or rusty steel is that much
    darker than the steel beside it; the rest is plate the matcher left unmatched at its rim, or
    surroundings as bright as the plate)."""
    with np.errstate(invalid="ignore"):
        dim = ring & (b < OUTLINE_ALBEDO_RATIO * reference)
    outside, dim_share = _local_mean(b, dim, size)
    with np.errstate(invalid="ignore", divide="ignore"):
        apart = (in_share > 0) & (dim_share > 0.5 * ring_share) & (ring_share > 0)
        nearer: np.ndarray = apart & (b < 0.5 * (level + outside))
    return nearer


def lit_surroundings(
    region: np.ndarray, brightness: np.ndarray, lit: np.ndarray, reach_px: int
) -> np.ndarray:
    """The region's pixels near its outline that are lit surroundings, by brightness.

    Parameters
    ----------
    region : (H, W) bool
        The plate as the stereo depth drew it.
    brightness : (H, W) float32
        A glare-free brightness (any linear unit, finite), e.g. the median photometric sample.
    lit : (H, W) bool
        Pixels outside ``region`` that are lit (candidates): the surroundings whose brightness is compared.
    reach_px : int
        How far the matcher carries the plate's depth (>= 1): the plate's reference lies ``reach_px`` to
        ``2 reach_px`` inside the outline, the surroundings within ``reach_px`` outside, each compared over
        a box of ``4 reach_px + 1`` px.

    Returns
    -------
    (H, W) bool
        The region's pixels joined to the outside through pixels that read as the lit surroundings within
        ``reach_px`` outside (:func:`_nearer_outside`) by either reference: the plate's local mean (within
        ``reach_px`` of the outline), or its two classes (:func:`_plate_classes`: the brighter for the
        ratio, the darker for the level; within ``2 reach_px`` steps, the box's half width, for surroundings
        matched at their own depth within the depth band reach beyond the matcher's fattening).
    """
    outside_lit = lit & ~region
    if reach_px < 1 or not outside_lit.any():
        return np.zeros(region.shape, bool)
    b = cv2.GaussianBlur(brightness.astype(np.float32), (0, 0), 1.0)
    depth_in = cv2.distanceTransform(region.view(np.uint8), cv2.DIST_L2, 3)
    depth_out = cv2.distanceTransform((~region).view(np.uint8), cv2.DIST_L2, 3)
    core = region & (depth_in > reach_px) & (depth_in <= 2 * reach_px)
    ring = outside_lit & (depth_out <= reach_px)
    size = 4 * reach_px + 1
    mean, in_share = _local_mean(b, core, size)
    bright, dark = _plate_classes(b, core, mean, size)
    ring_share = cv2.blur(ring.astype(np.float32), (size, size), borderType=cv2.BORDER_CONSTANT)
    by_mean = _nearer_outside(b, ring, ring_share, mean, mean, in_share, size)
    by_mean &= region & (depth_in <= reach_px)
    by_classes = region & _nearer_outside(b, ring, ring_share, bright, dark, in_share, size)
    # joined to the outside through such pixels: grown from those touching it
    touching = cv2.dilate((~region).view(np.uint8), np.ones((3, 3), np.uint8)).view(bool)
    by_mean = grow_within(touching & by_mean, by_mean, reach_px)
    found: np.ndarray = by_mean | grow_within(touching & by_classes, by_classes, 2 * reach_px)
    return found
