"""Step 5b of the segmentation: the outline beside lit surroundings, at the glare-free brightness step.

Synthetic ground truth: a plate whose true outline is known, a stereo region that reaches a few pixels
beyond it (the matcher's foreground fattening), and a glare-free brightness with the plate's albedo and
the surroundings' on either side of the true outline.
"""

from __future__ import annotations

import numpy as np

from pipeline.segmentation.outline import OUTLINE_REACH_PX, lit_surroundings

H, W = 200, 240
TRUE_LEFT = 80  # the plate's true outline: columns >= TRUE_LEFT, rows 30..169
OVERSHOOT = 7  # the stereo region reaches this many px onto what lies beside the plate


def _scene(plate_rim: float, beside: float, seed: int = 3):
    """(region, brightness, lit, truth): plate brightness ~0.25 (its outer 10 px ``plate_rim`` times that),
    what lies beside it ``beside`` times that; everything lit (candidates)."""
    rng = np.random.default_rng(seed)
    truth = np.zeros((H, W), bool)
    truth[30:170, TRUE_LEFT:] = True
    region = np.zeros((H, W), bool)
    region[30:170, TRUE_LEFT - OVERSHOOT :] = True
    b = np.full((H, W), 0.25 * beside, np.float32)
    b[truth] = 0.25
    b[30:170, TRUE_LEFT : TRUE_LEFT + 10] = 0.25 * plate_rim
    b *= (1 + 0.05 * rng.standard_normal((H, W))).astype(np.float32)  # texture and noise
    lit = np.zeros((H, W), bool)
    lit[20:180, 40:] = True
    return region, b, lit, truth


def test_a_dim_conveyor_taken_in_by_the_stereo_depth_is_cut_at_the_brightness_step():
    region, b, lit, truth = _scene(plate_rim=1.0, beside=0.25)
    beside = lit_surroundings(region, b, lit, OUTLINE_REACH_PX)
    overshoot = region & ~truth
    rows = slice(40, 160)  # away from the corners
    # the whole overshoot is found, and no plate pixel beyond the mixed one at the step
    assert np.count_nonzero(beside[rows] & overshoot[rows]) >= 0.95 * np.count_nonzero(
        overshoot[rows]
    )
    assert not (beside & truth)[:, TRUE_LEFT + 1 :].any()


def test_a_dark_rim_of_the_plate_itself_is_not_cut():
    # the plate's own darker rim (rust beside paint, 0.55 of it) outside the stereo region: plate, not surroundings
    region, b, lit, truth = _scene(plate_rim=0.55, beside=0.55)
    region = truth & (np.arange(W)[None, :] >= TRUE_LEFT + 6)  # the matcher left the rim unmatched
    assert not lit_surroundings(region, b, lit, OUTLINE_REACH_PX).any()


def test_surroundings_as_bright_as_the_plate_leave_the_outline_to_the_depth():
    region, b, lit, _truth = _scene(plate_rim=1.0, beside=0.9)
    assert not lit_surroundings(region, b, lit, OUTLINE_REACH_PX).any()


def test_darkness_beside_the_plate_changes_nothing():
    region, b, _lit, truth = _scene(plate_rim=1.0, beside=0.05)
    lit = truth | region  # what lies beside is dark: not a candidate
    assert not lit_surroundings(region, b, lit, OUTLINE_REACH_PX).any()
