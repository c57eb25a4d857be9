"""One inspection job: claim the row under a lease, (render,) inspect, store done or failed.

Runs in the consumer (:mod:`app.worker`); see :class:`app.services.leases.LeaseKeeper` for the lease and
:mod:`app.jobs.memory` for the memory bound.
"""

from __future__ import annotations

import importlib
import json
import logging
import os
import tempfile
import time
from collections.abc import Mapping
from contextlib import ExitStack
from pathlib import Path
from typing import Any, TypedDict

import numpy as np
from sqlalchemy.orm import Session, sessionmaker

from app.jobs.memory import is_out_of_memory, out_of_memory_message
from app.models import JobStatus, LightCalibration
from app.services import inspections as svc
from app.services import leases, light_calibrations
from app.services.acquisitions import ACQUIRED_SOURCE, capture_for_job
from app.services.inspections import SIMULATION_FILE
from app.services.leases import LeaseKeeper
from app.services.stations import capture_bundles
from app.settings import InspectFunction, Settings
from app.storage import Storage
from pipeline.acquisition import add_after_last_frame
from pipeline.formats import InputError, PipelineError
from pipeline.lights import Lights

log = logging.getLogger(__name__)

#: Stage name reported while a simulated capture is rendered (before the pipeline's stages).
SIMULATE_STAGE = "simulate"
#: Suffix (then ``-<random>``) of the folders a simulated bundle is rendered into, beside the bundle.
PARTIAL_SUFFIX = ".partial"


class ProgressWriter:
    """The pipeline's progress callback: writes stage and fraction to the row, throttled.

    A write happens when the stage changes, at the end (fraction 1), or when
    ``interval_s`` has passed since the last write; it is a no-op once ``owner`` no longer holds
    the job's lease. A failed write (database busy) is logged and skipped: progress is
    informative, the job goes on.
    """

    def __init__(
        self,
        session_factory: sessionmaker[Session],
        inspection_id: int,
        *,
        interval_s: float,
        owner: str | None = None,
    ):
        self.session_factory = session_factory
        self.inspection_id = inspection_id
        self.interval_s = interval_s
        self.owner = owner or leases.process_lease_owner()
        self._last_stage: str | None = None
        self._last_time = float("-inf")

    def __call__(self, stage: str, fraction: float) -> None:
        now = time.monotonic()
        if stage == self._last_stage and fraction < 1.0 and now - self._last_time < self.interval_s:
            return
        try:
            with self.session_factory() as session:
                leases.record_progress(
                    session=session,
                    inspection_id=self.inspection_id,
                    stage=stage,
                    progress=fraction,
                    owner=self.owner,
                )
                session.commit()
        except ValueError:
            raise
        except Exception:
            log.warning("inspection %s: progress write skipped", self.inspection_id, exc_info=True)
            return
        self._last_stage, self._last_time = stage, now


def warm_up_entry(inspect: InspectFunction) -> float | None:
    """Load the compiled kernels of the inspection entry's module (its ``warm_up()``, as
    :func:`pipeline.run.warm_up`) so that no job pays for them; its run time (s), or None when
    the module has none (a stand-in pipeline)."""
    module = importlib.import_module(inspect.__module__)
    warm = getattr(module, "warm_up", None)
    return None if warm is None else float(warm())


def render_simulated_bundle(*, bundle_dir: Path, plate_id: str, simulation: dict[str, Any]) -> Path:
    """Render a simulated capture bundle into ``bundle_dir`` with the pipeline's simulator.

    Idempotent: an existing complete bundle (its ``capture.json`` present) is reused. The bundle is
    rendered into a new folder of its own beside it (``bundle.partial-<random>``), then renamed
    into place, so folders left by a killed run (removed first) or a concurrent one never collide
    with it.
    """
    from pipeline.simulate import simulate_capture

    bundle_dir = Path(bundle_dir)
    if (bundle_dir / "capture.json").is_file():
        return bundle_dir
    try:
        plate, capture = svc.simulation_specs(simulation)
    except ValueError as err:  # the simulator refuses the described plate
        raise InputError(SIMULATION_FILE, "", str(err)) from None
    bundle_dir.parent.mkdir(parents=True, exist_ok=True)
    for leftover in bundle_dir.parent.glob(bundle_dir.name + PARTIAL_SUFFIX + "*"):
        Storage.remove(leftover)
    partial = Path(
        tempfile.mkdtemp(prefix=bundle_dir.name + PARTIAL_SUFFIX + "-", dir=bundle_dir.parent)
    )
    try:
        simulate_capture(
            partial,
            plate=plate,
            capture=capture,
            plate_id=plate_id,
            tolerance_mm=float(simulation["tolerance_mm"]),
            seed=int(simulation["seed"]),
        )
        if bundle_dir.exists() and not (bundle_dir / "capture.json").is_file():
            Storage.remove(bundle_dir)  # an incomplete bundle: replaced
        if not bundle_dir.exists():
            os.rename(partial, bundle_dir)
    finally:
        Storage.remove(partial)
    return bundle_dir


