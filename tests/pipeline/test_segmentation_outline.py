"""Step 5b of the segmentation: the outline beside lit surroundings, at the glare-free brightness step.

Synthetic ground truth: a plate whose true outline is known, a stereo region that reaches a few pixels
beyond it (the matcher's foreground fattening), and a glare-free brightness with the plate's albedo and
the surroundings' on either side of the true outline; and one scene of the simulator (bench_lights case
11) segmented as the inspection does it, against its true plate mask.
"""

from __future__ import annotations

import numpy as np

from pipeline.segmentation import segment_plate
from pipeline.segmentation.outline import OUTLINE_REACH_PX, lit_surroundings
from pipeline.simulate import CaptureSpec, PlateSpec, simulate_capture
from tests.pipeline.bundles import before_segmentation

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


def _rust_lined(overshoot: int, rust_rows: tuple[int, int], rust_px: int):
    """(region, brightness, lit, truth): ``_scene``'s plate (paint) with a rust patch (0.45 of the paint)
    over rows ``rust_rows`` of its outer ``rust_px`` columns, a glare-lit conveyor (0.2 of the paint,
    0.44 of the rust) beside it, and a stereo region ``overshoot`` px onto the conveyor."""
    region, b, lit, truth = _scene(plate_rim=1.0, beside=0.2)
    b[rust_rows[0] : rust_rows[1], TRUE_LEFT : TRUE_LEFT + rust_px] *= 0.45
    region = np.zeros((H, W), bool)
    region[30:170, TRUE_LEFT - overshoot :] = True
    return region, b, lit, truth


def _found(
    beside: np.ndarray, region: np.ndarray, truth: np.ndarray, rows: slice
) -> tuple[float, bool]:
    """Share of the overshoot on ``rows`` found, and whether no plate pixel more than ``4`` px inside the
    step was taken (anywhere): the local mean's reference, kept, takes a few rust pixels at the step into
    the edge band."""
    overshoot = (region & ~truth)[rows]
    share = np.count_nonzero(beside[rows] & overshoot) / np.count_nonzero(overshoot)
    return share, not (beside & truth)[:, TRUE_LEFT + 4 :].any()


def test_a_rust_patch_lining_the_edge_and_its_reference_is_told_apart_from_the_conveyor():
    # the rust lines the edge over 55 rows (longer than the 45 px box) and 20 px in: the zone inside
    # the outline and the plate's whole reference zone there. Its mean reads the rust, and the conveyor
    # ~0.44 of it, over OUTLINE_ALBEDO_RATIO: the local mean alone found half of the overshoot on those
    # rows. The paint beside the rust, within the box along the edge, tells what steel may be; the rust
    # what the plate's darker pixels are
    region, b, lit, truth = _rust_lined(OVERSHOOT, (70, 125), rust_px=20)
    beside = lit_surroundings(region, b, lit, OUTLINE_REACH_PX)
    share, plate_kept = _found(beside, region, truth, slice(70, 125))
    assert share >= 0.95 and plate_kept


def test_surroundings_matched_beyond_the_matchers_reach_are_cut_as_far_as_they_are_seen():
    # the conveyor matched at its own depth within the depth band (38 mm below the plate's edge, inside
    # 50 mm): the region reaches 18 px onto it, beyond the matcher's fattening, and the plate's reference
    # zone holds conveyor too. All but the column that the blur mixes with the plate at the step is found
    region, b, lit, truth = _rust_lined(18, (0, 0), rust_px=0)
    beside = lit_surroundings(region, b, lit, OUTLINE_REACH_PX)
    share, plate_kept = _found(beside, region, truth, slice(40, 160))
    assert share >= 0.9 and plate_kept


def test_a_rust_patch_filling_every_reference_is_left_to_the_depth():
    # the limit: no paint within reach to tell what steel may be, so the conveyor (0.44 of the rust)
    # could be a darker coating of the plate: nothing is cut
    region, b, lit, _truth = _rust_lined(OVERSHOOT, (0, H), rust_px=W)
    assert not lit_surroundings(region, b, lit, OUTLINE_REACH_PX).any()


def test_a_rust_patch_at_the_edge_beside_a_glare_lit_conveyor_is_told_apart(tmp_path):
    # bench_lights case 11, seed 1 (simulate_capture seed 101): a broad lobe (18 LEDs, shininess 15) lights
    # the dark conveyor (albedo 0.05) into the candidates beside the plate's left edge, where a rust patch
    # (albedo ~0.34) lines it; the stereo matcher carries the plate's depth up to 7 px onto the conveyor
    # there. In the median sample the conveyor read 0.37 of the plate just inside (0.36 tells them apart)
    # and 205 conveyor px stayed in the mask; in the darkest quarter's brightest sample (the glare-free
    # brightness) it reads ~0.3. Only the truth decides here, never the deviation.
    near = dict(near_field_mm=2800.0, light_elevation_deg=30.0, led_mu=1.5)
    spec = CaptureSpec(width=1224, height=1024, n_lights=18, specular=0.5, shininess=15.0, **near)
    out = simulate_capture(tmp_path / "case11", plate=PlateSpec(), capture=spec, seed=101)
    cap, pre, cand, depth = before_segmentation(out)
    seg = segment_plate(
        pre.brightness,
        depth,
        cap.rig.left.K,
        seen=pre.seen,
        candidates=cand,
        glare_free=pre.glare_free,
    )  # no normals: under point lights the inspection has none at segmentation
    with np.load(out / "truth.npz") as z:
        truth = z["mask"]
    # the conveyor beside the rust is lit (a candidate) and matched at the plate's depth ...
    rows, cols = slice(495, 556), slice(176, 188)
    assert np.count_nonzero(cand[rows, cols] & ~truth[rows, cols]) > 200
    # ... yet no pixel off the plate is measured (the median sample's outline kept 205)
    assert np.count_nonzero(seg.mask & ~truth) <= 20
    # and the plate is not cut for it: the mask and its edge band leave under 1 % of the truth out
    assert np.count_nonzero(truth & ~(seg.mask | seg.edge_band)) < 0.01 * np.count_nonzero(truth)
