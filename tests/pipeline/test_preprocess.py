from dataclasses import replace

import cv2
import numpy as np
import pytest

from pipeline.formats import CaptureError
from pipeline.preprocess import plate_mask


def test_plate_mask_finds_a_textured_quadrilateral_on_a_dark_belt():
    rng = np.random.default_rng(1)
    h, w = 240, 320
    yy, xx = np.mgrid[0:h, 0:w]
    # a perspective-looking quadrilateral plate with rust texture on a dim, textured conveyor
    inside = (yy > 30 + 0.05 * xx) & (yy < 210 - 0.03 * xx) & (xx > 40) & (xx < 290)
    img = 0.05 + 0.02 * rng.random((h, w))
    img[inside] = 0.6 + 0.15 * rng.random(np.count_nonzero(inside))
    mask = plate_mask(img, erode_px=0)
    agreement = np.mean(mask == inside)
    assert agreement > 0.99  # only blurred edge pixels may differ
    eroded = plate_mask(img, erode_px=3)
    assert eroded.sum() < mask.sum() and not (eroded & ~mask).any()


def test_plate_mask_refuses_a_dark_image():
    with pytest.raises(CaptureError, match="no light on the plate"):
        plate_mask(np.zeros((50, 60)))


def test_plate_mask_refuses_a_tiny_plate():
    img = np.full((200, 200), 0.05)
    img[100:104, 100:104] = 1.0
    with pytest.raises(CaptureError, match="the plate covers"):
        plate_mask(img, erode_px=0)


def test_plate_mask_is_one_piece_after_erosion():
    # a plate with a thin spur: eroding cuts the spur's tip loose; only the plate may remain
    img = np.full((200, 240), 0.04)
    img[40:160, 40:200] = 0.8
    img[100:103, 200:230] = 0.8  # a 3 px spur
    img[95:108, 225:235] = 0.8  # with a blob at its end
    mask = plate_mask(img, erode_px=2)
    from scipy import ndimage

    assert ndimage.label(mask)[1] == 1


def _sphere_capture(tmp_path, **kwargs):
    from pipeline.io import load_capture
    from tests.pipeline.bundles import write_bundle

    return load_capture(write_bundle(tmp_path, n_lights=6, width=96, height=80, **kwargs))


def test_preprocess_normalises_and_flags_saturation_and_shadows(tmp_path):
    from pipeline.preprocess import preprocess

    cap = _sphere_capture(tmp_path)
    pre = preprocess(cap)
    assert pre.images.shape == (6, 80, 96) and pre.images.dtype == np.float32
    # dark-subtracted and divided by full scale: the sphere's brightest samples are ~0.8 * cos(slant)
    assert 0.5 < float(np.percentile(pre.images[:, pre.mask], 99)) < 0.85
    assert pre.n_saturated == 0
    # lights on a ring: the sphere's rim facing away from a light is in attached shadow for that light
    assert pre.n_shadowed > 0
    assert not pre.valid[:, pre.mask].all()


def test_preprocess_drops_saturated_samples(tmp_path):
    from pipeline.preprocess import preprocess

    img = np.full((80, 96), 65535, np.uint16)
    img[:, :40] = 20000
    cap = _sphere_capture(tmp_path, files={"ps_02.png": img})
    pre = preprocess(cap)
    # the saturated half of image 2 is not valid anywhere inside the plate; the other images are untouched
    right = np.zeros((80, 96), bool)
    right[:, 50:] = True
    assert not pre.valid[2][pre.mask & right].any()
    assert pre.n_saturated >= np.count_nonzero(pre.mask & right)


def test_a_glossy_plates_highlights_do_not_split_its_mask(tmp_path):
    # 18 lights and a lobe half as bright as the diffuse part: the maxima over the lights hold three
    # populations (conveyor, plate, highlights), and Otsu's threshold of the maxima alone fell between
    # the plate and its highlights, leaving a third of the plate out
    from pipeline.io import load_capture
    from pipeline.preprocess import preprocess
    from pipeline.simulate import CaptureSpec, PlateSpec, simulate_capture

    spec = CaptureSpec(n_lights=18, specular=0.5, width=320, height=256)
    bundle = simulate_capture(tmp_path / "glossy", plate=PlateSpec(), capture=spec, seed=1)
    pre = preprocess(load_capture(bundle))
    truth = np.load(bundle / "truth.npz")["mask"]
    assert np.count_nonzero(truth & ~pre.mask) < 0.1 * truth.sum()  # the eroded rim: ~6 %
    assert np.count_nonzero(pre.mask & ~truth) == 0
    assert plate_mask(pre.brightest).sum() < 0.8 * truth.sum()  # the maxima alone: the split


