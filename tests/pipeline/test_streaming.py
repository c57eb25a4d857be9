"""Frames folded as they are taken (pipeline.acquisition.streaming): the very arrays loading, binning and
undistorting give, taken only for the capture they were folded for; an acquired inspection reads as
one of its written bundle."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from pipeline.acquisition import StreamedFrames, acquire, write_demo_cell
from pipeline.io import Capture, load_capture
from pipeline.preprocess import WORKING_CELL_MM, bin_capture, undistorted
from pipeline.run import inspect
from pipeline.simulate import CaptureSpec, PlateSpec, simulate_capture

#: The depth assumed without a working distance (the bundles here have one).
DISTANCE_MM = 3500.0
#: The order an acquisition takes them in (pipeline.acquisition.acquire).
ORDER = ("stereo_left.png", "stereo_right.png", "dark.png")


@pytest.fixture(scope="module")
def bundle(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("streaming") / "bundle"
    simulate_capture(
        out,
        plate=PlateSpec(shape="cylinder", radius_mm=5000.0, convex=True),
        capture=CaptureSpec(n_lights=6, width=612, height=512),
        seed=3,
    )
    return out


def _cell_mm(bundle: Path, factor: int) -> float:
    """The working cell that bins the bundle's images by ``factor``."""
    cap = load_capture(bundle)
    fx = max(cap.rig.left.K[0, 0], cap.rig.left.K[1, 1])
    assert cap.working_distance_mm is not None
    return (factor + 0.5) * cap.working_distance_mm / fx


def _streamed(
    bundle: Path, factor: int, *, skip: tuple[str, ...] = (), order: tuple[str, ...] = ORDER
) -> StreamedFrames:
    """The bundle's frames (but ``skip``) stored in acquisition order (``order`` first, then the
    photometric images) into frames folded for ``factor``."""
    cap = load_capture(bundle)
    assert cap.working_distance_mm is not None
    frames = StreamedFrames(
        cap.rig, cap.lights, cap.working_distance_mm, cell_mm=_cell_mm(bundle, factor)
    )
    assert frames.factor == factor
    frames.begin(cap.bit_depth)
    names = [*order, *(f"ps_{k:02d}.png" for k in range(cap.n_lights))]
    for name in (n for n in names if n not in skip):
        frames[name] = cv2.imread(str(bundle / name), cv2.IMREAD_UNCHANGED)
    return frames


def _taken(frames: StreamedFrames, bundle: Path, factor: int) -> Capture | None:
    return frames.capture(bundle, cell_mm=_cell_mm(bundle, factor), distance_mm=DISTANCE_MM)


@pytest.mark.parametrize("factor", [1, 2])
def test_folded_frames_are_the_arrays_of_loading_binning_and_undistorting(bundle, factor):
    frames = _streamed(bundle, factor)
    folded = _taken(frames, bundle, factor)
    expected = bin_capture(load_capture(bundle), factor)
    assert folded is not None
    for name in ("images", "dark", "stereo_left", "stereo_right"):
        np.testing.assert_array_equal(getattr(folded, name), getattr(expected, name), err_msg=name)
    for name in (
        "plate_id",
        "captured_at",
        "bit_depth",
        "working_distance_mm",
        "station",
        "source",
    ):
        assert getattr(folded, name) == getattr(expected, name), name
    np.testing.assert_array_equal(folded.light_intensity, expected.light_intensity)
    np.testing.assert_array_equal(folded.rig.left.K, expected.rig.left.K)
    np.testing.assert_array_equal(folded.rig.right.K, expected.rig.right.K)
    assert folded.rig.image_size == expected.rig.image_size
    assert folded.rig.rms_px == expected.rig.rms_px
    if factor == 1:
        assert folded.raw_noise is None and expected.raw_noise is None
    else:
        assert folded.raw_noise is not None and expected.raw_noise is not None
        np.testing.assert_array_equal(folded.raw_noise[0], expected.raw_noise[0])
        assert folded.raw_noise[1] == expected.raw_noise[1]

    lit = frames.undistorted(folded)
    assert lit is not None
    ref = undistorted(expected)
    got = undistorted(folded, folded=lit)
    for name in ("images", "saturated", "brightest", "brightness", "glare_free", "seen"):
        np.testing.assert_array_equal(getattr(got, name), getattr(ref, name), err_msg=name)
    assert got.any_saturated == ref.any_saturated


def test_frames_folded_for_another_capture_are_not_taken(bundle):
    frames = _streamed(bundle, 2)
    assert _taken(frames, bundle, 1) is None  # another working grid
    folded = _taken(frames, bundle, 2)
    assert folded is not None
    # lights of other intensities (a light calibration applied, say): the images are normalised anew
    brighter = replace(folded.lights, intensity=folded.lights.intensity * 1.1)
    assert frames.undistorted(replace(folded, lights=brighter)) is None
    assert frames.undistorted(replace(folded, bit_depth=folded.bit_depth - 1)) is None
    assert frames.undistorted(bin_capture(load_capture(bundle), 2)) is None  # not the folded images

    # a photometric image never stored or before the dark frame, one that could not be folded (a
    # colour frame), one of fewer bits than the capture's (loading names the file and the field)
    assert _taken(_streamed(bundle, 2, skip=("ps_03.png",)), bundle, 2) is None
    late_dark = _streamed(bundle, 2, skip=("dark.png",), order=ORDER[:2])
    late_dark["dark.png"] = cv2.imread(str(bundle / "dark.png"), cv2.IMREAD_UNCHANGED)
    assert _taken(late_dark, bundle, 2) is None  # photometric images before the dark frame
    colour = _streamed(bundle, 2)
    colour["ps_01.png"] = np.zeros((*folded.images.shape[1:], 3), np.uint16)
    assert _taken(colour, bundle, 2) is None
    cap = load_capture(bundle)
    assert cap.bit_depth > 8
    eight = _streamed(bundle, 2)  # an 8-bit frame of a capture of more bits
    eight["ps_02.png"] = np.zeros(cap.images.shape[1:], np.uint8)
    assert _taken(eight, bundle, 2) is None


def test_an_acquired_inspection_folds_its_frames_and_reads_as_its_bundle(tmp_path):
    cell = write_demo_cell(tmp_path / "cell", n_lights=6, width=612, height=512)
    frames = StreamedFrames.for_cell(cell)
    bundle = acquire(cell, plate_id="P-STREAM", out_dir=tmp_path / "bundle", frames=frames)
    target = cell.parent / "target.json"
    streamed = inspect(bundle, target, out_dir=tmp_path / "streamed", frames=frames).document
    from_files = inspect(bundle, target, out_dir=tmp_path / "files").document
    assert frames.capture(bundle, cell_mm=WORKING_CELL_MM, distance_mm=DISTANCE_MM) is not None
    for name in ("depth.npy", "uncertainty.npy"):
        assert (tmp_path / "streamed" / name).read_bytes() == (
            tmp_path / "files" / name
        ).read_bytes()
    assert streamed["verdict"] == from_files["verdict"] == "pass"
    assert streamed["radius_mm"] == from_files["radius_mm"]
    assert streamed["deviation_mm"] == from_files["deviation_mm"]
