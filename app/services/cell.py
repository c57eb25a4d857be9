"""The cell: its configuration, who holds its cameras, and their state for the dashboard and ``/healthz``.

The cell is named by ``PLATE_INSPECT_CELL_CONFIG`` (a ``cell-config/1`` file, docs/acquisition.md).
In demo mode without one, the demo cell of simulated cameras and lights is written under the data
dir (:data:`DEMO_CELL_DIR`) and used instead, so that the demo goes through the same acquisition as
a real cell. The web process and the consumer read the configuration each time they need it (an
edited file is taken up without a restart).

The cameras are used by one process at a time: ``<data dir>/cell/lock`` (:class:`CellLock`, an
exclusive ``flock``) is held by the consumer while a job acquires and by the web process while it
checks the cameras (:class:`CameraMonitor`). A GigE Vision camera gives control to one
application only, so a check must never overlap a capture; and while a capture runs, the dashboard
reports the last known state instead of checking. After each capture the consumer records the
cameras' description and a thumbnail of their last frames (:func:`record_capture`).
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import shutil
import tempfile
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from app.limits import Limits
from app.limits.work import check_calibration_size, check_light_count
from app.services.errors import ServiceError
from app.settings import ENV_PREFIX, Settings
from pipeline.acquisition import (
    CellConfig,
    load_cell_config,
)
from pipeline.acquisition import write_demo_cell as _write_demo_cell
from pipeline.acquisition.cameras import Side
from pipeline.formats import InputError

log = logging.getLogger(__name__)

#: Folder (under the data dir) of the demo cell written in demo mode without a cell config.
DEMO_CELL_DIR = "demo-cell"
#: Folder (under the data dir) of the cell's lock, its last capture's record and thumbnails.
CELL_DIR = "cell"
#: Seconds a camera check may take before the cameras it has not reached are reported unreachable.
PROBE_TIMEOUT_S = 3.0
#: Seconds a camera check's answer is reused.
STATE_TTL_S = 5.0
#: Width of a camera's last-frame thumbnail, px.
THUMBNAIL_WIDTH = 320
#: Longest cell id (the column ``inspections.cell_id``).
MAX_CELL_ID = 64
#: The setting that names the cell's configuration, for messages.
CELL_SETTING = f"{ENV_PREFIX}CELL_CONFIG"

SIDES: tuple[Side, Side] = ("left", "right")


class CellUnavailable(ServiceError):
    """The server has no usable cell: none configured, or a configuration it cannot use (answered 409)."""


# ------------------------------------------------------------------ configuration


def cell_config_path(settings: Settings) -> Path | None:
    """The cell's configuration file: ``PLATE_INSPECT_CELL_CONFIG``, the demo cell's in demo mode, or None."""
    if settings.cell_config is not None:
        return settings.cell_config
    if settings.demo:
        return settings.data_dir / DEMO_CELL_DIR / "cell.json"
    return None


def ensure_demo_cell(settings: Settings) -> None:
    """In demo mode without a cell config, write the demo cell under the data dir unless it is there.

    Written into a folder of its own and renamed into place, so that the web process and the
    consumer starting together never read a half-written one; an existing one is kept (a test
    may write a smaller one first).
    """
    if settings.cell_config is not None or not settings.demo:
        return
    folder = settings.data_dir / DEMO_CELL_DIR
    if (folder / "cell.json").is_file():
        return
    folder.parent.mkdir(parents=True, exist_ok=True)
    partial = Path(tempfile.mkdtemp(prefix=DEMO_CELL_DIR + ".partial-", dir=folder.parent))
    try:
        _write_demo_cell(
            partial
        )  # 8 lights, 1224 x 1024: the size of the Cell page's simulated plates
        os.rename(partial, folder)
    except OSError:
        if not (folder / "cell.json").is_file():  # not another process's demo cell: a real failure
            raise
    finally:
        shutil.rmtree(partial, ignore_errors=True)


def demo_target(settings: Settings) -> Path | None:
    """The demo cell's ``target.json`` (the target of a plate that has none, in demo mode), or None."""
    if settings.cell_config is not None or not settings.demo:
        return None
    path = settings.data_dir / DEMO_CELL_DIR / "target.json"
    return path if path.is_file() else None


def load_cell(settings: Settings) -> CellConfig:
    """The cell's configuration, read and checked (no device is touched).

    Besides what :func:`pipeline.acquisition.load_cell_config` checks, the cell must be within the
    request limits of an uploaded capture (its lights, its calibration's image size) and its id
    fit :data:`MAX_CELL_ID` characters.

    Raises
    ------
    CellUnavailable
        No cell configured (the message names :data:`CELL_SETTING`), or the configuration is not
        usable (the message names the file and the field, relative to the configuration's folder).
    """
    path = cell_config_path(settings)
    if path is None:
        raise CellUnavailable(
            f"{CELL_SETTING}: no cell is configured on this server: set {CELL_SETTING} to the cell's "
            "cell-config/1 file (docs/acquisition.md), or run in demo mode for the simulated demo cell"
        )
    try:
        config = load_cell_config(path)
        limits = Limits.from_settings(settings)
        check_light_count(config.lights.n, limits, label=path.name, field="lights.lights")
        check_calibration_size(config.rig.image_size, limits, label=config.calibration_path.name)
        if len(config.cell_id) > MAX_CELL_ID:
            raise InputError(
                path.name,
                "cell_id",
                f"expected at most {MAX_CELL_ID} characters, got {len(config.cell_id)}",
            )
    except InputError as err:
        raise CellUnavailable(
            f"{CELL_SETTING}: the cell's configuration is not usable: {cell_message(str(err), path)}"
        ) from None
    return config


