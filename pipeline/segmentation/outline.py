"""Step 5b: the outline where the stereo depth cannot draw it, at the brightness step between the plate and
lit surroundings.

The stereo matcher's correlation window straddles the plate's edge and gives its outer pixels the plate's
depth (foreground fattening): next to darkness the candidates bound the plate there, but next to
surroundings lit well enough to be candidates (a conveyor under a broad glare lobe beside a plate's dim
edge, bench_lights case 11) nothing did, and the plate reached up to ``OUTLINE_REACH_PX`` onto them, with
their flat normals bending the measured edge. There the plate and what lies beside it still differ in
the glare-free brightness (the brightest of the darkest quarter of the samples, which the lobe lights
least, :attr:`pipeline.preprocess.Preprocessed.glare_free`) mostly by their albedos: where most of the
lit pixels within reach outside are darker than ``OUTLINE_ALBEDO_RATIO``
times the plate's mean further inside (no painted or rusty steel is that much darker than the plate beside
it), the region's pixels within reach that are nearer the outside's brightness than the plate's, and
joined to the outside through such pixels, are surroundings. Elsewhere (a lit floor as bright as the
plate, a plate's own unmatched rim) nothing changes and the depth alone draws the outline.

Limits: even there the lobe is not gone. Beside a rust patch (albedo ~0.34) at the plate's edge the
glare-lit dark conveyor (0.05) reads ~0.43 of the rust (0.53 in the median sample, which kept 205 px of
it in the mask on bench_lights case 11 seed 1); it is told apart because the plate within reach further
inside is partly paint (its local mean sets the ratio: ~0.3). A rust patch that lined the edge over the
whole reference zone (``reach_px`` to ``2 reach_px`` inside) would not be, and the depth's outline would
stay (docs/figures.md).
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


def lit_surroundings(
    region: np.ndarray, brightness: np.ndarray, lit: np.ndarray, reach_px: int
) -> np.ndarray:
    """The region's pixels within ``reach_px`` of its outline that are lit surroundings, by brightness.

    Parameters
    ----------
    region : (H, W) bool
        The plate as the stereo depth drew it.
    brightness : (H, W) float32
        A glare-free brightness (any linear unit, finite), e.g. the median photometric sample.
    lit : (H, W) bool
        Pixels outside ``region`` that are lit (candidates): the surroundings whose brightness is compared.
    reach_px : int
        How far from the outline pixels are examined (>= 1).

    Returns
    -------
    (H, W) bool
        Pixels of ``region`` within ``reach_px`` of its outline nearer in brightness to the lit surroundings
        within ``reach_px`` outside than to the plate within ``reach_px`` further inside, where most of those
        surroundings are darker than ``OUTLINE_ALBEDO_RATIO`` times the plate's (a local mean over a box of
        ``4 reach_px + 1`` px), joined to the outside through such pixels.
    """
    outside_lit = lit & ~region
    if reach_px < 1 or not outside_lit.any():
        return np.zeros(region.shape, bool)
    b = cv2.GaussianBlur(brightness.astype(np.float32), (0, 0), 1.0)
    depth_in = cv2.distanceTransform(region.view(np.uint8), cv2.DIST_L2, 3)
    depth_out = cv2.distanceTransform((~region).view(np.uint8), cv2.DIST_L2, 3)
    zone = region & (depth_in <= reach_px)
    core = region & (depth_in > reach_px) & (depth_in <= 2 * reach_px)
    ring = outside_lit & (depth_out <= reach_px)
    size = 4 * reach_px + 1
    inside, in_share = _local_mean(b, core, size)
    with np.errstate(invalid="ignore"):
        # the lit pixels just outside far darker than the plate just inside: surroundings (the rest is
        # plate the matcher left unmatched at its rim, or surroundings as bright as the plate)
        dim = ring & (b < OUTLINE_ALBEDO_RATIO * inside)
    outside, dim_share = _local_mean(b, dim, size)
    ring_share = cv2.blur(ring.astype(np.float32), (size, size), borderType=cv2.BORDER_CONSTANT)
    with np.errstate(invalid="ignore", divide="ignore"):
        # told apart where most of the lit pixels just outside are such surroundings
        apart = (in_share > 0) & (dim_share > 0.5 * ring_share) & (ring_share > 0)
        darker = b < 0.5 * (inside + outside)
    candidates = zone & apart & darker
    # joined to the outside through such pixels: grown from those touching it
    touching = candidates & cv2.dilate((~region).view(np.uint8), np.ones((3, 3), np.uint8)).view(
        bool
    )
    return grow_within(touching, candidates, reach_px)
