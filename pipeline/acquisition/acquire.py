"""The acquisition sequence: from a cell configuration to a ``plate-capture/1`` bundle.

1. Read the configuration and what it names (:func:`~pipeline.acquisition.config.load_cell_config`);
   refuse an output folder that exists.
2. Connect the light controller, open both cameras; choose the best monochrome pixel format both
   offer (Mono16, Mono14, Mono12, Mono10, Mono8: unpacked, ``bit_depth`` its bits); set a region of
   the calibration's ``image_size`` centred on each sensor; set the gain (the configuration's
   ``gain_db``, else the camera's lowest).
3. Exposure: the configuration's ``exposure_us``, or auto-exposure pre-shots (:func:`auto_exposure`)
   with all photometric lights on (left camera: that lighting bounds every single light's frame)
   and with the stereo lighting (both cameras).
4. The stereo pair: the stereo light on (``stereo_on``), or else every photometric light; both
   cameras triggered before either frame is read (together), or back to back where a camera has no
   software trigger; the lighting off. Without a stereo light, a configured ``exposure_us`` is
   divided by the number of lights for the stereo pair (all of them together are as bright as one).
5. The dark frame: a left frame with every light off, at the photometric exposure.
6. Photometric images, light by light in image order: light k on, a left frame, light k off. They
   come last so that an inspection that follows folds each frame as it arrives
   (:mod:`pipeline.acquisition.streaming`) and has only the last image's share left when it arrives.
7. ``capture.json`` with an ``acquisition`` record, the calibration, the images (16-bit PNG, 8-bit
   for Mono8).

Everything is written into ``OUT.partial`` beside ``OUT`` and renamed to ``OUT`` at the end; on any
failure the partial folder is removed, whatever was switched on is switched off, and the error
names the device and the step.

Kept as one module (~620 lines): the steps above share the open devices and the run folder and
undo in one place when one fails; split, each would pass the run around. A cell with a conveyor
(:mod:`~pipeline.acquisition.stations`) opens the devices once (:func:`open_devices`) and takes
each station's bundle as one plate's (:func:`take_bundle`, :meth:`Run.next_bundle`).
"""

from __future__ import annotations

import json
import os
import shutil
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import ExitStack
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ..formats import CAPTURE_FORMAT, AcquisitionError, CaptureFile, CellCamera, InputError
from .cameras import (
    PIXEL_FORMATS,
    Camera,
    Frame,
    Side,
    SimulatedCell,
    choose_pixel_format,
    open_camera,
)
from .config import CellConfig, load_cell_config
from .conveyor import Conveyor
from .lights import LightController, open_light_controller
from .streaming import StreamedFrames

#: Seconds a frame may take beyond its exposure time before the camera is taken to be gone.
FRAME_TIMEOUT_S = 2.0
#: Threads encoding the frames' PNGs beside the sequence: the stereo pair comes last, both frames at
#: once, and its two files are what the bundle waits for after the last frame.
PNG_WRITERS = 2
#: How a frame's PNG is written: stored (deflate level 0), rows unfiltered. A camera frame is mostly
#: sensor noise that deflate barely shrinks: OpenCV's default took 100 ms a 2448x2048 16-bit frame
#: for 8.5 MB, this takes 18 ms for 10.0 MB (lossless either way; an archive may recompress). At 25
#: frames a second two writers kept up with the cameras only with the cores to themselves.
FRAME_PNG = [cv2.IMWRITE_PNG_COMPRESSION, 0, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_NONE]
#: Auto-exposure: the brightest samples (this percentile of a pre-shot) ...
BRIGHTEST_PERCENTILE = 99.9
#: ... are kept at or under this fraction of full scale ...
EXPOSURE_LIMIT = 0.9
#: ... and above this one where the camera's exposure range allows ...
EXPOSURE_FLOOR = 0.45
#: ... aiming at this fraction when scaling the exposure from a pre-shot.
EXPOSURE_TARGET = 0.75
#: A pre-shot this bright is saturated: the exposure is cut by :data:`SATURATED_CUT`.
SATURATED = 0.98
SATURATED_CUT = 8.0
#: Auto-exposure gives up after this many pre-shots of one camera.
MAX_PRE_SHOTS = 8
#: The first pre-shot's exposure (microseconds), within the camera's range.
FIRST_PRE_SHOT_US = 10_000.0