def execute_inspection(
    inspection_id: int,
    *,
    settings: Settings,
    session_factory: sessionmaker[Session],
    storage: Storage,
    owner: str | None = None,
) -> str:
    """Run one inspection job: claim the row under a lease, (render,) inspect, store done or failed.

    The light calibration recorded in the row at submission (if any) is read from its file and
    passed to the pipeline as ``light_calibration``; the result's ``warnings`` say whether it
    was applied. The lease (``settings.job_lease_s``) is renewed while the job runs; the result
    is stored only if it is still held.

    Parameters
    ----------
    inspection_id : int
    settings : Settings
    session_factory : sessionmaker
    storage : Storage
    owner : str, optional
        Lease owner; default :func:`app.services.leases.process_lease_owner`.

    Returns
    -------
    str
        The row's final status (``"done"``, ``"error"``); ``"skipped"`` when the row was not
        claimable (done, failed, or run by another consumer: a duplicate delivery); ``"lost"`` when
        the lease was lost while the job ran (another consumer or a stop took it over).

    Notes
    -----
    Never raises for a job failure: bad input (:class:`InputError`) and unmeasurable captures
    (:class:`PipelineError`) store their one-line message; running out of memory stores
    :func:`app.jobs.memory.out_of_memory_message`; anything else stores
    ``"internal error: <type>: <message>"`` and logs the traceback. Stored messages name files
    relative to the inspection's inputs or the data dir, never by server path.
    """
    owner = owner or leases.process_lease_owner()
    job = _claim(inspection_id, settings, session_factory, storage, owner=owner)
    if job is None:
        return "skipped"
    progress = ProgressWriter(
        session_factory, inspection_id, interval_s=settings.progress_interval_s, owner=owner
    )
    message, document = None, {}
    with LeaseKeeper(
        session_factory, inspection_id, owner=owner, lease_s=settings.lease_s
    ) as lease:
        try:
            document = _run(inspection_id, settings, storage, progress, **job)
        except (InputError, PipelineError) as err:
            message = _client_message(str(err), storage, inspection_id) or type(err).__name__
            log.info("inspection %s: failed: %s", inspection_id, message)
        except Exception as err:
            if is_out_of_memory(err):
                message = out_of_memory_message(settings.worker_memory_mb)
                log.error("inspection %s: %s", inspection_id, message)
            else:
                log.exception("inspection %s: internal error", inspection_id)
                text = _client_message(str(err), storage, inspection_id)
                message = f"internal error: {type(err).__name__}: {text}"
    stored = _store(session_factory, inspection_id, owner, document=document, message=message)
    if not stored:
        log.warning(
            "inspection %s: lease lost while it ran%s; its result is not stored by this consumer",
            inspection_id,
            " (renewal refused)" if lease.lost.is_set() else "",
        )
        return "lost"
    if message is not None:
        return JobStatus.ERROR
    log.info("inspection %s: done, verdict %s", inspection_id, document.get("verdict"))
    return JobStatus.DONE


class _JobInputs(TypedDict):
    """A claimed job's inputs: the keyword arguments of :func:`_run`."""

    source: str
    plate_id: str
    simulation: dict[str, Any] | None
    capture_path: Path
    target_path: Path
    light_calibration: LightCalibration | None


def _claim(
    inspection_id: int,
    settings: Settings,
    session_factory: sessionmaker[Session],
    storage: Storage,
    *,
    owner: str,
) -> _JobInputs | None:
    """Claim the row under a lease; the job's inputs (keyword arguments of :func:`_run`), or None
    when the row is not claimable (done, failed, or run by another consumer)."""
    with session_factory() as session:
        if not leases.claim(
            session=session, inspection_id=inspection_id, owner=owner, lease_s=settings.lease_s
        ):
            session.rollback()
            log.info("inspection %s: not claimable (done, failed or taken), skipped", inspection_id)
            return None
        session.commit()
        row = svc.get_inspection(session=session, inspection_id=inspection_id)
        if row is None or row.capture_path is None or row.target_path is None:
            raise RuntimeError(
                f"inspection {inspection_id}: claimed, but its row or inputs are gone"
            )
        log.info(
            "inspection %s: running (%s, plate %s, attempt %s%s)",
            inspection_id,
            row.source,
            row.plate_id,
            row.attempts,
            f", after {row.deaths} worker death(s)" if row.deaths else "",
        )
        return _JobInputs(
            source=row.source,
            plate_id=row.plate_id,
            simulation=row.simulation,
            capture_path=storage.absolute(row.capture_path),
            target_path=storage.absolute(row.target_path),
            # recorded at submission: a re-run uses the same lights
            light_calibration=row.light_calibration,
        )


