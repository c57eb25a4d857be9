"""Regions of a mask: connected components with their areas (without the statistics nobody reads), and
the mask's bounding box.

``cv2.connectedComponentsWithStats`` computes every component's bounding box and centroid beside its
area, which costs several times the labelling itself on a full image; the pipeline reads only the
areas. :func:`labelled` labels with ``cv2.connectedComponents`` (the same labels) and counts the
areas with one ``np.bincount``.
"""

from __future__ import annotations

import cv2
import numpy as np


def labelled(binary: np.ndarray, connectivity: int) -> tuple[int, np.ndarray, np.ndarray]:
    """The connected components of a (H, W) bool or uint8 image (non-zero: foreground).

    Returns
    -------
    n : int
        Number of labels, the background's (0) included.
    labels : (H, W) int32
        ``cv2.connectedComponents``' labels (those of ``cv2.connectedComponentsWithStats``).
    areas : (n,) int64
        Pixels per label (``stats[:, cv2.CC_STAT_AREA]``).
    """
    image = binary.view(np.uint8) if binary.dtype == bool else binary
    n, labels = cv2.connectedComponents(image, connectivity=connectivity)
    areas = np.bincount(labels.ravel(), minlength=n)
    return int(n), labels, areas


def bounding_box(mask: np.ndarray, margin: int = 0) -> tuple[slice, slice] | None:
    """The rows and columns of a (H, W) mask's bounding box, ``margin`` px wider within the grid; None
    for a mask without a pixel."""
    rows = np.flatnonzero(mask.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(mask.any(axis=0))
    h, w = mask.shape
    return (
        slice(max(0, int(rows[0]) - margin), min(h, int(rows[-1]) + 1 + margin)),
        slice(max(0, int(cols[0]) - margin), min(w, int(cols[-1]) + 1 + margin)),
    )
