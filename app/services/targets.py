"""Plate targets (``plate-target/1``): validated with the pipeline's loader and the bounds of a hull
plate (:mod:`app.limits.physical`), versioned per plate."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

from sqlalchemy.orm import Session

from app.limits.physical import check_target
from app.models import Target
from app.services.plates import get_or_create_plate
from app.storage import Storage
from pipeline import io as pio

TARGET_FILE = "target.json"


def validate_target_dir(folder: Path) -> tuple[pio.Target, dict[str, Any]]:
    """Load ``folder/target.json`` (and its mesh file, if any) and check it against a hull plate's bounds.

    The pipeline's loader reads it; :func:`app.limits.physical.check_target` bounds it.

    Returns
    -------
    (pipeline.io.Target, dict)
        The loaded target and the JSON document as sent.

    Raises
    ------
    pipeline.formats.InputError
        The file or a field of it is wrong, or no hull plate is like it (names the file and the field).
    """
    path = Path(folder) / TARGET_FILE
    target = pio.load_target(path, base_dir=Path(folder))
    check_target(target, label=str(path))
    document = json.loads(path.read_text(encoding="utf-8"))
    return target, document


def create_target(
    *,
    session: Session,
    storage: Storage,
    plate_id: str,
    staging_dir: Path,
    validated: tuple[pio.Target, dict[str, Any]] | None = None,
) -> Target:
    """A new current target for a plate from a staging folder holding ``target.json`` (+ mesh).

    The folder is validated first (unless ``validated`` gives :func:`validate_target_dir`'s
    answer for the same files) and, once the row has an id, moved to the plate's target
    folder. On any error nothing is added and the staging folder is left for the caller to remove.

    Raises
    ------
    pipeline.formats.InputError
        Bad target file.
    ValueError
        Bad plate id.
    """
    loaded, document = validate_target_dir(staging_dir) if validated is None else validated
    get_or_create_plate(session=session, plate_id=plate_id)
    row = Target(
        plate_id=plate_id,
        shape=loaded.shape,
        radius_mm=loaded.radius_mm,
        tolerance_mm=float(loaded.tolerance_mm),
        document=document,
        path="",
    )
    session.add(row)
    session.flush()
    destination = storage.target_dir(plate_id, row.id)
    storage.adopt(staging_dir, destination)
    row.path = storage.relative(destination / TARGET_FILE)
    session.flush()
    return row


def copy_target_files(*, storage: Storage, target: Target, destination: Path) -> Path:
    """Copy a target's folder (target.json + mesh) to ``destination``; returns the new target.json."""
    source = storage.absolute(target.path).parent
    shutil.copytree(source, destination)
    return destination / TARGET_FILE