def _store(
    session_factory: sessionmaker[Session],
    inspection_id: int,
    owner: str,
    *,
    document: dict[str, Any],
    message: str | None,
) -> bool:
    """Store done (``message`` None) or failed; False when ``owner`` no longer holds the lease."""
    with session_factory() as session:
        if message is None:
            stored = leases.mark_done(
                session=session, inspection_id=inspection_id, document=document, owner=owner
            )
        else:
            stored = leases.mark_error(
                session=session, inspection_id=inspection_id, error=message, owner=owner
            )
        session.commit()
    return stored


def _run(
    inspection_id: int,
    settings: Settings,
    storage: Storage,
    progress: ProgressWriter,
    *,
    source: str,
    plate_id: str,
    simulation: dict[str, Any] | None,
    capture_path: Path,
    target_path: Path,
    light_calibration: LightCalibration | None,
) -> dict[str, Any]:
    """The job's work: render a simulated capture or acquire one, load the lights, measure the bundles;
    the result document."""
    out_dir = storage.clear_artifacts(inspection_id)
    if source == "simulated":
        progress(SIMULATE_STAGE, 0.0)
        if simulation is None:
            raise ValueError(f"inspection {inspection_id}: simulated, but without its parameters")
        render_simulated_bundle(bundle_dir=capture_path, plate_id=plate_id, simulation=simulation)
    lights = None
    if light_calibration is not None:
        lights = light_calibrations.load_lights(storage=storage, calibration=light_calibration)
    if source != ACQUIRED_SOURCE:
        return measure_bundles(
            settings.inspect_entry,
            capture_bundles(capture_path),
            target_path,
            out_dir,
            progress=progress,
            lights=lights,
        )
    with ExitStack() as stack:
        # a cell with a conveyor: each station reconstructed while the next is photographed
        early = _early_stations(settings.inspect_entry, target_path, capture_path, lights)
        if early is not None:
            stack.enter_context(early)
        captured = capture_for_job(
            inspection_id,
            settings=settings,
            storage=storage,
            plate_id=plate_id,
            bundle_dir=capture_path,
            progress=progress,
            station_done=None if early is None else early.station_done,
        )
        document = measure_bundles(
            settings.inspect_entry,
            captured.bundles,
            target_path,
            out_dir,
            progress=progress,
            lights=lights,
            early=early,
            frames=captured.frames,
        )
    if captured.last_frame_at is not None:
        add_after_last_frame(document, out_dir, captured.last_frame_at)
    return document


def _early_stations(
    inspect: InspectFunction, target_path: Path, stations_dir: Path, lights: Lights | None
) -> Any:
    """The inspection entry's reconstruction of stations as they arrive (its module's
    ``EarlyStations``, as :class:`pipeline.stations.EarlyStations`, made with the target and lights
    the entry will be given), or None when the module has none (a stand-in pipeline)."""
    module = importlib.import_module(inspect.__module__)
    early = getattr(module, "EarlyStations", None)
    return None if early is None else early(target_path, stations_dir, light_calibration=lights)


def measure_bundles(
    inspect: InspectFunction,
    bundles: list[Path],
    target_path: Path,
    out_dir: Path,
    *,
    progress: ProgressWriter,
    lights: Lights | None,
    early: Any = None,
    frames: Mapping[str, np.ndarray] | None = None,
) -> dict[str, Any]:
    """Measure a job's capture bundles with the inspection entry (:func:`pipeline.run.inspect`): one
    bundle as itself, several as the conveyor stations of one plate (the entry reports each station's
    stages as ``station 2/4: normals``); the result document, plain JSON types only.

    Every source of bundles comes here: an upload (one bundle, or a plate's stations), a simulated
    capture, an acquisition (one bundle, or the stations of a cell with a conveyor). ``early``: the
    stations reconstructed while they were photographed (see :func:`_early_stations`), passed to the
    entry for several bundles. ``frames``: one bundle's images already in memory (an acquisition's),
    loaded from there instead of decoded again.
    """
    capture: Path | list[Path] = bundles[0] if len(bundles) == 1 else list(bundles)
    more: dict[str, Any] = {} if early is None or len(bundles) == 1 else {"early": early}
    if frames and len(bundles) == 1:
        more["frames"] = frames
    result = inspect(
        capture, target_path, out_dir=out_dir, progress=progress, light_calibration=lights, **more
    )
    document: dict[str, Any] = json.loads(json.dumps(result.document))
    return document


def _client_message(text: str, storage: Storage, inspection_id: int) -> str:
    """``text`` on one line, with server paths made relative: to the inspection's inputs
    (``capture.zip``, ``bundle/...``, as the client knows them), else to the data dir."""
    for prefix in (storage.inputs_dir(inspection_id), storage.data_dir):
        text = text.replace(str(prefix) + "/", "").replace(str(prefix), ".")
    return " ".join(text.split())
