"""Stations reconstructed as they arrive: each station, once photographed, goes through the stages of
one view on a worker thread while the conveyor carries the plate on and the next one is photographed;
after the last, only the registration, the mosaic and the whole plate's judgement remain
(docs/stations.md, *Reconstructed as they arrive*).

:func:`pipeline.acquisition.acquire_stations` feeds it through its ``station_done`` hook; the one entry
point takes it (``pipeline.run.inspect(..., early=...)``), which hands each station's result to
:func:`pipeline.stations.measure_stations` in place of reconstructing it. One worker thread: the
reconstruction's parallel numba kernels take both cores, and may run on one thread at a time (the
acquisition beside it mostly waits on the conveyor and the cameras).
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
import threading
from concurrent.futures import Future, ThreadPoolExecutor, wait
from dataclasses import replace
from pathlib import Path
from types import TracebackType
from typing import Any

from pipeline.formats import CaptureError, InputError, PipelineError
from pipeline.io import Target, load_target
from pipeline.lights.model import Lights
from pipeline.parallel import single_threaded_blas
from pipeline.stages import InspectOptions

from .inspect import StationResult, reconstruct_station
from .plan import StationRef, station_ref

log = logging.getLogger(__name__)


class EarlyStations:
    """The stations of one acquisition, reconstructed on a worker thread as each is photographed.

    Parameters
    ----------
    target : Target, dict or path
        The plate's target, as the inspection will be given it (it is loaded here once).
    stations_dir : path
        Where the stations' bundles end up (``out_dir`` of
        :func:`~pipeline.acquisition.acquire_stations`): the stations are named by their bundles
        there, as the inspection of the written bundles names them.
    options : InspectOptions, optional
    light_calibration : Lights, optional
        As the inspection will be given them.

    The hook :meth:`station_done` links each bundle's files into a folder of its own beside
    ``stations_dir`` (the acquisition renames its partial folder at the end, and removes it on a
    failure) and queues its reconstruction. :meth:`result` gives a station's result, waiting for it,
    or raises the error its reconstruction raised, renamed to the station's final bundle (a station
    that failed stops the reconstruction of those after it). Use it as a context manager, or call
    :meth:`close`: the worker is stopped and the links removed.

    While it lives, BLAS runs on one thread in the whole process, as during
    :func:`pipeline.run.inspect` (whose limit is process-wide too): the stations are reconstructed
    exactly as an inspection of their bundles would, and the limit nests with the inspection's
    (this object is made before the inspection and closed after it).
    """

    def __init__(
        self,
        target: Target | dict[str, Any] | str | os.PathLike[str],
        stations_dir: str | os.PathLike[str],
        *,
        options: InspectOptions | None = None,
        light_calibration: Lights | None = None,
    ) -> None:
        self.target = target
        self.options = options or InspectOptions()
        self.light_calibration = light_calibration
        self._tgt = target if isinstance(target, Target) else load_target(target)
        self._final = Path(stations_dir)
        self._links: Path | None = None
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="early-station")
        self._jobs: dict[int, Future[StationResult | None]] = {}
        self._failed = threading.Event()
        # as pipeline.run.inspect: BLAS calls here are small, its threads would only spin
        self._blas = single_threaded_blas()

    def __enter__(self) -> EarlyStations:
        return self

    def __exit__(
        self,
        kind: type[BaseException] | None,
        err: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def station_done(self, index: int, bundle: str | os.PathLike[str]) -> None:
        """The acquisition's hook: station ``index``'s bundle is complete at ``bundle``.

        Never stops the acquisition: a bundle that cannot be linked (a full disk) is left to the
        inspection, which reconstructs it from where it is written (a warning is logged).
        """
        src = Path(bundle)
        try:
            if self._links is None:
                self._final.parent.mkdir(parents=True, exist_ok=True)
                self._links = Path(
                    tempfile.mkdtemp(prefix=f".{self._final.name}.early-", dir=self._final.parent)
                )
            linked = self._links / src.name
            shutil.copytree(src, linked, copy_function=_link)
        except OSError as err:
            log.warning("station %d (%s): not reconstructed early: %s", index, src, err)
            return
        self._jobs[index] = self._pool.submit(
            self._reconstruct, index, linked, self._final / src.name
        )

    def matches(
        self,
        target: Target | dict[str, Any] | str | os.PathLike[str],
        options: InspectOptions,
        light_calibration: Lights | None,
    ) -> bool:
        """Whether an inspection with these inputs may take these stations' results."""
        same_target = target is self.target or (
            isinstance(target, (str, os.PathLike))
            and isinstance(self.target, (str, os.PathLike))
            and Path(target) == Path(self.target)
        )
        return (
            same_target and options == self.options and light_calibration is self.light_calibration
        )

    def result(self, ref: StationRef) -> StationResult | None:
        """The station of ``ref`` reconstructed (waiting for it), or None when this acquisition did
        not reconstruct that bundle. Raises the error its reconstruction raised."""
        job = self._jobs.get(ref.station.index)
        station = None if job is None else job.result()
        if station is None or station.ref.label != ref.label:
            # the caller reconstructs it: on its own thread, so none of ours may run meanwhile
            wait(self._jobs.values())
            return None
        return station

    def close(self) -> None:
        """Stop the worker (a station under way is finished, the others dropped); remove the links."""
        self._pool.shutdown(wait=True, cancel_futures=True)
        self._blas.restore_original_limits()
        if self._links is not None:
            shutil.rmtree(self._links, ignore_errors=True)

    def _reconstruct(self, index: int, linked: Path, final: Path) -> StationResult | None:
        """Station ``index`` from its linked bundle, named by its ``final`` bundle."""
        if self._failed.is_set():
            return None  # a station before it failed: the inspection ends with that error
        try:
            ref = station_ref(linked)
            station = reconstruct_station(ref, self._tgt, self.options, self.light_calibration)
        except Exception as err:
            self._failed.set()
            raise _renamed(err, index, linked, final) from err
        finally:
            shutil.rmtree(linked, ignore_errors=True)
        label = ref.label.replace(str(linked), str(final))
        return replace(
            station,
            ref=replace(station.ref, source=final, label=label),
            view=replace(station.view, label=label),
        )


def _link(src: str, dst: str) -> None:
    """A hard link of ``src`` at ``dst`` (a copy across file systems)."""
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def _renamed(err: Exception, index: int, linked: Path, final: Path) -> Exception:
    """``err`` of station ``index`` read from ``linked``, naming its ``final`` bundle: the same kind
    of error (an InputError, a PipelineError), or a RuntimeError naming the station for any other."""
    label = str(final / "capture.json")

    def named(text: str) -> str:
        text = text.replace(str(linked), str(final))
        return text if str(final) in text else f"{label}: station {index}: {text}"

    if isinstance(err, InputError):
        return InputError(
            err.file.replace(str(linked), str(final)),
            err.field,
            err.reason.replace(str(linked), str(final)),
        )
    if isinstance(err, PipelineError):
        try:
            return type(err)(named(str(err)))
        except TypeError:
            return CaptureError(named(str(err)))
    return RuntimeError(
        f"{label}: station {index}: the station's reconstruction failed: "
        f"{type(err).__name__}: {str(err).replace(str(linked), str(final))}"
    )