Progress = Callable[[str, float], None]


@dataclass
class Run:
    """What one bundle's acquisition has taken so far, on the open devices (:func:`open_devices`)."""

    config: CellConfig
    controller: LightController
    left: Camera
    right: Camera
    folder: Path
    writer: ThreadPoolExecutor
    timeout_s: float
    progress: Progress
    n_frames: int
    bit_depth: int
    t0: float = field(default_factory=time.monotonic)
    frames: list[dict[str, Any]] = field(default_factory=list)
    writes: list[Future[None]] = field(default_factory=list)
    exposure_us: dict[Side, float] = field(default_factory=dict)
    pre_shots: int = 0
    #: Receives each capture frame's image by its file name, when given (see :func:`acquire`).
    images: dict[str, np.ndarray] | None = None

    def next_bundle(self, folder: Path, progress: Progress) -> Run:
        """A fresh run on the same open devices, writing into ``folder`` (the next station's bundle):
        no frame taken, no exposure set, its clock started now."""
        return replace(
            self,
            folder=folder,
            progress=progress,
            t0=time.monotonic(),
            frames=[],
            writes=[],
            exposure_us={},
            pre_shots=0,
            images=None,
        )

    def elapsed(self) -> float:
        """Seconds since the acquisition started."""
        return time.monotonic() - self.t0

    def keep(
        self, name: str, camera: Camera, frame: Frame, lighting: str | list[int], t_s: float
    ) -> None:
        """Record a capture frame received ``t_s`` after the start, and queue it for writing as ``name``."""
        self.frames.append(
            {
                "file": name,
                "camera": camera.side,
                "lights": lighting,
                "exposure_us": self.exposure_us[camera.side],
                "t_s": round(t_s, 6),
                "device_timestamp_ns": frame.device_timestamp_ns,
                "frame_id": frame.frame_id,
            }
        )
        self.writes.append(self.writer.submit(_write_png, self.folder / name, frame.image))
        if self.images is not None:
            self.images[name] = frame.image
        self.progress(f"{name} taken", len(self.frames) / self.n_frames)

    def expose(self, camera: Camera, exposure_us: float, *, step: str) -> None:
        self.exposure_us[camera.side] = camera.set_exposure(exposure_us, step=step)

    def timeout(self, camera: Camera) -> float:
        return self.timeout_s + self.exposure_us[camera.side] * 1e-6


def _write_png(path: Path, image: np.ndarray) -> None:
    if not cv2.imwrite(str(path), image, FRAME_PNG):
        raise OSError(f"{path}: could not write the image")


def brightest_fraction(image: np.ndarray, bit_depth: int) -> float:
    """The image's brightest samples (:data:`BRIGHTEST_PERCENTILE`) as a fraction of full scale.

    A percentile, not the maximum, so that a few hot pixels or glints do not set the exposure.
    """
    full_scale: int = 2**bit_depth - 1
    return float(np.percentile(image[::2, ::2], BRIGHTEST_PERCENTILE)) / full_scale


