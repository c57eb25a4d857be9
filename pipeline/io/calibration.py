"""stereo-calibration/1: reading and writing."""

from __future__ import annotations

import os
import re
from typing import Any

import numpy as np

from ..camera import CameraModel, StereoRig
from ..formats import (
    CALIBRATION_FORMAT,
    InputError,
    StereoCalibrationFile,
)
from .jsonfile import read_json
from .validation import _validate


def load_calibration(
    source: str | os.PathLike[str] | dict[str, Any], *, file_label: str | None = None
) -> StereoRig:
    """Read a ``stereo-calibration/1`` document into a :class:`StereoRig`.

    Parameters
    ----------
    source : str, Path or dict
        A path to the JSON file, or the parsed object itself.
    file_label : str, optional
        How error messages name the document (default: the path, or
        ``"calibration.json"`` for a dict).

    Returns
    -------
    StereoRig
        ``K`` in pixels, ``dist`` = ``k1 k2 p1 p2 k3``, ``X_right = R X_left + T``
        with ``T`` in mm; ``image_size`` = ``(width, height)`` px; ``rms_px`` and
        ``board`` (``{"inner_corners": [cols, rows], "square_mm": s}``) kept when given.

    Raises
    ------
    InputError
        Unreadable file, unknown format, unknown or missing keys, non-finite
        numbers, a K that is not ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]``, an R
        that is not a rotation.
    """
    if isinstance(source, dict):
        return _calibration_from_doc(source, label=file_label or "calibration.json")
    if isinstance(source, (str, os.PathLike)):
        label = file_label or str(source)
        return _calibration_from_doc(read_json(source, label=label), label=label)
    raise TypeError(f"source: expected a path or a dict, got {type(source).__name__}")


def _calibration_from_doc(doc: dict[str, Any], *, label: str, prefix: str = "") -> StereoRig:
    cal = _validate(
        StereoCalibrationFile, doc, label=label, expected_format=CALIBRATION_FORMAT, prefix=prefix
    )
    size = (int(cal.image_size[0]), int(cal.image_size[1]))
    cams = {}
    for side in ("left", "right"):
        intr = getattr(cal, side)
        try:
            cams[side] = CameraModel(K=np.array(intr.K), dist=np.array(intr.dist), image_size=size)
        except ValueError as exc:
            raise _value_error_to_input(exc, label, f"{prefix}{side}") from None
    board = cal.board.model_dump() if cal.board is not None else None
    try:
        return StereoRig(
            left=cams["left"],
            right=cams["right"],
            R=np.array(cal.R),
            T=np.array(cal.T),
            rms_px=cal.rms_px,
            board=board,
        )
    except ValueError as exc:
        raise _value_error_to_input(exc, label, prefix.rstrip(".")) from None


def _value_error_to_input(exc: ValueError, label: str, field: str) -> InputError:
    """``"K: expected ..."`` from a dataclass check -> field ``<field>.K``."""
    m = re.match(r"^(\w+): (.*)$", str(exc))
    if m:
        return InputError(label, f"{field}.{m.group(1)}" if field else m.group(1), m.group(2))
    return InputError(label, field, str(exc))


def calibration_document(rig: StereoRig) -> dict[str, Any]:
    """A :class:`StereoRig` as a ``stereo-calibration/1`` object (inverse of :func:`load_calibration`).

    Parameters
    ----------
    rig : StereoRig

    Returns
    -------
    dict
        JSON-ready (plain floats and lists); ``rms_px`` and ``board`` only when
        the rig has them.
    """
    if not isinstance(rig, StereoRig):
        raise TypeError(f"rig: expected a StereoRig, got {type(rig).__name__}")
    doc: dict[str, Any] = {
        "format": CALIBRATION_FORMAT,
        "image_size": [int(rig.image_size[0]), int(rig.image_size[1])],
        "left": {"K": rig.left.K.tolist(), "dist": rig.left.dist.tolist()},
        "right": {"K": rig.right.K.tolist(), "dist": rig.right.dist.tolist()},
        "R": rig.R.tolist(),
        "T": rig.T.tolist(),
    }
    if rig.rms_px is not None:
        doc["rms_px"] = float(rig.rms_px)
    if rig.board is not None:
        doc["board"] = {
            "inner_corners": [int(v) for v in rig.board["inner_corners"]],
            "square_mm": float(rig.board["square_mm"]),
        }
    return doc
