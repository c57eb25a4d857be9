"""Background jobs (huey, SQLite storage under the data dir): run the pipeline on an inspection.

The web process only enqueues ids; a consumer process (:mod:`app.worker`) runs them, so the
pipeline's CPU work never starves the web server or the 3D view. The inspection row is the
source of truth: a task only carries the id, claims the row (queued -> running) before working,
and a task delivered twice runs once. huey drops a task when a worker picks it up, so a job
whose consumer died is re-queued from the database when the consumer starts
(:meth:`JobQueue.requeue_interrupted`).
"""

from __future__ import annotations

import importlib
import json
import logging
import time
from collections.abc import Callable
from pathlib import Path

from huey import SqliteHuey
from sqlalchemy.orm import Session, sessionmaker

from app.services import inspections as svc
from app.services import light_calibrations
from app.services.inspections import SIMULATION_FILE
from app.settings import Settings
from app.storage import Storage
from pipeline.formats import InputError, PipelineError

log = logging.getLogger(__name__)

TASK_NAME = "run_inspection"
#: Stage name reported while a simulated capture is rendered (before the pipeline's stages).
SIMULATE_STAGE = "simulate"


class JobQueue:
    """The huey queue of inspection jobs, shared by the web process (enqueue) and the consumer (run).

    Parameters
    ----------
    settings : Settings
    session_factory : sessionmaker
        Sessions on the service database (each job opens its own).
    storage : Storage
    immediate : bool
        Run tasks in the calling thread (unit tests of the job body only).
    """

    def __init__(self, settings: Settings, session_factory: sessionmaker[Session], storage: Storage, *, immediate=False):
        settings.data_dir.mkdir(parents=True, exist_ok=True)
        self.settings = settings
        self.session_factory = session_factory
        self.storage = storage
        self.huey = SqliteHuey(
            name="plate-inspect", filename=str(settings.huey_path), results=False, immediate=immediate
        )
        self._task = self.huey.task(name=TASK_NAME)(self._run_task)

    def enqueue(self, inspection_id: int) -> None:
        """Queue the job of a committed inspection row."""
        self._task(int(inspection_id))

    def pending_count(self) -> int:
        return self.huey.pending_count()

    def requeue_interrupted(self) -> list[int]:
        """Consumer start: rows left "running" go back to "queued", and every queued row is queued again.

        The huey queue is emptied first, so the database alone decides what runs (no duplicates
        from earlier deliveries; a duplicate would be harmless anyway, see :func:`execute_inspection`).
        """
        self.huey.storage.flush_queue()
        with self.session_factory() as session:
            ids = svc.requeue_interrupted(session=session)
            session.commit()
        for inspection_id in ids:
            self.enqueue(inspection_id)
        if ids:
            log.info("re-queued inspections %s", ids)
        return ids

    def create_consumer(self, **options):
        """A huey consumer of this queue (one worker thread by default; the pipeline uses the cores)."""
        defaults = dict(workers=1, worker_type="thread", periodic=False, max_delay=1.0, initial_delay=0.1)
        defaults.update(options)
        return self.huey.create_consumer(**defaults)

    def _run_task(self, inspection_id: int) -> None:
        execute_inspection(
            inspection_id, settings=self.settings, session_factory=self.session_factory, storage=self.storage
        )


class ProgressWriter:
    """The pipeline's progress callback: writes stage and fraction to the row, throttled.

    A write happens when the stage changes, at the end (fraction 1), or when
    ``interval_s`` has passed since the last write. A failed write (database busy) is logged
    and skipped: progress is informative, the job goes on.
    """

    def __init__(self, session_factory: sessionmaker[Session], inspection_id: int, *, interval_s: float):
        self.session_factory = session_factory
        self.inspection_id = inspection_id
        self.interval_s = interval_s
        self._last_stage: str | None = None
        self._last_time = float("-inf")

    def __call__(self, stage: str, fraction: float) -> None:
        now = time.monotonic()
        if stage == self._last_stage and fraction < 1.0 and now - self._last_time < self.interval_s:
            return
        try:
            with self.session_factory() as session:
                svc.record_progress(session=session, inspection_id=self.inspection_id, stage=stage, progress=fraction)
                session.commit()
        except ValueError:
            raise
        except Exception:  # noqa: BLE001 - a progress write must not fail the job
            log.warning("inspection %s: progress write skipped", self.inspection_id, exc_info=True)
            return
        self._last_stage, self._last_time = stage, now