def cell_message(text: str, config_path: Path) -> str:
    """``text`` with the configuration's folder cut from the paths in it (``cell.json: ...``)."""
    for folder in {str(config_path.parent), str(config_path.resolve().parent)}:
        if folder not in ("", "."):
            text = text.replace(folder.rstrip("/") + "/", "")
    return text


def light_controller_label(config: CellConfig) -> str:
    """The light controller as the dashboard names it: ``tcp 10.0.0.5:5000`` or ``simulated``."""
    lights = config.light_controller
    return f"{lights.driver} {lights.address}" if lights.address else lights.driver


# ------------------------------------------------------------------ the cameras' lock


class CellLock:
    """Exclusive use of the cell's cameras, between processes (``<data dir>/cell/lock``, ``flock``).

    Parameters
    ----------
    data_dir : Path
    """

    def __init__(self, data_dir: Path):
        self.path = Path(data_dir) / CELL_DIR / "lock"
        self._fd: int | None = None

    def acquire(self, holder: str, *, timeout_s: float = 0.0) -> bool:
        """Take the lock, waiting up to ``timeout_s`` for another holder; ``holder`` is written into it.

        Returns
        -------
        bool
            False when another process (or another :class:`CellLock` of this one) held it throughout.
        """
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() >= deadline:
                    os.close(fd)
                    return False
                time.sleep(0.1)
        os.ftruncate(fd, 0)
        os.pwrite(fd, holder.encode("utf-8"), 0)
        self._fd = fd
        return True

    def release(self) -> None:
        """Give the lock back (closing the descriptor frees it)."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def holder(self) -> str:
        """Who holds (or last held) the lock, as it wrote it."""
        try:
            return self.path.read_text(encoding="utf-8").strip()
        except OSError:
            return ""


# ------------------------------------------------------------------ the last capture


def record_capture(
    data_dir: Path,
    bundle: Path,
    *,
    inspection_id: int,
    frames: Mapping[str, np.ndarray] | None = None,
) -> None:
    """After a capture: its cameras' description (``cell/state.json``) and their last frames' thumbnails.

    Each camera's frame shown is its image of the stereo pair, the one frame both cameras take (from
    ``frames``, the bundle's images in memory by file name, where it is there; else read from the
    bundle; the acquisition takes the pair first, the left camera's photometric images after it); the
    thumbnail is :data:`THUMBNAIL_WIDTH` px wide, 8-bit, its brightest samples (99.5th percentile)
    white. Every file is written beside its place and renamed into it (the web process reads them).
    """
    doc = json.loads((bundle / "capture.json").read_text(encoding="utf-8"))
    record = doc["acquisition"]
    folder = Path(data_dir) / CELL_DIR
    folder.mkdir(parents=True, exist_ok=True)
    for side in SIDES:
        name = doc["stereo"][side]
        image = (frames or {}).get(name)
        if image is None:
            image = cv2.imread(str(bundle / name), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise OSError(f"{side} image: could not read it")
        ok, png = cv2.imencode(".png", _thumbnail(image))
        if not ok:
            raise OSError(f"{side} thumbnail: could not encode it")
        _write_atomic(folder / f"{side}.png", png.tobytes())
    state = {
        "cell_id": record["cell_id"],
        "inspection_id": inspection_id,
        "plate_id": doc["plate_id"],
        "captured_at": doc["captured_at"],
        "cameras": {
            side: {
                key: record["cameras"][side].get(key)
                for key in ("driver", "device_id", "vendor", "model", "serial")
            }
            for side in SIDES
        },
    }
    _write_atomic(folder / "state.json", json.dumps(state, indent=2).encode("utf-8"))


def last_capture(data_dir: Path) -> dict[str, Any] | None:
    """What :func:`record_capture` recorded last (``cell_id``, ``inspection_id``, ``plate_id``,
    ``captured_at``, ``cameras``), or None."""
    try:
        state: dict[str, Any] = json.loads(
            (Path(data_dir) / CELL_DIR / "state.json").read_text(encoding="utf-8")
        )
    except (OSError, ValueError):
        return None
    return state


def thumbnail_path(data_dir: Path, side: str) -> Path | None:
    """The last-frame thumbnail of camera ``side`` (``left``/``right``), or None before the first capture."""
    if side not in SIDES:
        raise ValueError(f"side: expected 'left' or 'right', got {side!r}")
    path = Path(data_dir) / CELL_DIR / f"{side}.png"
    return path if path.is_file() else None


def _thumbnail(image: np.ndarray) -> np.ndarray:
    grey = image.astype(np.float32)
    top = max(float(np.percentile(grey[::4, ::4], 99.5)), 1.0)
    height = max(1, round(grey.shape[0] * THUMBNAIL_WIDTH / grey.shape[1]))
    small = cv2.resize(grey, (THUMBNAIL_WIDTH, height), interpolation=cv2.INTER_AREA)
    thumb: np.ndarray = np.clip(small * (255.0 / top), 0, 255).astype(np.uint8)
    return thumb


def _write_atomic(path: Path, data: bytes) -> None:
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", dir=path.parent)
    try:
        os.fchmod(fd, 0o644)
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