def test_binning_averages_blocks_and_keeps_the_rays(tmp_path):
    from pipeline.preprocess import bin_capture
    from pipeline.surface.normals.noise import image_noise

    cap = _sphere_capture(tmp_path)
    small = bin_capture(cap, 2)
    assert small.images.shape == (6, 40, 48) and small.rig.image_size == (48, 40)
    for full, binned in [
        (cap.images[3], small.images[3]),
        (cap.dark, small.dark),
        (cap.stereo_right, small.stereo_right),
    ]:
        np.testing.assert_allclose(binned, full.reshape(40, 2, 48, 2).mean(axis=(1, 3)), rtol=1e-6)
    # a binned pixel sees the ray through the centre of its 2x2 block, both cameras alike
    for side in ("left", "right"):
        K_full, K_small = getattr(cap.rig, side).K, getattr(small.rig, side).K
        u, v = 17.0, 9.0
        centre = np.linalg.solve(K_full, [2 * u + 0.5, 2 * v + 0.5, 1.0])
        np.testing.assert_allclose(np.linalg.solve(K_small, [u, v, 1.0]), centre, atol=1e-12)
    # a size that is not a whole number of blocks (80 rows by 3): the last rows are left out, the rays
    # still go through the blocks' centres
    thirds = bin_capture(cap, 3)
    assert thirds.images.shape == (6, 26, 32) and thirds.rig.image_size == (32, 26)
    for side in ("left", "right"):
        K_full, K_small = getattr(cap.rig, side).K, getattr(thirds.rig, side).K
        centre = np.linalg.solve(K_full, [3 * 17.0 + 1, 3 * 20.0 + 1, 1.0])
        np.testing.assert_allclose(np.linalg.solve(K_small, [17.0, 20.0, 1.0]), centre, atol=1e-12)
    assert small.rig.rms_px == pytest.approx(cap.rig.rms_px / 2)
    # the sensor's noise, measured on the images as given, falls by the factor
    everywhere = np.ones((80, 96), bool)
    own, dark = small.raw_noise
    np.testing.assert_allclose(own, image_noise(cap.images, everywhere) / 2)
    assert dark == pytest.approx(image_noise(cap.dark[None], everywhere)[0] / 2)
    assert bin_capture(cap, 1) is cap


def test_a_saturated_sample_saturates_its_bin(tmp_path):
    from pipeline.preprocess import bin_capture, preprocess

    img = np.full((80, 96), 20000, np.uint16)
    img[41, 61] = 65535  # one raw sample of the block (20..21, 30..31) once binned
    cap = _sphere_capture(tmp_path, files={"ps_02.png": img})
    small = bin_capture(cap, 2)
    assert small.images[2, 20, 30] == 65535
    assert np.count_nonzero(small.images[2] == 65535) == 1
    pre = preprocess(small)
    # found saturated: the bin and its neighbours (preprocess dilates by one pixel before undistorting)
    assert 1 <= pre.n_saturated <= 9


def test_a_bin_with_saturated_samples_takes_its_brightest():
    # the blocks with a sample at or above the threshold take the block's brightest sample, the
    # others its mean; rows and columns beyond the last whole block (80 by 3: row 79) are left out
    from pipeline.preprocess import _bin_into

    rng = np.random.default_rng(5)
    raw = rng.uniform(1000.0, 2000.0, (80, 97)).astype(np.float32)
    hot = rng.choice(raw.size, 60, replace=False)
    raw.flat[hot] = rng.uniform(3000.0, 4000.0, hot.size)
    raw[79, :] = 5000.0  # beyond the last block of 3 rows
    out = np.empty((26, 32), np.float32)
    _bin_into(raw, out, 3, 3000.0)
    blocks = raw[:78, :96].reshape(26, 3, 32, 3)
    brightest = blocks.max(axis=(1, 3))
    mean = cv2.resize(raw[:78, :96], (32, 26), interpolation=cv2.INTER_AREA)
    np.testing.assert_array_equal(out, np.where(brightest >= 3000.0, brightest, mean))
    assert 0 < np.count_nonzero(brightest >= 3000.0) < out.size


def test_the_working_grid_follows_the_cells_geometry(tmp_path):
    from pipeline.preprocess import working_binning

    cap = _sphere_capture(tmp_path)  # fx 80 px at 1000 mm: 12.5 mm per pixel
    assert cap.working_distance_mm == 1000.0
    assert working_binning(cap, None, 3500.0) == 1
    assert working_binning(cap, 12.0, 3500.0) == 1
    assert working_binning(cap, 25.0, 3500.0) == 2
    assert working_binning(cap, 38.0, 3500.0) == 3
    # without a working distance, the depth assumed
    far = replace(cap, working_distance_mm=None)
    assert working_binning(far, 25.0, 2000.0) == 1