def auto_exposure(
    cameras: list[Camera], *, bit_depth: int, timeout_s: float, step: str
) -> tuple[dict[Side, float], int]:
    """Pre-shots under the present lighting until each camera's brightest samples lie between
    :data:`EXPOSURE_FLOOR` and :data:`EXPOSURE_LIMIT` of full scale.

    Each round triggers every camera still metering, then scales its exposure towards
    :data:`EXPOSURE_TARGET` from what it saw (cut by :data:`SATURATED_CUT` when saturated); where
    that leaves the bracket of exposures already seen too dark and too bright (a camera that is not
    linear), it bisects the bracket instead. A camera at the top of its exposure range that is
    still too dark keeps that exposure.

    Parameters
    ----------
    cameras : list of Camera
        Started cameras.
    bit_depth : int
    timeout_s : float
        Seconds a frame may take beyond its exposure.
    step : str
        Names the step in an error.

    Returns
    -------
    (exposures, n)
        Exposure (microseconds) by camera side, and the number of pre-shots taken.

    Raises
    ------
    AcquisitionError
        A camera that saturates at its shortest exposure, or has not settled after
        :data:`MAX_PRE_SHOTS` pre-shots; any camera failure.
    """
    bounds = {cam.side: cam.exposure_bounds_us() for cam in cameras}
    exposure = {cam.side: float(np.clip(FIRST_PRE_SHOT_US, *bounds[cam.side])) for cam in cameras}
    too_dark = {cam.side: 0.0 for cam in cameras}  # the longest exposure seen too dark
    too_bright = {cam.side: np.inf for cam in cameras}  # the shortest seen too bright
    metering, shots = list(cameras), 0
    for _ in range(MAX_PRE_SHOTS):
        for cam in metering:
            exposure[cam.side] = cam.set_exposure(exposure[cam.side], step=step)
            cam.trigger(step=step)
        shots += len(metering)
        still = []
        for cam in metering:
            side, (lo, hi) = cam.side, bounds[cam.side]
            now = exposure[side]
            p = brightest_fraction(
                cam.fetch(step=step, timeout_s=timeout_s + now * 1e-6).image, bit_depth
            )
            if EXPOSURE_FLOOR <= p <= EXPOSURE_LIMIT or (p < EXPOSURE_FLOOR and now >= hi):
                continue
            if p > EXPOSURE_LIMIT and now <= lo:
                raise AcquisitionError(
                    cam.device,
                    step,
                    f"the brightest samples are at {100 * p:.0f} % of full scale even at the shortest exposure "
                    f"({lo:g} us): lower the gain or the lights",
                )
            if p < EXPOSURE_FLOOR:
                too_dark[side] = max(too_dark[side], now)
            else:
                too_bright[side] = min(too_bright[side], now)
            proposal = (
                now / SATURATED_CUT if p >= SATURATED else now * EXPOSURE_TARGET / max(p, 1e-3)
            )
            if (
                not too_dark[side] < proposal < too_bright[side]
            ):  # a camera that is not linear: bisect
                proposal = float(np.sqrt(max(too_dark[side], lo) * min(too_bright[side], hi)))
            exposure[side] = float(np.clip(proposal, lo, hi))
            still.append(cam)
        metering = still
        if not metering:
            return exposure, shots
    raise AcquisitionError(
        metering[0].device, step, f"auto-exposure did not settle within {MAX_PRE_SHOTS} pre-shots"
    )