def resolve_entry(entry: str) -> Callable:
    """The function named by ``"module:function"``."""
    module_name, _, attr = entry.partition(":")
    return getattr(importlib.import_module(module_name), attr)


def render_simulated_bundle(*, bundle_dir: Path, plate_id: str, simulation: dict) -> Path:
    """Render a simulated capture bundle into ``bundle_dir`` with the pipeline's simulator.

    Idempotent: an existing complete bundle (its ``capture.json`` present) is reused; a partial
    one left by a killed job is rendered again.
    """
    from pipeline.simulate import simulate_capture

    if (bundle_dir / "capture.json").is_file():
        return bundle_dir
    partial = bundle_dir.with_name(bundle_dir.name + ".partial")
    Storage.remove(partial)
    partial.mkdir(parents=True)
    try:
        plate, capture = svc.simulation_specs(simulation)
    except ValueError as err:  # the simulator refuses the described plate
        raise InputError(SIMULATION_FILE, "", str(err)) from None
    simulate_capture(
        partial,
        plate=plate,
        capture=capture,
        plate_id=plate_id,
        tolerance_mm=float(simulation["tolerance_mm"]),
        seed=int(simulation["seed"]),
    )
    partial.rename(bundle_dir)
    return bundle_dir


def execute_inspection(
    inspection_id: int, *, settings: Settings, session_factory: sessionmaker[Session], storage: Storage
) -> str:
    """Run one inspection job: claim the row, (render,) inspect, store done or failed.

    The light calibration recorded in the row at submission (if any) is read from its file and
    passed to the pipeline as ``light_calibration``; the result's ``warnings`` say whether it
    was applied.

    Returns
    -------
    str
        The row's final status, or ``"skipped"`` when the row was not queued (already taken,
        done or failed: a duplicate delivery).

    Notes
    -----
    Never raises for a job failure: bad input (:class:`InputError`) and unmeasurable captures
    (:class:`PipelineError`) store their one-line message; anything else stores
    ``"internal error: <type>: <message>"`` and logs the traceback.
    """
    with session_factory() as session:
        if not svc.claim(session=session, inspection_id=inspection_id):
            session.rollback()
            log.info("inspection %s: not queued, skipped", inspection_id)
            return "skipped"
        session.commit()
        row = svc.get_inspection(session=session, inspection_id=inspection_id)
        source, plate_id, simulation = row.source, row.plate_id, row.simulation
        capture_path, target_path = storage.absolute(row.capture_path), storage.absolute(row.target_path)
        light_calibration = row.light_calibration  # recorded at submission: a re-run uses the same lights

    progress = ProgressWriter(session_factory, inspection_id, interval_s=settings.progress_interval_s)
    log.info("inspection %s: running (%s, plate %s)", inspection_id, source, plate_id)
    try:
        out_dir = storage.clear_artifacts(inspection_id)
        if source == "simulated":
            progress(SIMULATE_STAGE, 0.0)
            render_simulated_bundle(bundle_dir=capture_path, plate_id=plate_id, simulation=simulation)
        lights = None
        if light_calibration is not None:
            lights = light_calibrations.load_lights(storage=storage, calibration=light_calibration)
        inspect = resolve_entry(settings.inspect_entry)
        result = inspect(capture_path, target_path, out_dir=out_dir, progress=progress, light_calibration=lights)
        document = json.loads(json.dumps(result.document))  # plain JSON types only
    except (InputError, PipelineError) as err:
        # Name the files as the client knows them (capture.zip, bundle/...), not by server path.
        inputs = str(storage.inputs_dir(inspection_id)) + "/"
        message = " ".join(str(err).replace(inputs, "").split()) or type(err).__name__
        log.info("inspection %s: failed: %s", inspection_id, message)
        return _finish_failed(session_factory, inspection_id, message)
    except Exception as err:  # noqa: BLE001 - stored as failed, never lost
        log.exception("inspection %s: internal error", inspection_id)
        return _finish_failed(session_factory, inspection_id, f"internal error: {type(err).__name__}: {err}")
    with session_factory() as session:
        svc.mark_done(session=session, inspection_id=inspection_id, document=document)
        session.commit()
    log.info("inspection %s: done, verdict %s", inspection_id, document.get("verdict"))
    return "done"


def _finish_failed(session_factory, inspection_id: int, message: str) -> str:
    with session_factory() as session:
        svc.mark_failed(session=session, inspection_id=inspection_id, error=message)
        session.commit()
    return "failed"
