"""Plain scenes (:mod:`pipeline.segmentation.plain`): when the brightness mask may stand for the plate."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from pipeline.run import inspect
from pipeline.segmentation import plain_depth
from pipeline.simulate import (
    CaptureSpec,
    Dent,
    Floor,
    PlateSpec,
    rail_supports,
    simulate_capture,
)

K = np.array([[433.0, 0.0, 306.0], [0.0, 433.0, 256.0], [0.0, 0.0, 1.0]])  # 6.9 mm/px at 3 m
SHAPE = (512, 612)
RAIL_ROWS = (slice(100, 122), slice(380, 402))  # 22 px: 150 mm rails
RAIL_COLS = (slice(29, 89), slice(517, 577))  # 60 px (415 mm) beyond the plate's curved ends


def _curved_plate(rails: str | None) -> tuple[np.ndarray, np.ndarray]:
    """Brightness mask and stereo depth of a 3 m cylinder R 5000 mm at 3 m, curved along the image rows;
    ``rails`` "unmatched" or "flat": two rails under each curved end, 150 mm wide, whose bright tops
    join the brightness mask, with no stereo depth (tops that show the pair nothing to match) or flat
    at the depth of the plate's edge (where its continuation turns away)."""
    h, w = SHAPE
    u = np.arange(w, dtype=np.float64)[None, :].repeat(h, axis=0)
    x_mm = (u - K[0, 2]) * 3000.0 / K[0, 0]
    depth = 3000.0 + x_mm**2 / (2.0 * 5000.0)
    mask = np.zeros(SHAPE, bool)
    mask[30:470, 89:517] = True
    depth += np.random.default_rng(0).normal(0.0, 1.0, SHAPE)
    for rows in RAIL_ROWS if rails else ():
        for cols, edge in zip(RAIL_COLS, (89, 516)):
            mask[rows, cols] = True
            depth[rows, cols] = np.nan if rails == "unmatched" else depth[rows, edge][:, None]
    return mask, np.where(mask, depth, np.nan)


def test_a_plate_alone_is_plain():
    mask, depth = _curved_plate(None)
    assert plain_depth(mask, depth, K)


@pytest.mark.parametrize("rails", ["unmatched", "flat"])
def test_rails_reaching_out_beside_the_plate_are_not_plain(rails):
    mask, depth = _curved_plate(rails)
    assert not plain_depth(mask, depth, K)


def test_unmatched_slivers_along_the_rim_stay_plain():
    # the stereo pair leaves a few pixels along the plate's outline unmatched (its windows straddle the
    # edge); narrow parts of the mask there are mostly unmatched, but no support is that thin
    mask, depth = _curved_plate(None)
    rim = mask & ~np.pad(mask[3:-3, 3:-3], 3)
    depth[rim] = np.nan
    assert plain_depth(mask, depth, K)


def _inspected(root: Path, plate: PlateSpec, seed: int) -> tuple[dict[str, object], np.ndarray]:
    bundle = simulate_capture(
        root / "bundle", plate=plate, capture=CaptureSpec(width=612, height=512), seed=seed
    )
    doc = inspect(bundle, bundle / "target.json", out_dir=root / "out").document
    measured = np.isfinite(np.load(root / "out" / "depth.npy"))
    return doc, measured & ~np.load(bundle / "truth.npz")["mask"]


def test_a_plate_on_rails_over_a_dark_floor_leaves_the_rails_out(tmp_path):
    """612 x 512, 12 distant lights, seed 3: the rails' bright tops joined the brightness mask, the scene
    was taken as plain and measured on that mask with its rails (4 807 px, radius +0.31 %, max 165 mm,
    fail); it is now segmented, which leaves the rails out."""
    floor = Floor(
        gap_mm=300.0, albedo=0.03, texture=0.0, supports=rail_supports((3000.0, 3000.0), 300.0, 3)
    )
    doc, off = _inspected(tmp_path, PlateSpec(floor=floor), seed=3)
    assert np.count_nonzero(off) < 100, np.count_nonzero(off)  # the outline's own pixels only
    assert doc["verdict"] == "pass" and abs(float(doc["radius_error_pct"])) < 0.1, doc  # type: ignore[arg-type]


def test_a_bent_corner_over_a_dark_background_is_judged(tmp_path):
    # a corner bent 15 mm towards the cameras is the plate's own, matched by the stereo pair and within the
    # depth band: the scene stays plain and the corner fails with its own depth (a support test on the
    # brightness mask took it for a support and cut it away)
    corner = Dent(x_mm=1500.0, y_mm=1500.0, radius_mm=250.0, depth_mm=-15.0)
    doc, _ = _inspected(tmp_path, PlateSpec(dents=(corner,)), seed=5)
    assert doc["verdict"] == "fail"
    assert doc["deviation_mm"]["max_abs"] > 8.0, doc  # type: ignore[index]
