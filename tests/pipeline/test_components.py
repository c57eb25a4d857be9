"""Regions of a mask (pipeline.solvers.components): connected components' areas, the bounding box."""

from __future__ import annotations

import cv2
import numpy as np

from pipeline.solvers import bounding_box, labelled


def test_labelled_gives_opencvs_labels_and_areas():
    rng = np.random.default_rng(0)
    binary = rng.random((40, 50)) > 0.6
    n, labels, areas = labelled(binary, connectivity=4)
    ref_n, ref_labels, stats, _ = cv2.connectedComponentsWithStats(
        binary.view(np.uint8), connectivity=4
    )
    assert n == ref_n
    np.testing.assert_array_equal(labels, ref_labels)
    np.testing.assert_array_equal(areas, stats[:, cv2.CC_STAT_AREA])


def test_bounding_box_with_a_margin_stays_within_the_grid():
    mask = np.zeros((20, 30), bool)
    assert bounding_box(mask) is None
    mask[3, 5] = mask[10, 27] = True
    assert bounding_box(mask) == (slice(3, 11), slice(5, 28))
    assert bounding_box(mask, 4) == (slice(0, 15), slice(1, 30))
