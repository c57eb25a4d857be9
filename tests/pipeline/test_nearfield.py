"""Near-field photometric normals against the simulator's truth (issue 10, item 2)."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.io import load_capture
from pipeline.lights.nearfield import estimate_normals_near
from pipeline.preprocess import preprocess
from pipeline.simulate import CaptureSpec, PlateSpec, simulate_capture
from pipeline.surface.normals import estimate_normals


@pytest.fixture(scope="module")
def near_capture(tmp_path_factory):
    """12 LEDs 2.8 m above a cylinder, 30 deg from the axis, beam profile mu 1.5, no noise."""
    out = tmp_path_factory.mktemp("near")
    bundle = simulate_capture(
        out,
        plate=PlateSpec(),
        capture=CaptureSpec(
            near_field_mm=2800.0,
            light_elevation_deg=30.0,
            led_mu=1.5,
            noise=0.0,
            width=320,
            height=256,
        ),
        seed=1,
    )
    cap = load_capture(bundle)
    return cap, preprocess(cap), np.load(bundle / "truth.npz")


def _angles_deg(a, b, mask):
    dot = np.clip(np.einsum("hwc,hwc->hw", a, b)[mask], -1.0, 1.0)
    return np.degrees(np.arccos(dot))


@pytest.mark.parametrize("method", ["robust", "lstsq"])
def test_point_lights_recover_the_true_normals(near_capture, method):
    cap, pre, truth = near_capture
    mask = pre.mask & truth["mask"]
    depth = np.where(mask, truth["depth_mm"], np.nan)
    field = estimate_normals_near(
        pre.images, cap.lights, depth, cap.rig.left.K, mask, valid=pre.valid, method=method
    )
    err = _angles_deg(field.normals, truth["normals"], field.mask & mask)
    # noise-free 16-bit images: quantisation and the bilinear undistortion of the images are all that is left
    assert np.percentile(err, 95) < 0.1, np.percentile(err, 95)
    assert field.n_filled == 0


def test_the_distant_model_is_wrong_by_degrees_under_leds(near_capture):
    """What near-field normals are for: the same images read with directions from the plate centre."""
    cap, pre, truth = near_capture
    mask = pre.mask & truth["mask"]
    nominal = cap.lights.nominal_directions(truth["T_cam_plate"][:3, 3])
    images = pre.images * (cap.lights.intensity / nominal.intensity)[:, None, None].astype(
        np.float32
    )
    field = estimate_normals(images, nominal.directions, mask, valid=pre.valid, method="lstsq")
    err = _angles_deg(field.normals, truth["normals"], field.mask & mask)
    assert np.percentile(err, 95) > 5.0


def test_a_depth_error_turns_the_normals_only_a_little(near_capture):
    """The alternation starts from the stereo surface: 20 mm off at 3 m costs a fraction of a degree."""
    cap, pre, truth = near_capture
    mask = pre.mask & truth["mask"]
    depth = np.where(mask, truth["depth_mm"] + 20.0, np.nan)
    field = estimate_normals_near(
        pre.images, cap.lights, depth, cap.rig.left.K, mask, valid=pre.valid
    )
    assert np.median(_angles_deg(field.normals, truth["normals"], field.mask & mask)) < 0.6


def test_bad_inputs_are_named(near_capture):
    cap, pre, truth = near_capture
    mask = pre.mask & truth["mask"]
    depth = np.where(mask, truth["depth_mm"], np.nan)
    K = cap.rig.left.K
    bad = depth.copy()
    bad[np.argwhere(mask)[0][0], np.argwhere(mask)[0][1]] = np.nan
    with pytest.raises(ValueError, match="depth_mm: expected finite depths > 0 mm on the mask"):
        estimate_normals_near(pre.images, cap.lights, bad, K, mask)
    with pytest.raises(ValueError, match="lights: expected Lights for 11 images"):
        estimate_normals_near(pre.images[:11], cap.lights, depth, K, mask)
    with pytest.raises(ValueError, match="method: expected one of"):
        estimate_normals_near(pre.images, cap.lights, depth, K, mask, method="fast")
