"""The work one request may ask for: image pixels, lights, a simulated capture's size (422 beyond).

An uploaded capture is checked from capture.json and its image headers only
(:func:`pipeline.io.read_capture_header`): the web process never decodes an image, so a small
upload declaring huge images costs it nothing. The job decodes the images later, within these
limits.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from app.limits import Limits, setting_name
from app.services.errors import UnprocessableError
from pipeline import io as pio
from pipeline.formats import InputError
from pipeline.io import CaptureHeader, InputLimitError

#: The Limits field behind each limit of pipeline.io.read_capture_header.
_CAPTURE_LIMITS = {"lights": "max_lights", "image_pixels": "max_image_pixels"}


def _raise_hint(limit: str) -> str:
    return f"(the server setting {setting_name(limit)} raises it)"


def read_capture_header(path: Path, limits: Limits) -> CaptureHeader:
    """Check an uploaded capture bundle without decoding it, within ``limits``.

    Raises
    ------
    pipeline.formats.InputError
        Anything :func:`pipeline.io.read_capture_header` refuses; over a limit, the message
        names the image file or the lights, the limit, and the setting that raises it.
    """
    try:
        return pio.read_capture_header(
            path, max_lights=limits.max_lights, max_image_pixels=limits.max_image_pixels
        )
    except InputLimitError as err:
        raise InputError(
            err.file, err.field, f"{err.reason} {_raise_hint(_CAPTURE_LIMITS[err.limit])}"
        ) from None


def check_calibration_size(image_size: tuple[int, int], limits: Limits, *, label: str) -> None:
    """Refuse a stereo calibration whose ``image_size`` is over the image pixel limit.

    Raises
    ------
    pipeline.formats.InputError
        Field ``image_size``.
    """
    width, height = image_size
    if width * height > limits.max_image_pixels:
        raise InputError(
            label,
            "image_size",
            f"{width}x{height} px = {width * height} px, more than the limit of {limits.max_image_pixels} px "
            f"per image {_raise_hint('max_image_pixels')}",
        )


def check_light_count(n_lights: int, limits: Limits, *, label: str, field: str) -> None:
    """Refuse a light calibration of more lights than the limit.

    Raises
    ------
    pipeline.formats.InputError
        Field ``field`` (the file's list of lights).
    """
    if n_lights > limits.max_lights:
        raise InputError(
            label,
            field,
            f"{n_lights} lights, more than the limit of {limits.max_lights} {_raise_hint('max_lights')}",
        )


def check_simulation(simulation: dict[str, Any], limits: Limits) -> None:
    """Refuse a simulated inspection over the lights or simulated pixel limits.

    ``simulation`` is a validated :class:`app.schemas.SimulatedInspectionIn` as a dict.

    Raises
    ------
    UnprocessableError
        Field ``n_lights``, or ``width`` (for width x height).
    """
    n = simulation["n_lights"]
    if n > limits.max_lights:
        raise UnprocessableError(
            f"n_lights: {n} lights, more than the limit of {limits.max_lights} {_raise_hint('max_lights')}",
            field="n_lights",
        )
    width, height = simulation["width"], simulation["height"]
    if width * height > limits.max_simulated_pixels:
        raise UnprocessableError(
            f"width: {width}x{height} px = {width * height} px, more than the limit of "
            f"{limits.max_simulated_pixels} px for a simulated capture {_raise_hint('max_simulated_pixels')}",
            field="width",
        )
