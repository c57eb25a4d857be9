"""Frames folded as an acquisition takes them, so that the inspection that follows starts further on.

An inspection that follows an acquisition at once (``plate-inspect acquire --target``, the service's
acquire job) used to start from nothing when the last frame arrived. :class:`StreamedFrames` is the
``frames`` mapping :func:`pipeline.acquisition.acquire` fills: each frame, as it is kept, is handed
to one thread beside the acquisition, which converts it to float32, bins it onto the working grid
(:func:`pipeline.preprocess.bin_capture`), measures its sensor noise and, a photometric image,
subtracts the dark frame, normalises and undistorts it (:func:`pipeline.preprocess.undistort_into`).
The acquisition takes the stereo pair and the dark frame before the photometric images, so only the
last image's share is left when it arrives, and it is done while the bundle's last file is written.

The inspection (:func:`pipeline.run.inspect` with ``frames``) takes the folded arrays only for the
capture they were folded for: the bundle's frames, bit depth, lights' intensities, calibration and
working grid must be those the frames were folded with (a light calibration that changes the
intensities, say, is not); it then reads only the bundle's JSON and image headers
(:func:`pipeline.io.read_capture_header`), and its full-size images are never made. Otherwise it
loads the bundle from the frames, as from files. Either way the arrays are the same to the bit
(``tests/pipeline/test_streaming.py``). A frame that cannot be folded (a colour frame, a wrong size,
fewer bits than the capture's, a photometric image before the dark frame) is left to that loading,
which names the file and the field.
"""

from __future__ import annotations

import os
import re
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np

from pipeline.camera import CameraModel, StereoRig
from pipeline.io import Capture, read_capture_header
from pipeline.lights.model import Lights
from pipeline.preprocess import (
    WORKING_CELL_MM,
    bin_into,
    binned_rig,
    binning_factor,
    saturation_level,
    undistort_gains,
    undistort_into,
)
from pipeline.surface.normals.noise import image_noise

from .config import CellConfig, load_cell_config

__all__ = ["StreamedFrames"]

_PHOTOMETRIC = re.compile(r"ps_(\d{2,})\.png")
_STEREO = {"stereo_left.png": 0, "stereo_right.png": 1}


