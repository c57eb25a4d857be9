"""Plain scenes (:mod:`pipeline.segmentation.plain`): when the brightness mask may stand for the plate."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.run import inspect
from pipeline.segmentation import plain_depth
from pipeline.simulate import CaptureSpec, Floor, PlateSpec, rail_supports, simulate_capture

K = np.array([[433.0, 0.0, 306.0], [0.0, 433.0, 256.0], [0.0, 0.0, 1.0]])  # 6.9 mm/px at 3 m
SHAPE = (512, 612)
RAIL_ROWS = (slice(100, 122), slice(380, 402))  # 22 px: 150 mm rails at 3 m


def _curved_plate(rails: bool) -> tuple[np.ndarray, np.ndarray]:
    """Brightness mask and stereo depth of a 3 m cylinder R 5000 mm at 3 m, curved along the image rows,
    and with ``rails`` two rails 150 mm wide under its curved ends, reaching 60 px (415 mm) beyond them,
    whose bright tops join the brightness mask 30 mm nearer than the plate's continuation (within the
    depth band that keeps a floor out)."""
    h, w = SHAPE
    u = np.arange(w, dtype=np.float64)[None, :].repeat(h, axis=0)
    x_mm = (u - K[0, 2]) * 3000.0 / K[0, 0]
    depth = 3000.0 + x_mm**2 / (2.0 * 5000.0)
    mask = np.zeros(SHAPE, bool)
    mask[30:470, 89:517] = True
    if rails:
        for rows in RAIL_ROWS:
            for beyond in (slice(29, 89), slice(517, 577)):
                mask[rows, beyond] = True
                depth[rows, beyond] -= 30.0
    noise = np.random.default_rng(0).normal(0.0, 1.0, SHAPE)
    return mask, np.where(mask, depth + noise, np.nan)


def test_a_plate_alone_is_plain():
    mask, depth = _curved_plate(rails=False)
    assert plain_depth(mask, depth, K)


def test_rails_reaching_out_beside_the_plate_at_its_depth_are_not_plain():
    # within the depth band of the plate's smooth surface near its edge, so only the support test of the
    # segmentation's step 3 tells them from the plate
    mask, depth = _curved_plate(rails=True)
    assert not plain_depth(mask, depth, K)


def test_a_plate_on_rails_over_a_dark_floor_leaves_the_rails_out(tmp_path):
    """612 x 512, 12 distant lights, seed 3: the rails' bright tops joined the brightness mask, the scene
    was taken as plain and measured on that mask with its rails (4 807 px, radius +0.31 %, max 165 mm,
    fail); it is now segmented, which leaves the supports out."""
    floor = Floor(
        gap_mm=300.0, albedo=0.03, texture=0.0, supports=rail_supports((3000.0, 3000.0), 300.0, 3)
    )
    bundle = simulate_capture(
        tmp_path / "bundle",
        plate=PlateSpec(floor=floor),
        capture=CaptureSpec(width=612, height=512),
        seed=3,
    )
    doc = inspect(bundle, bundle / "target.json", out_dir=tmp_path / "out").document
    truth = np.load(bundle / "truth.npz")
    measured = np.isfinite(np.load(tmp_path / "out" / "depth.npy"))
    off = np.count_nonzero(measured & ~truth["mask"])
    assert off < 0.002 * np.count_nonzero(truth["mask"]), off  # the outline's own pixels only
    assert doc["verdict"] == "pass" and abs(doc["radius_error_pct"]) < 0.1, doc


@pytest.mark.parametrize("rails", [False, True])
def test_plain_depth_needs_a_sheet_and_no_support(rails):
    # the two checks together: a floor far behind the plate in the mask is not plain either way
    mask, depth = _curved_plate(rails)
    mask[480:505, :] = True
    depth[480:505, :] = 3300.0
    assert not plain_depth(mask, depth, K)
