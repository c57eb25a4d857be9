"""Light calibrations of the cell (``light-calibration/1``); the newest is the current one.

The current light calibration stands in for the nominal light directions of uploaded captures:
an inspection records the one that was current when it was submitted (see
:func:`light_calibration_for_capture`), and its job passes those lights to the pipeline
(:func:`load_lights`), which applies them and says so in the result's ``warnings``.
"""

from __future__ import annotations

import json
import re
from pathlib import Path, PurePosixPath

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.limits import DEFAULT_LIMITS, Limits
from app.limits.physical import check_lights
from app.limits.work import check_light_count
from app.models import LightCalibration
from app.storage import Storage
from pipeline import io as pio
from pipeline.io import Capture, CaptureHeader
from pipeline.lights.model import Lights

LIGHT_CALIBRATION_FILE = "lights.json"
#: How error messages name a light calibration sent as a JSON request body (it has no file name).
BODY_LABEL = "body"
_UNPRINTABLE = re.compile(r"[\x00-\x1f\x7f]")


def upload_name(raw: str | None) -> str | None:
    """The base name of an uploaded file as the client sent it, fit to show (None if it sent none).

    Folders (either slash) are dropped, control characters removed, and the name cut to 255
    characters.
    """
    if raw is None:
        return None
    name = PurePosixPath(_UNPRINTABLE.sub("", raw).replace("\\", "/")).name.strip()[:255]
    return name or None


def create_light_calibration(
    *,
    session: Session,
    storage: Storage,
    staging_dir: Path,
    file_name: str | None,
    limits: Limits = DEFAULT_LIMITS,
) -> LightCalibration:
    """Store the light calibration in ``staging_dir/lights.json`` as the cell's current one.

    Parameters
    ----------
    file_name : str or None
        The uploaded file's name (from :func:`upload_name`): error messages name it. None for
        a JSON request body (messages then say ``body``).
    limits : Limits, optional
        Its lights count against ``max_lights`` (default: :data:`app.limits.DEFAULT_LIMITS`).

    Raises
    ------
    pipeline.formats.InputError
        Bad light calibration, more lights than the limit, or a light farther than the cell
        reaches (names the file and the field); nothing was added.
    """
    path = Path(staging_dir) / LIGHT_CALIBRATION_FILE
    label = file_name or BODY_LABEL
    lights, rms = pio.load_light_calibration(path, file_label=label)  # raises InputError
    check_light_count(lights.n, limits, label=label, field="lights")
    check_lights(lights, label=label, field="lights")
    row = LightCalibration(
        file_name=file_name,
        n_lights=lights.n,
        rms=rms,
        document=json.loads(path.read_text(encoding="utf-8")),
        path="",
    )
    session.add(row)
    session.flush()
    destination = storage.light_calibration_dir(row.id)
    storage.adopt(staging_dir, destination)
    row.path = storage.relative(destination / LIGHT_CALIBRATION_FILE)
    session.flush()
    return row


def current_light_calibration(*, session: Session) -> LightCalibration | None:
    return session.scalars(
        select(LightCalibration).order_by(LightCalibration.id.desc()).limit(1)
    ).first()


def get_light_calibration(
    *, session: Session, light_calibration_id: int
) -> LightCalibration | None:
    return session.get(LightCalibration, light_calibration_id)


def list_light_calibrations(*, session: Session, limit: int = 20) -> list[LightCalibration]:
    return list(
        session.scalars(select(LightCalibration).order_by(LightCalibration.id.desc()).limit(limit))
    )


def light_calibration_for_capture(
    *, session: Session, capture: Capture | CaptureHeader
) -> LightCalibration | None:
    """The light calibration an inspection of ``capture`` is run with: the current one, or None.

    None when no light calibration was uploaded, or when the capture gives point lights of its
    own (the pipeline keeps those: there is nothing to apply). A calibration with another count
    of lights than the capture is still returned: the pipeline then leaves the nominal lights
    and says why in the result's warnings.
    """
    if capture.lights.any_point:
        return None
    return current_light_calibration(session=session)


def load_lights(*, storage: Storage, calibration: LightCalibration) -> Lights:
    """The stored calibration's lights, read and checked again from its file (for the job).

    Raises
    ------
    pipeline.formats.InputError
        The stored file is missing or no longer valid (named ``light calibration #<id>``).
    """
    lights, _rms = pio.load_light_calibration(
        storage.absolute(calibration.path), file_label=f"light calibration #{calibration.id}"
    )
    return lights
