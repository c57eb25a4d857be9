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

The plate's reference lies ``reach_px`` to ``2 reach_px`` inside the outline, in two classes over a box
of ``4 reach_px + 1`` px: the brighter (the mean of what is at or above the local mean: the paint beside a
rust patch) and the darker (the mean of the lower half of what may be steel beside the brighter). Where
most of the lit pixels within reach outside are darker than ``OUTLINE_ALBEDO_RATIO`` times the brighter
class (no painted or rusty steel is that much darker than the steel beside it), the region's pixels nearer
the outside's brightness than the darker class, and joined to the outside through such pixels within the
box's half width, are surroundings. Elsewhere (a lit floor as bright as the plate, a plate's own unmatched
rim) nothing changes and the depth alone draws the outline.

The local mean the reference was before read a rust patch lining the edge as the plate: the glare-lit dark
conveyor (albedo 0.05) reads ~0.43 of the rust (0.34) even in the darkest samples, over the ratio, so
124 px of conveyor stayed in the mask on bench_lights case 13 seed -39; and the midpoint between that mean
and the outside cut rust pixels beyond the step where paint was near. The classes tell both apart as long
as some paint lies within the box along the edge.

Limits: a rust patch that lines the edge over every box's reference (no brighter steel within ``2
reach_px`` along and inside it) is not told from a glare-lit conveyor, and the depth's outline stays
there (docs/figures.md).
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


def _plate_levels(
    b: np.ndarray, core: np.ndarray, size: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The plate's brighter and darker brightness classes over ``core`` in a ``size`` box around each
    pixel, and the share of the box in ``core``.

    The brighter class is the mean of the core's pixels at or above the local mean (the paint beside a rust
    patch, the plate beside surroundings the depth band let into the core); the darker class is the mean of
    the pixels below the mean of those that may be steel beside it (not under ``OUTLINE_ALBEDO_RATIO`` of
    the brighter class): a rust patch beside paint, the plate's own texture on a plate of one coating.
    """
    mean, share = _local_mean(b, core, size)
    with np.errstate(invalid="ignore"):
        bright, _ = _local_mean(b, core & (b >= mean), size)
        steel = core & (b >= OUTLINE_ALBEDO_RATIO * bright)
        steel_mean, _ = _local_mean(b, steel, size)
        dark, _ = _local_mean(b, steel & (b < steel_mean), size)
    return bright, np.where(np.isnan(dark), steel_mean, dark), share


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
        Pixels of ``region`` nearer in brightness to the lit surroundings within ``reach_px`` outside than to
        the plate's darker class further inside (:func:`_plate_levels`), where most of those surroundings
        are darker than ``OUTLINE_ALBEDO_RATIO`` times the plate's brighter class, joined to the outside
        through such pixels within ``2 reach_px`` steps (the box's half width: surroundings matched at
        their own depth within the depth band reach beyond the matcher's fattening).
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
    bright, dark, in_share = _plate_levels(b, core, size)
    # a pixel outside whose box holds no core takes the brighter class of the boxes around it
    known = np.isfinite(bright)
    bright = np.where(known, bright, _local_mean(np.nan_to_num(bright), known, size)[0])
    with np.errstate(invalid="ignore"):
        # the lit pixels just outside far darker than the plate's steel just inside: surroundings (the
        # rest is plate the matcher left unmatched at its rim, or surroundings as bright as the plate)
        dim = ring & (b < OUTLINE_ALBEDO_RATIO * bright)
    outside, dim_share = _local_mean(b, dim, size)
    ring_share = cv2.blur(ring.astype(np.float32), (size, size), borderType=cv2.BORDER_CONSTANT)
    with np.errstate(invalid="ignore", divide="ignore"):
        # told apart where most of the lit pixels just outside are such surroundings
        apart = (in_share > 0) & (dim_share > 0.5 * ring_share) & (ring_share > 0)
        darker = b < 0.5 * (dark + outside)
    candidates = region & apart & darker
    # joined to the outside through such pixels: grown from those touching it
    touching = candidates & cv2.dilate((~region).view(np.uint8), np.ones((3, 3), np.uint8)).view(
        bool
    )
    return grow_within(touching, candidates, 2 * reach_px)
