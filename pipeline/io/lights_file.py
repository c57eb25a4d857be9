"""light-calibration/1: reading and writing."""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from pipeline.formats import LIGHT_CALIBRATION_FORMAT, LightCalibrationFile
from pipeline.io.jsonfile import read_json
from pipeline.io.validation import _validate
from pipeline.lights.model import Lights


def load_light_calibration(
    source: str | os.PathLike[str] | dict[str, Any], *, file_label: str | None = None
) -> tuple[Lights, float | None]:
    """Read a ``light-calibration/1`` document.

    Parameters
    ----------
    source : str, Path or dict
        A path to the JSON file, or the parsed object itself.
    file_label : str, optional
        How error messages name the document.

    Returns
    -------
    (Lights, rms)
        The calibrated point lights in image order (left-camera frame, mm) and the fit's
        residual (None when the file does not give it).

    Raises
    ------
    InputError
        Unreadable file, unknown format, unknown or missing keys, non-finite numbers, an axis that
        is not a unit vector, a negative mu, fewer than 3 lights.
    """
    if isinstance(source, dict):
        label, doc = file_label or "lights.json", source
    elif isinstance(source, (str, os.PathLike)):
        label = file_label or str(source)
        doc = read_json(source, label=label)
    else:
        raise TypeError(f"source: expected a path or a dict, got {type(source).__name__}")
    cal = _validate(
        LightCalibrationFile, doc, label=label, expected_format=LIGHT_CALIBRATION_FORMAT
    )
    return Lights.from_documents(cal.lights), cal.rms


def light_calibration_document(lights: Lights, rms: float | None) -> dict[str, Any]:
    """Point lights as a ``light-calibration/1`` object (inverse of :func:`load_light_calibration`)."""
    if not lights.is_point.all():
        raise ValueError("lights: a light calibration holds point lights only, got distant ones")
    light_docs: list[dict[str, Any]] = []
    doc: dict[str, Any] = {
        "format": LIGHT_CALIBRATION_FORMAT,
        "lights": light_docs,
        "rms": None if rms is None else float(rms),
    }
    for k in range(lights.n):
        axis = lights.axes[k] if np.isfinite(lights.axes[k]).all() else np.array([0.0, 0.0, 1.0])
        light_docs.append(
            {
                "position_mm": [float(v) for v in lights.positions_mm[k]],
                "axis": [float(v) for v in axis],
                "mu": float(lights.mu[k]),
                "intensity": float(lights.intensity[k]),
            }
        )
    if rms is None:
        doc.pop("rms")
    LightCalibrationFile.model_validate(doc)
    return doc
