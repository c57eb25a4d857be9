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
