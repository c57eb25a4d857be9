"""The cameras' state for the dashboard and ``/healthz``: checked by the web process under the
cell lock (:class:`CameraMonitor`), or the last capture's while a capture holds the cameras.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from typing import Any

from app.services.cell import (
    PROBE_TIMEOUT_S,
    SIDES,
    STATE_TTL_S,
    CellLock,
    CellUnavailable,
    cell_config_path,
    last_capture,
    light_controller_label,
    load_cell,
)
from app.settings import Settings
from pipeline.acquisition import (
    CellConfig,
    SimulatedCell,
    SimulatedLightController,
    open_camera,
)
from pipeline.acquisition.cameras import Side
from pipeline.formats import AcquisitionError, CellCamera

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class CameraState:
    """One camera as the dashboard and ``/healthz`` report it.

    Attributes
    ----------
    side : {"left", "right"}
    driver : str
        ``aravis`` or ``simulated``.
    device_id : str or None
    state : {"connected", "unreachable", "error", "unknown"}
        Opened and described; not found or not answering (within :data:`PROBE_TIMEOUT_S`);
        another failure (e.g. Aravis not installed); not checked yet.
    vendor, model, serial : str or None
        As the camera gives them (when connected, or at the last capture).
    detail : str or None
        Why it is not connected, or where a state comes from that is not a check of now.
    """

    side: str
    driver: str
    device_id: str | None
    state: str
    vendor: str | None = None
    model: str | None = None
    serial: str | None = None
    detail: str | None = None


@dataclass(frozen=True)
class CellState:
    """The cell as the dashboard and ``/healthz`` report it.

    Attributes
    ----------
    configured : bool
        A cell config is set (or the demo cell is in use).
    ready : bool
        Acquisitions can be queued: the configuration is usable (the cameras may still be unreachable).
    reason : str or None
        Why not ready (names :data:`CELL_SETTING`, or the file and field).
    cell_id, config, light_controller : str or None
        The configuration's cell id, its file name, its light controller (:func:`light_controller_label`).
    demo : bool
        The demo cell of simulated cameras and lights.
    cameras : tuple of CameraState
    in_use : str or None
        Who holds the cameras now (an acquisition job): the cameras' state is then the last known one.
    checked_at : datetime or None
        When the cameras were last checked.
    last_capture : dict or None
        :func:`last_capture`.
    """

    configured: bool
    ready: bool
    reason: str | None = None
    cell_id: str | None = None
    config: str | None = None
    light_controller: str | None = None
    demo: bool = False
    cameras: tuple[CameraState, ...] = ()
    in_use: str | None = None
    checked_at: datetime | None = None
    last_capture: dict[str, Any] | None = None


@dataclass
class _Probe:
    """One check of the cameras, run in a thread of its own; ``results`` fills as cameras answer."""

    config: CellConfig
    results: dict[str, CameraState] = field(default_factory=dict)
    finished: threading.Event = field(default_factory=threading.Event)
    started_at: datetime = field(default_factory=lambda: datetime.now(UTC))
    started: float = field(default_factory=time.monotonic)

    @property
    def key(self) -> tuple[Any, ...]:
        return _config_key(self.config)


@dataclass(frozen=True)
class _Known:
    """The answer of the last finished check: its cameras' configuration, the cameras, when it started."""

    key: tuple[Any, ...]
    cameras: tuple[CameraState, ...]
    checked_at: datetime
    finished: float


