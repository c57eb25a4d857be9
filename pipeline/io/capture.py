"""plate-capture/1: a bundle loaded into a Capture (images decoded, lights checked)."""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.camera import StereoRig
from pipeline.formats import (
    CALIBRATION_FORMAT,
    CAPTURE_FORMAT,
    CaptureFile,
    InputError,
    Station,
    StereoCalibrationFile,
)
from pipeline.io.bundle import (
    MAX_ZIP_RATIO,
    MAX_ZIP_TOTAL_BYTES,
    _Bundle,
    _check_relative,
    _open_bundle,
)
from pipeline.io.calibration import _calibration_from_doc
from pipeline.io.images import _ImageJob, _load_images
from pipeline.io.jsonfile import _json_type, _parse_json
from pipeline.io.validation import _validate
from pipeline.lights.model import CAMERA_HEAD_RADIUS_MM, Lights


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
    lights : pipeline.lights.model.Lights
        The N lights (distant or point lights), left-camera frame, mm.
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
    station : pipeline.formats.Station or None
        Where the plate stood on the conveyor (a station of a plate longer than the view,
        docs/stations.md); None for a plate measured in one view.
    raw_noise : ((N,) float64, float or None) or None
        The noise (raw counts, standard deviation) of each photometric image and of the dark frame
        (None without one), when it was measured before the images were binned
        (:func:`pipeline.preprocess.bin_capture`); None: it is measured on ``images``.
    """

    plate_id: str
    captured_at: str | None
    rig: StereoRig
    bit_depth: int
    lights: Lights
    images: np.ndarray
    dark: np.ndarray | None
    stereo_left: np.ndarray | None
    stereo_right: np.ndarray | None
    working_distance_mm: float | None
    source: Path
    station: Station | None = None
    raw_noise: tuple[np.ndarray, float | None] | None = None

    @property
    def n_lights(self) -> int:
        return self.lights.n

    @property
    def light_dirs(self) -> np.ndarray:
        """(N, 3) float64 unit directions of distant lights (NaN rows for point lights)."""
        return self.lights.directions

    @property
    def light_intensity(self) -> np.ndarray:
        """(N,) float64 relative intensity ``e_k`` of light k."""
        return self.lights.intensity

    @property
    def has_stereo(self) -> bool:
        return self.stereo_left is not None and self.stereo_right is not None


def load_capture(
    path: str | os.PathLike[str],
    *,
    max_total_bytes: int = MAX_ZIP_TOTAL_BYTES,
    max_ratio: float = MAX_ZIP_RATIO,
    workers: int | None = None,
    frames: Mapping[str, np.ndarray] | None = None,
) -> Capture:
    """Load a ``plate-capture/1`` bundle: a folder holding capture.json, or a .zip of one.

    Parameters
    ----------
    path : str or Path
        The bundle folder (or its ``capture.json``), or a ``.zip`` with
        ``capture.json`` at its root or inside its one top folder.
    max_total_bytes : int
        Zip only: refuse a zip whose members add up to more uncompressed bytes.
    max_ratio : float
        Zip only: refuse a member (over 1 MiB uncompressed) whose uncompressed
        size is more than ``max_ratio`` times its compressed size.
    workers : int, optional
        Decoding threads (default: the number of CPUs).
    frames : mapping of str to (H, W) uint8 or uint16 array, optional
        Images of the bundle already in memory, by their path in the bundle (``"ps_00.png"``): the
        frames an acquisition has just written (:func:`pipeline.acquisition.acquire`'s ``frames``).
        They are checked as their files would be and not decoded again; the rest is read.

    Returns
    -------
    Capture
        Images as float32 raw counts (H, W) = the calibration's ``image_size``
        (width, height) reversed; colour images are converted to grey with
        ``cv2.COLOR_BGR2GRAY``, Y = 0.299 R + 0.587 G + 0.114 B (alpha dropped).
        Light directions are normalised to unit length (the file's are within
        ``formats.UNIT_TOLERANCE`` of it).

    Raises
    ------
    InputError
        Any bad input, naming the file and the field: bundle or capture.json
        missing, empty or not JSON; unknown format, unknown or missing keys,
        non-finite numbers; bad light directions or counts; image paths that
        leave the bundle; missing, undecodable or wrongly sized images (photometric,
        dark, stereo); pixels above ``2**bit_depth - 1``; zip members that
        leave the bundle, are links, or break the size limits.

    Notes
    -----
    Zips are read in memory, never extracted: all member names and sizes are
    checked before any member is read.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path: expected a path, got {type(path).__name__}")
    if not max_total_bytes > 0:
        raise ValueError(f"max_total_bytes: expected a positive byte count, got {max_total_bytes}")
    if not max_ratio >= 1:
        raise ValueError(f"max_ratio: expected a ratio >= 1, got {max_ratio}")
    path = Path(path)
    bundle = _open_bundle(path, max_total_bytes=max_total_bytes, max_ratio=max_ratio)
    try:
        return _load_capture(bundle, path, workers=workers, frames=frames)
    finally:
        bundle.close()


def _read_capture_json(
    bundle: _Bundle,
) -> tuple[CaptureFile, StereoRig, list[tuple[str | None, _ImageJob]]]:
    """capture.json and its calibration, validated; the image files it names, every path checked.

    Returns ``(capture file, rig, [(key, job), ...])``: photometric images first (key None),
    then ``"dark"``, ``"left"``, ``"right"`` when the bundle has them.
    """
    label = bundle.capture_label
    doc = _parse_json(bundle.read("capture.json", field=""), label)

    # The calibration first: a dict or a file name, never the union's error noise.
    cal = doc.get("calibration")
    if isinstance(cal, dict):
        _validate(
            StereoCalibrationFile,
            cal,
            label=label,
            expected_format=CALIBRATION_FORMAT,
            prefix="calibration.",
        )
    elif "calibration" in doc and not isinstance(cal, str):
        raise InputError(
            label,
            "calibration",
            f"expected a file name in the bundle or a calibration object, got {_json_type(cal)}",
        )
    cap = _validate(CaptureFile, doc, label=label, expected_format=CAPTURE_FORMAT)

    if isinstance(cap.calibration, str):
        rel = _check_relative(cap.calibration, label=label, field="calibration")
        cal_label = bundle.label(rel)
        rig = _calibration_from_doc(
            _parse_json(bundle.read(rel, field="calibration"), cal_label), label=cal_label
        )
    else:
        rig = _calibration_from_doc(doc["calibration"], label=label, prefix="calibration.")

    # Every path is checked before any image is read.
    size = rig.image_size
    wanted: list[tuple[str | None, str, str, tuple[int, int], str]] = [
        (None, name, f"photometric.images[{k}]", size, "photometric image")
        for k, name in enumerate(cap.photometric.images)
    ]
    if cap.photometric.dark is not None:
        wanted.append(("dark", cap.photometric.dark, "photometric.dark", size, "dark frame"))
    if cap.stereo is not None:
        for side in ("left", "right"):
            cam_size = getattr(rig, side).image_size
            wanted.append(
                (
                    side,
                    getattr(cap.stereo, side),
                    f"stereo.{side}",
                    cam_size,
                    f"stereo {side} image",
                )
            )
    return (
        cap,
        rig,
        [
            (key, _ImageJob(_check_relative(name, label=label, field=field), field, sz, what))
            for key, name, field, sz, what in wanted
        ],
    )


def _load_capture(
    bundle: _Bundle, source: Path, *, workers: int | None, frames: Mapping[str, np.ndarray] | None
) -> Capture:
    label = bundle.capture_label
    cap, rig, wanted = _read_capture_json(bundle)
    size = rig.image_size
    n = len(cap.photometric.images)
    images = np.empty((n, size[1], size[0]), dtype=np.float32)
    named = {
        key: np.empty((job.expected_size[1], job.expected_size[0]), np.float32)
        for key, job in wanted[n:]
    }
    jobs = [job for _, job in wanted]
    _load_images(
        bundle,
        jobs,
        [*images, *named.values()],
        bit_depth=cap.bit_depth,
        workers=workers,
        frames=frames,
    )

    lights = Lights.from_documents(cap.photometric.lights)
    _check_light_positions(lights, rig, cap.working_distance_mm, label=label)
    return Capture(
        plate_id=cap.plate_id,
        captured_at=cap.captured_at,
        rig=rig,
        bit_depth=int(cap.bit_depth),
        lights=lights,
        images=images,
        dark=named.get("dark"),
        stereo_left=named.get("left"),
        stereo_right=named.get("right"),
        working_distance_mm=cap.working_distance_mm,
        source=source,
        station=cap.station,
    )


def _check_light_positions(
    lights: Lights, rig: StereoRig, working_distance_mm: float | None, *, label: str
) -> None:
    """Point lights must lie between the camera head and the plate: not inside the head, not behind the plate."""
    centres = {"left": np.zeros(3), "right": -rig.R.T @ rig.T}
    for k in np.flatnonzero(lights.is_point):
        p = lights.positions_mm[k]
        field = f"photometric.lights[{k}].position_mm"
        for side, c in centres.items():
            if np.linalg.norm(p - c) < CAMERA_HEAD_RADIUS_MM:
                raise InputError(
                    label,
                    field,
                    f"a light {np.linalg.norm(p - c):.0f} mm from the {side} camera's centre is inside the camera head "
                    f"(expected at least {CAMERA_HEAD_RADIUS_MM:.0f} mm; positions are mm in the left camera frame), "
                    f"got {[round(float(v), 1) for v in p]}",
                )
        if working_distance_mm is not None and p[2] >= working_distance_mm:
            raise InputError(
                label,
                field,
                f"a light at z = {p[2]:.0f} mm is behind the plate (working_distance_mm {working_distance_mm:.0f}; "
                f"positions are mm in the left camera frame, z forward), got {[round(float(v), 1) for v in p]}",
            )