def acquire(
    config_path: str | os.PathLike[str],
    plate_id: str,
    out_dir: str | os.PathLike[str],
    *,
    progress: Progress | None = None,
    frame_timeout_s: float = FRAME_TIMEOUT_S,
    frames: dict[str, np.ndarray] | None = None,
) -> Path:
    """Photograph a plate in the cell and write a ``plate-capture/1`` bundle (module docstring).

    Parameters
    ----------
    config_path : str or Path
        The ``cell-config/1`` file.
    plate_id : str
        Written into the bundle; a simulated cell renders a plate seeded by it.
    out_dir : str or Path
        The bundle folder to write; it must not exist (its parent is created).
    progress : callable, optional
        ``progress(stage, fraction)`` after each step (fraction of the capture frames taken).
    frame_timeout_s : float
        Seconds a frame may take beyond its exposure before the camera counts as gone.
    frames : dict, optional
        Receives every capture frame's image as the camera gave it, by its file name in the bundle
        (``"ps_00.png"``, ...), so that an inspection that follows at once takes them from memory
        (:func:`pipeline.io.load_capture`'s ``frames``) instead of decoding the files again. A
        :class:`pipeline.acquisition.streaming.StreamedFrames` folds each one for it as it arrives.

    Returns
    -------
    Path
        ``out_dir``, holding ``capture.json`` (with ``acquisition``: the cameras' vendor, model,
        serial, pixel format, exposure and gain, the light controller, every frame's time and
        lighting, total time), ``calibration.json``, ``ps_00.png`` ..., ``dark.png``,
        ``stereo_left.png``, ``stereo_right.png``.

    Raises
    ------
    InputError
        A bad configuration (file and field named), an existing ``out_dir``, a camera whose sensor is
        smaller than the calibration's ``image_size``, an ``exposure_us`` or ``gain_db`` out of the
        camera's range.
    AcquisitionError
        A device that is missing, refuses, times out, gives incomplete frames, or disappears; the
        device and the step are named. Nothing is left in ``out_dir``.
    """
    if not plate_id:
        raise ValueError("plate_id: expected a non-empty plate id")
    config = load_cell_config(config_path)
    if config.conveyor is not None:
        raise InputError(
            config.label,
            "conveyor",
            "this cell carries the plate station by station: acquire_stations writes one bundle per "
            "station",
        )
    out = Path(out_dir)
    if out.exists():
        raise InputError(str(out), "", "already exists; acquire writes a new bundle folder")
    partial = out.with_name(out.name + ".partial")
    if partial.exists():
        shutil.rmtree(partial)  # left by an acquisition that was killed
    partial.mkdir(parents=True)
    started_at = datetime.now(UTC)
    try:
        with ExitStack() as stack:
            writer = stack.enter_context(ThreadPoolExecutor(max_workers=PNG_WRITERS))
            run = open_devices(
                stack,
                config,
                plate_id,
                partial,
                writer,
                frame_timeout_s,
                progress or (lambda stage, f: None),
            )
            run.images = frames
            if isinstance(frames, StreamedFrames):
                frames.begin(run.bit_depth)  # each frame folded as it is kept
                stack.callback(frames.close)
            take_bundle(run, plate_id, started_at)
        os.rename(partial, out)
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    return out


def last_frame_lag_s(bundle: str | os.PathLike[str]) -> float | None:
    """Seconds from a bundle's last frame to the end of its acquisition (its ``acquisition`` record:
    ``total_s`` less the last frame's ``t_s``); None for a bundle without that record.

    With the moment ``acquire`` returned, this gives when the last frame arrived: what
    ``timings_s.after_last_frame`` of an acquired inspection counts from.
    """
    try:
        record = json.loads((Path(bundle) / "capture.json").read_text())["acquisition"]
        return float(record["total_s"]) - float(record["frames"][-1]["t_s"])
    except (OSError, KeyError, IndexError, TypeError, ValueError):
        return None


def last_frame_time(bundle: str | os.PathLike[str], returned_at: float) -> float | None:
    """The :func:`time.monotonic` when the last frame of ``bundle`` arrived, from ``returned_at``, the
    moment its acquisition returned (less :func:`last_frame_lag_s`); None without an acquisition
    record."""
    lag = last_frame_lag_s(bundle)
    return None if lag is None else returned_at - lag


def add_after_last_frame(document: dict[str, Any], out_dir: Path, last_frame_at: float) -> None:
    """``timings_s.after_last_frame`` of an acquired inspection's result ``document``: seconds from
    the last frame's arrival (``last_frame_at``, :func:`time.monotonic`, see :func:`last_frame_time`)
    to now; written into ``out_dir/result.json`` too."""
    timings = document.get("timings_s")
    if not isinstance(timings, dict):
        return
    timings["after_last_frame"] = round(time.monotonic() - last_frame_at, 3)
    result_file = out_dir / "result.json"
    if result_file.is_file():
        result_file.write_text(json.dumps(document, indent=2) + "\n")