class StreamedFrames(dict[str, np.ndarray]):
    """A bundle's frames by file name (``ps_00.png``, ``dark.png``, ``stereo_left.png``, ...), each
    folded on a thread as it is stored (module docstring) once :meth:`begin` has been called.

    Parameters
    ----------
    rig : StereoRig
        The cell's calibration (full size, as the frames are taken).
    lights : Lights
        The cell's photometric lights in image order (their intensities normalise the images).
    working_distance_mm : float
        The cell's working distance (sets the working grid, :func:`pipeline.preprocess.working_binning`).
    cell_mm : float or None
        The working grid's coarsest cell (:class:`pipeline.stages.InspectOptions` ``working_cell_mm``).
    """

    def __init__(
        self,
        rig: StereoRig,
        lights: Lights,
        working_distance_mm: float,
        *,
        cell_mm: float | None = WORKING_CELL_MM,
    ) -> None:
        super().__init__()
        self._rig = rig
        self._lights = lights
        self._factor = binning_factor(rig.left.K, working_distance_mm, cell_mm)
        grid = binned_rig(rig, self._factor) if self._factor > 1 else rig
        self._camera: CameraModel = grid.left
        self._maps = self._camera.undistort_maps()
        w, h = grid.left.image_size
        n = lights.n
        self._binned = np.empty((n, h, w), np.float32)
        self._images = np.empty((n, h, w), np.float32)
        self._saturated = np.zeros((n, h, w), bool)
        self._any_saturated = False
        self._noise = np.zeros(n)
        self._dark: np.ndarray | None = None
        self._dark_noise: float | None = None
        self._stereo: list[np.ndarray | None] = [None, None]
        self._folded: set[int] = set()
        self._failed = False
        self._bits = 16  # the fewest bits a frame came in
        self._peak = 0  # the brightest sample of any frame
        self._bit_depth: int | None = None
        self._pool: ThreadPoolExecutor | None = None
        self._jobs: list[Future[None]] = []
        self._gains = np.zeros(n)  # each image's, set by begin()
        self._saturation = np.inf
        self._everywhere = np.ones((rig.image_size[1], rig.image_size[0]), bool)

    @classmethod
    def for_cell(cls, config: CellConfig | str | os.PathLike[str]) -> StreamedFrames:
        """Frames of a cell (its ``cell-config/1`` file, or the configuration read)."""
        cell = config if isinstance(config, CellConfig) else load_cell_config(config)
        return cls(cell.rig, cell.lights, cell.working_distance_mm)

    @property
    def factor(self) -> int:
        """The working grid's binning the frames are folded for."""
        return self._factor

    def begin(self, bit_depth: int) -> None:
        """Fold every frame stored from now on (``bit_depth``: the cameras' significant bits, which
        set full scale and the saturation level)."""
        self._bit_depth = int(bit_depth)
        self._gains = undistort_gains(self._lights.intensity, self._bit_depth)
        self._saturation = saturation_level(self._bit_depth)
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="fold")

    def __setitem__(self, name: str, image: np.ndarray) -> None:
        super().__setitem__(name, image)
        if self._pool is not None:
            self._jobs.append(self._pool.submit(self._fold, name, image))

    def close(self) -> None:
        """Wait for the frames stored so far to be folded and stop the folding thread."""
        for job in self._jobs:
            job.exception()
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    # ------------------------------------------------------------------ folding (its own thread)

    def _fold(self, name: str, image: np.ndarray) -> None:
        try:
            self._fold_one(name, image)
        except Exception:  # the inspection loads this frame itself and says what is wrong
            self._failed = True

    def _fold_one(self, name: str, image: np.ndarray) -> None:
        photometric = _PHOTOMETRIC.fullmatch(name)
        if photometric is None and name != "dark.png" and name not in _STEREO:
            return
        if image.ndim != 2 or image.dtype not in (np.uint8, np.uint16):
            self._failed = True  # colour or odd frames: the inspection converts them itself
            return
        if (image.shape[1], image.shape[0]) != self._rig.image_size:
            self._failed = True
            return
        # what loading checks of each frame's pixels (pipeline.io): its bits against the capture's
        self._bits = min(self._bits, 8 * image.dtype.itemsize)
        self._peak = max(self._peak, int(image.max()))
        raw = image.astype(np.float32)
        if photometric is not None:
            k = int(photometric.group(1))
            if k >= self._lights.n:
                self._failed = True
                return
            if self._dark is None:  # the acquisition takes the dark frame first
                self._failed = True
                return
            self._noise[k] = self._noise_of(raw)
            self._bin(raw, self._binned[k])
            self._undistort(k)
            self._folded.add(k)
        elif name == "dark.png":
            self._dark_noise = self._noise_of(raw)
            self._dark = self._bin(raw)
        else:
            self._stereo[_STEREO[name]] = self._bin(raw)

    def _bin(self, raw: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """``raw`` on the working grid (into ``out`` when given)."""
        if out is None:
            if self._factor == 1:
                return raw
            w, h = self._camera.image_size
            out = np.empty((h, w), np.float32)
        if self._factor == 1:
            np.copyto(out, raw)
        else:
            bin_into(raw, out, self._factor, self._depth())
        return out

    def _depth(self) -> int:
        if self._bit_depth is None:
            raise RuntimeError("StreamedFrames: begin(bit_depth) was not called")
        return self._bit_depth

    def _noise_of(self, raw: np.ndarray) -> float:
        """One image's sensor noise as :func:`pipeline.preprocess.raw_noise_counts` measures it."""
        return float(image_noise(raw[None], self._everywhere)[0])

    def _undistort(self, k: int) -> None:
        if undistort_into(
            self._binned[k],
            self._dark,
            float(self._gains[k]),
            self._maps,
            self._saturation,
            self._images[k],
            self._saturated[k],
        ):
            self._any_saturated = True

    # ------------------------------------------------------------------ taken by the inspection

    def capture(
        self, path: str | os.PathLike[str], *, cell_mm: float | None, distance_mm: float
    ) -> Capture | None:
        """The bundle ``path`` written from these frames, loaded onto the working grid of ``cell_mm``
        (``distance_mm``: the depth without a working distance) from the folded frames: the capture
        :func:`pipeline.io.load_capture` and :func:`pipeline.preprocess.bin_capture` give, its
        full-size images never made. None when the frames were not folded for it (another grid, bit
        depth, calibration or lights, a frame not folded, pixels loading would refuse): it is then
        loaded as any bundle, and what is wrong named there."""
        self.close()
        header = read_capture_header(path)
        names = [image.name for image in header.images]
        expected = [f"ps_{k:02d}.png" for k in range(self._lights.n)]
        expected += ["dark.png", "stereo_left.png", "stereo_right.png"]
        factor = binning_factor(
            header.rig.left.K, header.working_distance_mm or distance_mm, cell_mm
        )
        if not (
            not self._failed
            and names == expected
            and factor == self._factor
            and header.bit_depth == self._bit_depth
            and self._bits >= header.bit_depth
            and self._peak <= 2**header.bit_depth - 1
            and self._folded == set(range(self._lights.n))
            and self._dark is not None
            and all(side is not None for side in self._stereo)
            and np.array_equal(header.lights.intensity, self._lights.intensity)
            and _same_rig(header.rig, self._rig)
        ):
            return None
        left, right = self._stereo
        capture = Capture(
            plate_id=header.plate_id,
            captured_at=header.captured_at,
            rig=header.rig,
            bit_depth=header.bit_depth,
            lights=header.lights,
            images=self._binned,
            dark=self._dark,
            stereo_left=left,
            stereo_right=right,
            working_distance_mm=header.working_distance_mm,
            source=Path(path),
            station=header.station,
        )
        if factor == 1:  # bin_capture leaves a capture at full resolution as it is
            return capture
        noise = (
            self._noise / factor,
            None if self._dark_noise is None else self._dark_noise / factor,
        )
        return replace(capture, rig=binned_rig(header.rig, factor), raw_noise=noise)

    def undistorted(self, capture: Capture) -> tuple[np.ndarray, np.ndarray, bool] | None:
        """The photometric images of ``capture`` (on the working grid, lights as the inspection takes
        them) undistorted as :func:`pipeline.preprocess.undistorted` does (its ``folded``); None when
        they were folded for other lights, another bit depth or grid."""
        self.close()
        if (
            self._failed
            or capture.images is not self._binned  # the capture made from these frames
            or capture.bit_depth != self._bit_depth
            or not np.array_equal(capture.light_intensity, self._lights.intensity)
            or not _same_camera(capture.rig.left, self._camera)
        ):
            return None
        return self._images, self._saturated, self._any_saturated


def _same_rig(a: StereoRig, b: StereoRig) -> bool:
    return (
        _same_camera(a.left, b.left)
        and _same_camera(a.right, b.right)
        and np.array_equal(a.R, b.R)
        and np.array_equal(a.T, b.T)
    )


def _same_camera(a: CameraModel, b: CameraModel) -> bool:
    return (
        a.image_size == b.image_size and np.array_equal(a.K, b.K) and np.array_equal(a.dist, b.dist)
    )
