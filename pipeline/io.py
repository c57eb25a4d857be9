"""Reading and writing the project's files: calibrations, capture bundles, targets, results.

Every failure on bad input is an :class:`~pipeline.formats.InputError` naming the
file and the field (``"capture.json: photometric.lights[3].direction: ..."``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .camera import StereoRig
from .formats import InputError  # noqa: F401  (re-exported for callers)


@dataclass(frozen=True)
class Capture:
    """A loaded capture bundle (``plate-capture/1``); images as the camera gave them.

    Attributes
    ----------
    plate_id : str
    captured_at : str or None
        ISO 8601 time stamp from the bundle.
    rig : StereoRig
        The calibration the bundle names; ``rig.image_size`` matches every image.
    bit_depth : int
        Significant bits per pixel; every pixel is ``<= 2**bit_depth - 1``.
    light_dirs : (N, 3) float64
        Unit vectors, left-camera frame, from the surface towards light k.
    light_intensity : (N,) float64
        Relative intensity ``e_k`` of light k.
    images : (N, H, W) float32
        Photometric images of the left camera, raw counts (distorted, dark not
        subtracted). Colour images are converted to grey on loading.
    dark : (H, W) float32 or None
        Dark frame, raw counts.
    stereo_left, stereo_right : (H, W) float32 or None
        The stereo pair, raw counts.
    working_distance_mm : float or None
    source : Path
        The folder or .zip the bundle was read from.
    """

    plate_id: str
    captured_at: str | None
    rig: StereoRig
    bit_depth: int
    light_dirs: np.ndarray
    light_intensity: np.ndarray
    images: np.ndarray
    dark: np.ndarray | None
    stereo_left: np.ndarray | None
    stereo_right: np.ndarray | None
    working_distance_mm: float | None
    source: Path

    @property
    def n_lights(self) -> int:
        return int(self.light_dirs.shape[0])

    @property
    def has_stereo(self) -> bool:
        return self.stereo_left is not None and self.stereo_right is not None


@dataclass(frozen=True)
class Target:
    """The CAD target of a plate (``plate-target/1``).

    Attributes
    ----------
    shape : {"plane", "cylinder", "sphere", "mesh"}
    radius_mm : float or None
        Cylinder or sphere radius; None for plane and mesh.
    size_mm : (float, float)
        Plate size; a cylinder's axis runs along the second size axis.
    tolerance_mm : float
        Allowed absolute deviation.
    mesh_vertices_mm : (V, 3) float64 or None
        For ``mesh``: vertices in the target's own frame, mm.
    mesh_faces : (F, 3) int64 or None
    source : Path or None
    """

    shape: str
    radius_mm: float | None
    size_mm: tuple[float, float]
    tolerance_mm: float
    mesh_vertices_mm: np.ndarray | None = None
    mesh_faces: np.ndarray | None = None
    source: Path | None = None
