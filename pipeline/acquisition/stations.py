"""A plate longer than the view, photographed station by station: one ``plate-capture/1`` bundle per
conveyor station (docs/stations.md, "Acquisition").

1. Read the configuration (it must have a ``conveyor``); refuse an output folder that exists.
2. Connect the conveyor, then the light controller and the cameras as :func:`~pipeline.acquisition.acquire`
   does.
3. For each station in order: carry the plate there and read the encoder
   (:meth:`~pipeline.acquisition.conveyor.Conveyor.go_to_station`), photograph it exactly as
   ``acquire`` photographs one plate (auto-exposure, photometric images, dark frame, stereo pair),
   and write ``OUT/station_NN`` (through ``OUT/station_NN.partial``, renamed when complete) with its
   ``station``: ``index``, ``travel_mm`` (the encoder's reading less station 0's) and the configured
   ``direction``.

On any failure everything written is removed (``OUT`` included), whatever was switched on is switched
off, and the error names the device and the step (a conveyor's: the station and its position).
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack
from datetime import UTC, datetime
from pathlib import Path

from ..formats import InputError
from .acquire import FRAME_TIMEOUT_S, PNG_WRITERS, Progress, open_devices, take_bundle
from .config import load_cell_config
from .conveyor import open_conveyor

#: ``station_done(index, bundle)``: station ``index``'s bundle is complete at ``bundle``.
StationDone = Callable[[int, Path], None]


def acquire_stations(
    config_path: str | os.PathLike[str],
    plate_id: str,
    out_dir: str | os.PathLike[str],
    *,
    progress: Progress | None = None,
    station_done: StationDone | None = None,
    frame_timeout_s: float = FRAME_TIMEOUT_S,
) -> list[Path]:
    """Carry a plate station by station under the head and write one bundle per station.

    Parameters
    ----------
    config_path : str or Path
        A ``cell-config/1`` file with a ``conveyor``.
    plate_id : str
        Written into every bundle; a simulated cell renders a plate seeded by it.
    out_dir : str or Path
        The folder of the stations' bundles; it must not exist (its parent is created). They are
        written into ``out_dir.partial`` (one left by a killed acquisition is removed first), renamed
        to ``out_dir`` once the last station is taken: ``out_dir`` exists only with every station.
    progress : callable, optional
        ``progress(stage, fraction)`` after each step: ``stage`` begins ``"station 2/4: "`` (1-based),
        ``fraction`` is of the whole plate (each station an equal share).
    station_done : callable, optional
        ``station_done(index, bundle)`` when a station's bundle is complete (0-based ``index``), before
        the conveyor moves on: a caller may start measuring it while the next one is photographed.
        ``bundle`` is then inside ``out_dir.partial`` (it moves with the rename at the end).
    frame_timeout_s : float
        Seconds a frame may take beyond its exposure before the camera counts as gone.

    Returns
    -------
    list of Path
        ``out_dir / "station_00"``, ``station_01``, ...: each a ``plate-capture/1`` bundle as
        :func:`~pipeline.acquisition.acquire` writes one, with ``station`` and, in its acquisition
        record, ``conveyor`` (the driver, the station's ``target_mm``, the encoder's ``encoder_mm``
        and the move's ``move_s``).

    Raises
    ------
    InputError
        A bad configuration (file and field named) or one without a conveyor, an existing
        ``out_dir``, and what :func:`~pipeline.acquisition.acquire` refuses of a camera.
    AcquisitionError
        A device that is missing, refuses, times out or disappears, the conveyor's included (named
        ``conveyor HOST:PORT``, the step naming the station and its position); a plate the encoder
        puts nearer another station than its own. Nothing is left in ``out_dir``.
    """
    if not plate_id:
        raise ValueError("plate_id: expected a non-empty plate id")
    config = load_cell_config(config_path)
    if config.conveyor is None:
        raise InputError(
            config.label,
            "conveyor",
            "missing: this cell photographs one view (acquire writes its one bundle)",
        )
    stations_mm = config.conveyor.stations_mm
    out = Path(out_dir)
    if out.exists():
        raise InputError(str(out), "", "already exists; acquire writes a new folder of stations")
    partial = out.with_name(out.name + ".partial")
    if partial.exists():
        shutil.rmtree(partial)  # left by an acquisition that was killed
    partial.mkdir(parents=True)
    report = progress or (lambda stage, fraction: None)
    n = len(stations_mm)
    bundles: list[Path] = []
    try:
        with ExitStack() as stack:
            writer = stack.enter_context(ThreadPoolExecutor(max_workers=PNG_WRITERS))
            report("connecting the conveyor", 0.0)
            conveyor = open_conveyor(config.conveyor, plate_id=plate_id)
            stack.callback(conveyor.close)
            run = open_devices(
                stack, config, plate_id, partial, writer, frame_timeout_s, report, conveyor
            )
            for k in range(n):

                def station_progress(stage: str, fraction: float, k: int = k) -> None:
                    report(f"station {k + 1}/{n}: {stage}", (k + fraction) / n)

                station_progress(f"moving to {stations_mm[k]:g} mm", 0.0)
                t_move = time.monotonic()
                travel_mm = conveyor.go_to_station(k)
                move_s = time.monotonic() - t_move
                bundle = partial / f"station_{k:02d}"
                bundle.mkdir()
                take_bundle(
                    run.next_bundle(bundle, station_progress),
                    plate_id,
                    datetime.now(UTC),
                    station={
                        "index": k,
                        "travel_mm": round(travel_mm, 3),
                        "direction": [float(v) for v in conveyor.direction],
                    },
                    conveyor=conveyor.describe()
                    | {
                        "target_mm": stations_mm[k],
                        "encoder_mm": conveyor.readings_mm[-1],
                        "move_s": round(move_s, 3),
                    },
                )
                bundles.append(bundle)
                if station_done is not None:
                    station_done(k, bundle)
        os.rename(partial, out)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    return [out / bundle.name for bundle in bundles]
