"""Connected components with their areas, without the statistics nobody reads.

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