class CameraMonitor:
    """The cameras' state, checked lazily in a thread, cached briefly, never blocking for long.

    :meth:`state` answers from a check that finished less than ``ttl_s`` ago; else it starts one
    (unless one is still running) and waits for it until ``timeout_s`` after it started: a camera
    that has not answered by then (a GigE camera that vanished takes Aravis about 15 s to give up
    on) is reported ``unreachable``, and later calls neither wait nor start another check until
    that one has returned. No check runs while another process holds the cell's lock (a capture):
    the last known state is reported, with who holds the cameras.

    Parameters
    ----------
    settings : Settings
    ttl_s, timeout_s : float
        See :data:`STATE_TTL_S`, :data:`PROBE_TIMEOUT_S`.
    """

    def __init__(
        self, settings: Settings, *, ttl_s: float = STATE_TTL_S, timeout_s: float = PROBE_TIMEOUT_S
    ):
        self.settings = settings
        self.ttl_s = ttl_s
        self.timeout_s = timeout_s
        self._mutex = threading.Lock()
        self._probe: _Probe | None = None
        self._known: _Known | None = None

    def state(self) -> CellState:
        """The cell and its cameras now (see the class docstring)."""
        path = cell_config_path(self.settings)
        demo = path is not None and self.settings.cell_config is None
        capture = last_capture(self.settings.data_dir)
        try:
            config = load_cell(self.settings)
        except CellUnavailable as err:
            return CellState(
                configured=path is not None,
                ready=False,
                reason=err.detail,
                demo=demo,
                config=None if path is None else path.name,
                last_capture=capture,
            )
        cameras, checked_at, in_use = self._cameras(config, capture)
        return CellState(
            configured=True,
            ready=True,
            cell_id=config.cell_id,
            config=config.path.name,
            light_controller=light_controller_label(config),
            demo=demo,
            cameras=cameras,
            in_use=in_use,
            checked_at=checked_at,
            last_capture=capture,
        )

    def _cameras(
        self, config: CellConfig, capture: dict[str, Any] | None
    ) -> tuple[tuple[CameraState, ...], datetime | None, str | None]:
        """(cameras, when they were checked, who holds them instead)."""
        key = _config_key(config)
        with self._mutex:
            self._take_finished()
            known = self._known if self._known is not None and self._known.key == key else None
            if known is not None and time.monotonic() - known.finished < self.ttl_s:
                return known.cameras, known.checked_at, None
            probe = self._probe
            if probe is None or probe.finished.is_set():
                lock = CellLock(self.settings.data_dir)
                if not lock.acquire(f"the web server's camera check (pid {os.getpid()})"):
                    cameras = known.cameras if known is not None else _last_seen(config, capture)
                    return cameras, None if known is None else known.checked_at, lock.holder()
                probe = self._probe = _Probe(config)
                threading.Thread(
                    target=_run_probe, args=(probe, lock), name="camera-check", daemon=True
                ).start()
        probe.finished.wait(
            max(0.0, self.timeout_s - (time.monotonic() - probe.started))
        )  # a hung check: no wait
        with self._mutex:
            self._take_finished()
            if self._known is not None and self._known.key == key and probe.finished.is_set():
                return self._known.cameras, self._known.checked_at, None
            return (
                tuple(
                    probe.results.get(side) or _no_answer(config, side, self.timeout_s)
                    for side in SIDES
                ),
                probe.started_at,
                None,
            )

    def _take_finished(self) -> None:
        """Keep the answer of a check that has finished (hold the mutex)."""
        probe = self._probe
        if probe is None or not probe.finished.is_set():
            return
        if self._known is None or self._known.checked_at < probe.started_at:
            failed = "the check failed (see the server log)"
            cameras = tuple(
                probe.results.get(side)
                or replace(_no_answer(probe.config, side, 0.0), state="error", detail=failed)
                for side in SIDES
            )
            self._known = _Known(probe.key, cameras, probe.started_at, time.monotonic())


def _last_seen(config: CellConfig, capture: dict[str, Any] | None) -> tuple[CameraState, ...]:
    """The cameras as the last capture of this cell described them (connected then), else unknown."""
    cameras = []
    last = capture or {}
    seen_by_side = last.get("cameras", {}) if last.get("cell_id") == config.cell_id else {}
    for side in SIDES:
        cam_config = getattr(config, side)
        seen = seen_by_side.get(side)
        if seen is not None and seen.get("device_id") == cam_config.device_id:
            cameras.append(
                CameraState(
                    side,
                    cam_config.driver,
                    cam_config.device_id,
                    "connected",
                    seen.get("vendor"),
                    seen.get("model"),
                    seen.get("serial"),
                    detail=f"at the last capture ({last['captured_at']})",
                )
            )
        else:
            cameras.append(
                CameraState(
                    side,
                    cam_config.driver,
                    cam_config.device_id,
                    "unknown",
                    detail="not checked yet",
                )
            )
    return tuple(cameras)


def _config_key(config: CellConfig) -> tuple[Any, ...]:
    """What a check's answer depends on: the cameras as configured."""
    return (config.path.resolve(), config.left, config.right)


def _no_answer(config: CellConfig, side: str, timeout_s: float) -> CameraState:
    cam_config = getattr(config, side)
    return CameraState(
        side,
        cam_config.driver,
        cam_config.device_id,
        "unreachable",
        detail=f"no answer within {timeout_s:g} s",
    )


def _run_probe(probe: _Probe, lock: CellLock) -> None:
    """Open each camera, describe it, close it (in a thread; the lock is held throughout)."""
    config = probe.config
    try:
        cell = None
        if "simulated" in (config.left.driver, config.right.driver):
            controller = SimulatedLightController(config.lights.n, False)
            cell = SimulatedCell(
                config.rig, config.lights, config.working_distance_mm, controller, "camera-check"
            )
        for side in SIDES:
            probe.results[side] = _check_camera(side, getattr(config, side), cell)
    except Exception:
        log.exception("the camera check failed")
    finally:
        lock.release()
        probe.finished.set()


def _check_camera(side: Side, cam_config: CellCamera, cell: SimulatedCell | None) -> CameraState:
    base = CameraState(side, cam_config.driver, cam_config.device_id, "unknown")
    try:
        camera = open_camera(side, cam_config, cell=cell)
        try:
            described = camera.describe()
        finally:
            camera.close()
    except AcquisitionError as err:
        state = "unreachable" if err.step == "opening" else "error"
        return replace(base, state=state, detail=f"{err.step}: {err.reason}")
    except Exception as err:
        log.exception("%s camera check failed", side)
        return replace(base, state="error", detail=f"{type(err).__name__}: {err}")
    return replace(
        base,
        state="connected",
        vendor=described.get("vendor"),
        model=described.get("model"),
        serial=described.get("serial"),
    )
