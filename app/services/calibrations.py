"""Calibrations of the camera pair (``stereo-calibration/1``); the newest is the current one."""

from __future__ import annotations

import json
from pathlib import Path

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.limits import DEFAULT_LIMITS, Limits
from app.limits.work import check_calibration_size
from app.models import Calibration
from app.storage import Storage
from pipeline import io as pio

CALIBRATION_FILE = "calibration.json"


def create_calibration(
    *, session: Session, storage: Storage, staging_dir: Path, limits: Limits = DEFAULT_LIMITS
) -> Calibration:
    """Store the calibration in ``staging_dir/calibration.json`` as the cell's current one.

    Its ``image_size`` is checked against ``limits`` (default: :data:`app.limits.DEFAULT_LIMITS`).

    Raises
    ------
    pipeline.formats.InputError
        Bad calibration file, or an ``image_size`` over the image pixel limit of ``limits``
        (names the file and the field).
    """
    path = Path(staging_dir) / CALIBRATION_FILE
    rig = pio.load_calibration(path, file_label=CALIBRATION_FILE)  # validates; raises InputError
    check_calibration_size(rig.image_size, limits, label=CALIBRATION_FILE)
    document = json.loads(path.read_text(encoding="utf-8"))
    width, height = (int(x) for x in document["image_size"])
    rms = document.get("rms_px")
    row = Calibration(
        image_width=width,
        image_height=height,
        rms_px=None if rms is None else float(rms),
        document=document,
        path="",
    )
    session.add(row)
    session.flush()
    destination = storage.calibration_dir(row.id)
    storage.adopt(staging_dir, destination)
    row.path = storage.relative(destination / CALIBRATION_FILE)
    session.flush()
    return row


def current_calibration(*, session: Session) -> Calibration | None:
    return session.scalars(select(Calibration).order_by(Calibration.id.desc()).limit(1)).first()


def get_calibration(*, session: Session, calibration_id: int) -> Calibration | None:
    return session.get(Calibration, calibration_id)


def list_calibrations(*, session: Session, limit: int = 20) -> list[Calibration]:
    return list(session.scalars(select(Calibration).order_by(Calibration.id.desc()).limit(limit)))