def take_bundle(
    run: Run,
    plate_id: str,
    started_at: datetime,
    *,
    station: dict[str, Any] | None = None,
    conveyor: dict[str, Any] | None = None,
) -> None:
    """Take every frame of a bundle into ``run.folder`` and write its ``capture.json`` once every
    image is written; ``station`` is the bundle's ``station`` field, ``conveyor`` goes into its
    acquisition record."""
    record = _sequence(run)
    for done in run.writes:
        done.result()
    if conveyor is not None:
        record["conveyor"] = conveyor
    record["total_s"] = round(time.monotonic() - run.t0, 3)
    record["time_per_image_s"] = round(record["total_s"] / len(run.frames), 4)
    _write_manifest(run, plate_id, started_at, record, station)


def open_devices(
    stack: ExitStack,
    config: CellConfig,
    plate_id: str,
    folder: Path,
    writer: ThreadPoolExecutor,
    timeout_s: float,
    progress: Progress,
    conveyor: Conveyor | None = None,
) -> Run:
    """Connect the light controller and open, check and configure both cameras (closed by ``stack``)."""
    progress("connecting", 0.0)
    controller = open_light_controller(config.light_controller, config.lights.n)
    stack.callback(controller.close)
    cell = None
    if "simulated" in (config.left.driver, config.right.driver):
        cell = SimulatedCell(
            config.rig, config.lights, config.working_distance_mm, controller, plate_id, conveyor
        )
    cameras: dict[Side, Camera] = {}
    sides: tuple[tuple[Side, CellCamera], ...] = (("left", config.left), ("right", config.right))
    for side, cam_config in sides:
        cameras[side] = open_camera(side, cam_config, cell=cell)
        stack.callback(cameras[side].close)
    left, right = cameras["left"], cameras["right"]

    width, height = config.rig.image_size
    for cam in (left, right):
        sw, sh = cam.sensor_size()
        if sw < width or sh < height:
            raise InputError(
                str(config.calibration_path),
                "image_size",
                f"{width}x{height} px is larger than the {cam.device}'s sensor ({sw}x{sh} px): "
                "a calibration of another camera?",
            )
    pixel_format = choose_pixel_format(left, right)
    for cam, cam_config in ((left, config.left), (right, config.right)):
        cam.configure(pixel_format=pixel_format, width=width, height=height)
        _check_settings(cam, cam_config, config)
        cam.start()
    n_frames = config.lights.n + 3
    return Run(
        config,
        controller,
        left,
        right,
        folder,
        writer,
        timeout_s,
        progress,
        n_frames,
        PIXEL_FORMATS[pixel_format],
    )


def _check_settings(cam: Camera, cam_config: CellCamera, config: CellConfig) -> None:
    """Set the gain; check the configured exposure against the camera's range."""
    field = f"cameras.{cam.side}"
    gain_bounds = cam.gain_bounds_db()
    if cam_config.gain_db is not None:
        if gain_bounds is None:
            raise InputError(
                config.label, f"{field}.gain_db", f"the {cam.device} has no gain control"
            )
        if not gain_bounds[0] <= cam_config.gain_db <= gain_bounds[1]:
            raise InputError(
                config.label,
                f"{field}.gain_db",
                f"expected within the {cam.device}'s range {gain_bounds[0]:g}-{gain_bounds[1]:g} dB, got {cam_config.gain_db:g}",
            )
        cam.set_gain(cam_config.gain_db)
    elif gain_bounds is not None:
        cam.set_gain(gain_bounds[0])
    if cam_config.exposure_us is not None:
        lo, hi = cam.exposure_bounds_us()
        if not lo <= cam_config.exposure_us <= hi:
            raise InputError(
                config.label,
                f"{field}.exposure_us",
                f"expected within the {cam.device}'s range {lo:g}-{hi:g} us, got {cam_config.exposure_us:g}",
            )


def _all_lights(run: Run, on: bool, *, step: str) -> None:
    for k in range(run.config.lights.n):
        (run.controller.on if on else run.controller.off)(k, step=step)


