"""The support test's corners (segmentation step 3): a narrow part that leaves the smooth surface is a
support reaching out of the plate's outline, or the plate's own corner, which the outline tells apart."""

from __future__ import annotations

import cv2
import numpy as np

from pipeline.segmentation.classify import narrow_parts, outline_corners, wide_parts

H, W = 400, 500
MM_PER_PX = 5.0  # the 250 mm support width is 50 px


def _plate(x0: int = 100, y0: int = 80, x1: int = 400, y1: int = 330) -> np.ndarray:
    core = np.zeros((H, W), bool)
    core[y0:y1, x0:x1] = True
    return core


def _parts(core: np.ndarray) -> np.ndarray:
    return wide_parts(narrow_parts(core, MM_PER_PX, 250.0), 2.5)


def test_a_plates_corner_is_a_corner() -> None:
    core = _plate()
    parts = _parts(core)
    assert parts[80:86, 100:106].all()  # the opening cuts the plate's corners: narrow parts
    corners = outline_corners(core, parts, 125.0 / MM_PER_PX)
    assert np.array_equal(corners, parts)


def test_a_corner_bulging_out_a_little_is_still_a_corner() -> None:
    # a corner bent towards the cameras lies a few pixels beyond the edges' lines in the image
    core = _plate()
    core[76:80, 100:112] = True
    core[80:92, 96:100] = True
    parts = _parts(core)
    corners = outline_corners(core, parts, 125.0 / MM_PER_PX)
    assert corners[78, 104] and corners[85, 98]


def test_a_rail_reaching_out_of_an_edge_is_not_a_corner() -> None:
    core = _plate()
    core[180:210, 400:460] = True  # a rail's top 150 mm wide, 300 mm beside the plate
    core[60:80, 300:330] = True  # a shorter stub of another on the top edge
    parts = _parts(core)
    corners = outline_corners(core, parts, 125.0 / MM_PER_PX)
    assert parts[195, 440] and not corners[195, 440]
    assert parts[65, 315] and not corners[65, 315]
    assert corners[82, 102]  # the plate's own corners are


def test_a_rail_at_the_plates_corner_is_not_a_corner() -> None:
    # a rail whose outer side runs on along the plate's side edge: one concavity, beside it
    core = _plate()
    core[330:380, 100:130] = True
    parts = _parts(core)
    corners = outline_corners(core, parts, 125.0 / MM_PER_PX)
    assert parts[360, 115] and not corners[360, 115]


def test_a_part_inside_a_notch_is_not_a_corner() -> None:
    # a support seen in a notch of the outline reaches nowhere beyond the plate's hull
    core = _plate()
    notch = np.zeros((H, W), np.uint8)
    cv2.circle(notch, (250, 330), 60, 1, -1)
    core &= notch == 0
    core[300:330, 240:260] = True  # the support's top in the notch
    parts = _parts(core)
    assert parts[320, 250]
    assert not outline_corners(core, parts, 125.0 / MM_PER_PX)[320, 250]


def test_surroundings_reaching_far_beyond_a_corner_are_not_a_corner() -> None:
    # lit surroundings matched at the plate's depth, a wedge swelling out of its corner, round the outline
    # out like a corner but reach farther beyond it than the opening's radius (125 mm, 25 px here): no
    # corner the opening cut off reaches so far
    core = _plate()
    wedge = np.zeros((H, W), np.uint8)
    cv2.fillConvexPoly(wedge, np.array([[359, 329], [399, 289], [444, 374]], np.int32), 1)
    core |= wedge > 0
    parts = _parts(core)
    assert parts[360, 420]
    assert outline_corners(core, parts, 1e9)[360, 420]  # by its outline alone, a corner
    assert not outline_corners(core, parts, 125.0 / MM_PER_PX)[360, 420]
