"""A bundle checked without decoding any image (capture.json, calibration, image headers)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from PIL import Image, UnidentifiedImageError

from pipeline.camera import StereoRig
from pipeline.formats import InputError, Station
from pipeline.io.bundle import MAX_ZIP_RATIO, MAX_ZIP_TOTAL_BYTES, _Bundle, _open_bundle
from pipeline.io.capture import _check_light_positions, _read_capture_json
from pipeline.io.images import _ImageJob
from pipeline.lights.model import Lights


class InputLimitError(InputError):
    """Input refused by a limit the caller set (not by the format); ``limit`` names which one.

    Attributes
    ----------
    limit : {"lights", "image_pixels"}
        The parameter of :func:`read_capture_header` that refused the input (``max_<limit>``).
    """

    def __init__(self, file: str, field: str, reason: str, *, limit: str) -> None:
        super().__init__(file, field, reason)
        self.limit = limit


@dataclass(frozen=True)
class ImageHeader:
    """One image file of a capture bundle as its header describes it (nothing decoded).

    Attributes
    ----------
    field : str
        Where capture.json names it: ``"photometric.images[3]"``, ``"photometric.dark"``, ``"stereo.left"``.
    name : str
        Its path in the bundle.
    what : str
        ``"photometric image"``, ``"dark frame"``, ``"stereo left image"``, ...
    width, height : int
        Pixels, from the header.
    """

    field: str
    name: str
    what: str
    width: int
    height: int


@dataclass(frozen=True)
class CaptureHeader:
    """A capture bundle checked as far as that goes without decoding an image (:func:`read_capture_header`).

    Attributes
    ----------
    label : str
        How error messages name the bundle's capture.json (``<bundle.zip>:capture.json``).
    plate_id, captured_at, rig, bit_depth, lights, working_distance_mm, station
        As in :class:`Capture`.
    images : tuple of ImageHeader
        Every image file the bundle names: photometric images in order, then the dark frame
        and the stereo pair when given.
    """

    label: str
    plate_id: str
    captured_at: str | None
    rig: StereoRig
    bit_depth: int
    lights: Lights
    working_distance_mm: float | None
    images: tuple[ImageHeader, ...]
    station: Station | None = None

    @property
    def n_lights(self) -> int:
        return self.lights.n


def read_capture_header(
    path: str | os.PathLike[str],
    *,
    max_lights: int | None = None,
    max_image_pixels: int | None = None,
    max_total_bytes: int = MAX_ZIP_TOTAL_BYTES,
    max_ratio: float = MAX_ZIP_RATIO,
) -> CaptureHeader:
    """Check a ``plate-capture/1`` bundle without decoding its images.

    Everything :func:`load_capture` checks before it decodes: the zip's members, capture.json
    and the calibration, the lights, every image path; then each image's format and size from
    its header only (Pillow reads the header lazily from the member's stream, so a small file
    claiming a huge image costs nothing). Pixel values are not read: an image that is corrupt
    past its header, or whose pixels exceed ``bit_depth``, is found by :func:`load_capture`.

    Parameters
    ----------
    path : str or Path
        As for :func:`load_capture`.
    max_lights : int, optional
        Refuse more lights (and so photometric images) than this, before any image is opened.
    max_image_pixels : int, optional
        Refuse an image whose header declares more pixels than this.
    max_total_bytes, max_ratio
        As for :func:`load_capture`.

    Returns
    -------
    CaptureHeader

    Raises
    ------
    InputLimitError
        Over ``max_lights`` or ``max_image_pixels`` (names the file and the field; ``limit`` says which).
    InputError
        Anything :func:`load_capture` refuses before decoding: bad zip, capture.json or
        calibration, image paths that leave the bundle or are missing, files that are not PNG
        or TIFF, headers whose size is not the calibration's ``image_size``.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path: expected a path, got {type(path).__name__}")
    for name, value in (("max_lights", max_lights), ("max_image_pixels", max_image_pixels)):
        if value is not None and not value >= 1:
            raise ValueError(f"{name}: expected a positive count or None, got {value}")
    path = Path(path)
    bundle = _open_bundle(path, max_total_bytes=max_total_bytes, max_ratio=max_ratio)
    try:
        label = bundle.capture_label
        cap, rig, wanted = _read_capture_json(bundle)
        n = len(cap.photometric.lights)
        if max_lights is not None and n > max_lights:
            raise InputLimitError(
                label,
                "photometric.lights",
                f"{n} lights (and images), more than the limit of {max_lights}",
                limit="lights",
            )
        lights = Lights.from_documents(cap.photometric.lights)
        _check_light_positions(lights, rig, cap.working_distance_mm, label=label)
        headers = tuple(
            _image_header(bundle, job, label=label, max_pixels=max_image_pixels)
            for _, job in wanted
        )
    finally:
        bundle.close()
    return CaptureHeader(
        label=label,
        plate_id=cap.plate_id,
        captured_at=cap.captured_at,
        rig=rig,
        bit_depth=int(cap.bit_depth),
        lights=lights,
        working_distance_mm=cap.working_distance_mm,
        images=headers,
        station=cap.station,
    )


def _image_header(
    bundle: _Bundle, job: _ImageJob, *, label: str, max_pixels: int | None
) -> ImageHeader:
    """Format and size of one image from its header (Pillow's lazy open); nothing is decoded."""
    name = repr(job.rel)
    with bundle.open(job.rel, field=job.field) as fh:
        try:
            with Image.open(fh, formats=("PNG", "TIFF")) as img:
                width, height = img.size
        except Image.DecompressionBombError:
            max_pixels_limit = Image.MAX_IMAGE_PIXELS
            if max_pixels_limit is None:  # Pillow raises this only when the limit is set
                raise
            bomb = 2 * max_pixels_limit  # Pillow refuses to open more
            raise InputError(
                label,
                job.field,
                f"{name} ({job.what}): its header declares more than {bomb} px (a decompression bomb?)",
            ) from None
        except UnidentifiedImageError:
            raise InputError(
                label,
                job.field,
                f"{name}: not a PNG or TIFF file (expected an 8- or 16-bit PNG or TIFF)",
            ) from None
        except Exception as exc:
            raise InputError(
                label, job.field, f"{name}: cannot read the image header: {exc}"
            ) from None
    if (width, height) != job.expected_size:
        ew, eh = job.expected_size
        raise InputError(
            label,
            job.field,
            f"{name} ({job.what}) is {width}x{height} px, expected {ew}x{eh} (calibration image_size, width x height)",
        )
    if max_pixels is not None and width * height > max_pixels:
        raise InputLimitError(
            label,
            job.field,
            f"{name} ({job.what}) is {width}x{height} px = {width * height} px, more than the limit of {max_pixels} px",
            limit="image_pixels",
        )
    return ImageHeader(field=job.field, name=job.rel, what=job.what, width=width, height=height)