def _stereo_lighting(run: Run, on: bool, *, step: str) -> None:
    if run.controller.has_stereo_light:
        (run.controller.stereo_on if on else run.controller.stereo_off)(step=step)
    else:
        _all_lights(run, on, step=step)


def _exposures(run: Run) -> tuple[float, dict[Side, float], dict[Side, str]]:
    """The left camera's photometric exposure, both cameras' stereo exposures (by side), and where
    each camera's came from: the configuration, or auto-exposure pre-shots."""
    config, left, right = run.config, run.left, run.right
    stereo_light = run.controller.has_stereo_light
    configured = {
        cam.side: cc.exposure_us for cam, cc in ((left, config.left), (right, config.right))
    }
    source = {
        side: "configuration" if us is not None else "auto-exposure"
        for side, us in configured.items()
    }
    photometric = configured["left"]
    # all the lights together are as bright as one light at N times the exposure
    stereo = {
        side: us if stereo_light else us / config.lights.n
        for side, us in configured.items()
        if us is not None
    }
    auto = [cam for cam in (left, right) if configured[cam.side] is None]
    if not auto and photometric is not None:  # (photometric is None only when the left one meters)
        return photometric, stereo, source
    run.progress("auto-exposure", 0.0)
    bit_depth, timeout_s = run.bit_depth, run.timeout_s
    if (
        not stereo_light
    ):  # one metering under all lights: the left camera's serves its photometric frames too
        step = "auto-exposure pre-shot, all photometric lights on"
        _all_lights(run, True, step=step)
        metered, shots = auto_exposure(auto, step=step, bit_depth=bit_depth, timeout_s=timeout_s)
        _all_lights(run, False, step=step)
        run.pre_shots += shots
        stereo.update(metered)
        if photometric is None:  # the left camera metered
            photometric = _single_light_exposure(run, metered["left"])
        return photometric, stereo, source
    if photometric is None:
        step = "auto-exposure pre-shot, all photometric lights on"
        _all_lights(run, True, step=step)
        metered, shots = auto_exposure([left], step=step, bit_depth=bit_depth, timeout_s=timeout_s)
        _all_lights(run, False, step=step)
        run.pre_shots += shots
        photometric = _single_light_exposure(run, metered["left"])
    step = "auto-exposure pre-shot, stereo light on"
    _stereo_lighting(run, True, step=step)
    metered, shots = auto_exposure(auto, step=step, bit_depth=bit_depth, timeout_s=timeout_s)
    _stereo_lighting(run, False, step=step)
    run.pre_shots += shots
    stereo.update(metered)
    return photometric, stereo, source


def _single_light_exposure(run: Run, all_on_us: float) -> float:
    """The photometric exposure (us) for frames lit by one light each, from the one metered with all on.

    Each photometric frame is lit by a single light, several times dimmer than all of them together:
    at the all-on exposure its signal would use a fraction of the sensor's range and its noise would
    weigh that many times more in the normals. One pre-shot per light at the all-on exposure finds
    the brightest single-light frame; the exposure is scaled so that it reaches
    :data:`EXPOSURE_TARGET` (never below the all-on exposure, within the camera's range; the camera
    is taken to be linear, as by :func:`auto_exposure`).
    """
    left, controller = run.left, run.controller
    step = "auto-exposure pre-shot, one photometric light at a time"
    run.expose(left, all_on_us, step=step)
    brightest = 0.0
    for k in range(run.config.lights.n):
        controller.on(k, step=step)
        frame = left.grab(step=step, timeout_s=run.timeout(left))
        controller.off(k, step=step)
        brightest = max(brightest, brightest_fraction(frame.image, run.bit_depth))
        run.pre_shots += 1
    if not brightest > 0:
        return all_on_us
    lo, hi = left.exposure_bounds_us()
    return float(np.clip(all_on_us * EXPOSURE_TARGET / brightest, max(all_on_us, lo), hi))


