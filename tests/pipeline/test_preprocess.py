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
    img[100:103, 200:230] = 0.8   # a 3 px spur
    img[95:108, 225:235] = 0.8    # with a blob at its end
    mask = plate_mask(img, erode_px=2)
    from scipy import ndimage

    assert ndimage.label(mask)[1] == 1