def _sequence(run: Run) -> dict[str, Any]:
    """Take every frame of the bundle; returns the acquisition record (without total times)."""
    config, controller, left, right = run.config, run.controller, run.left, run.right
    photometric_us, stereo_us, source = _exposures(run)

    t_first = time.monotonic()
    # the stereo pair first: an inspection that follows folds each later frame as it arrives
    # (pipeline.acquisition.streaming), and the last frame is a photometric image
    step = "stereo pair (stereo_left.png, stereo_right.png)"
    for cam in (left, right):
        run.expose(cam, stereo_us[cam.side], step=step)
    stereo_us = dict(run.exposure_us)
    lighting = "stereo light" if controller.has_stereo_light else list(range(config.lights.n))
    _stereo_lighting(run, True, step=step)
    together = left.can_trigger and right.can_trigger
    pair = []
    if together:
        left.trigger(step=step)
        right.trigger(step=step)
        for cam in (left, right):
            pair.append((cam.fetch(step=step, timeout_s=run.timeout(cam)), run.elapsed()))
    else:
        for cam in (left, right):
            pair.append((cam.grab(step=step, timeout_s=run.timeout(cam)), run.elapsed()))
    _stereo_lighting(run, False, step=step)
    (left_frame, t_left), (right_frame, t_right) = pair
    run.keep("stereo_left.png", left, left_frame, lighting, t_left)
    run.keep("stereo_right.png", right, right_frame, lighting, t_right)

    run.expose(left, photometric_us, step="setting the photometric exposure")
    photometric_us = run.exposure_us["left"]  # as the camera took it
    step = "dark frame (dark.png)"
    frame = left.grab(step=step, timeout_s=run.timeout(left))
    run.keep("dark.png", left, frame, [], run.elapsed())

    for k in range(config.lights.n):
        name = f"ps_{k:02d}.png"
        step = f"photometric image {k} ({name})"
        controller.on(k, step=step)
        frame = left.grab(step=step, timeout_s=run.timeout(left))
        t_s = run.elapsed()
        controller.off(k, step=step)
        run.keep(name, left, frame, [k], t_s)
    sequence_s = time.monotonic() - t_first

    cameras: dict[str, dict[str, Any]] = {}
    for cam in (left, right):
        cameras[cam.side] = cam.describe() | {
            "exposure_source": source[cam.side],
            "exposure_us": {"photometric": photometric_us, "stereo": stereo_us["left"]}
            if cam is left
            else {"stereo": stereo_us["right"]},
        }
    return {
        "program": "plate-inspect acquire",
        "cell_id": config.cell_id,
        "config": config.path.name,
        "cameras": cameras,
        "light_controller": controller.describe(),
        "stereo_lighting": "stereo light"
        if controller.has_stereo_light
        else "all photometric lights",
        "stereo_trigger": "together" if together else "back to back",
        "pre_shots": run.pre_shots,
        "sequence_s": round(sequence_s, 3),
        "frames": run.frames,
    }


def _write_manifest(
    run: Run,
    plate_id: str,
    started_at: datetime,
    record: dict[str, Any],
    station: dict[str, Any] | None,
) -> None:
    """``calibration.json`` (the configuration's, as it is) and ``capture.json``."""
    config = run.config
    shutil.copyfile(config.calibration_path, run.folder / "calibration.json")
    doc = {
        "format": CAPTURE_FORMAT,
        "plate_id": plate_id,
        "captured_at": started_at.strftime("%Y-%m-%dT%H:%M:%SZ"),
        "calibration": "calibration.json",
        "bit_depth": run.bit_depth,
        "photometric": {
            "lights": config.lights.documents(),
            "images": [f"ps_{k:02d}.png" for k in range(config.lights.n)],
            "dark": "dark.png",
        },
        "stereo": {"left": "stereo_left.png", "right": "stereo_right.png"},
        "working_distance_mm": config.working_distance_mm,
        "acquisition": record,
    }
    if station is not None:
        doc["station"] = station
    CaptureFile.model_validate(doc)
    (run.folder / "capture.json").write_text(json.dumps(doc, indent=2) + "\n")
