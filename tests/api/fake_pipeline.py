"""A test double of ``pipeline.run.inspect`` for the job machinery's tests (timing under control).

It validates its inputs with the real loaders, reports progress through stages, sleeps
``PLATE_INSPECT_TEST_STAGE_DELAY_S`` seconds per stage (so a test can kill the consumer
mid-job), and writes a ``plate-result/1`` document whose numbers come from the target (it does
not measure anything: the tests using it check the service, not the measurement). A plate id
containing ``UNMEASURABLE`` raises :class:`CaptureError`; ``CRASH`` raises a RuntimeError;
``PATHERROR`` raises the ``FileExistsError`` of a leftover ``bundle.partial`` folder beside the
capture, with its server path (as an unguarded render did);
``KILLSELF`` kills its own process with SIGKILL in the ``normals`` stage (a job that kills its
worker); ``HOG`` asks numpy for ``PLATE_INSPECT_TEST_ALLOCATE_MB`` MiB (default 2048; the pages are
not touched, so without a memory limit it succeeds and the job completes).
With ``PLATE_INSPECT_TEST_INVOCATIONS`` set to a file, each call appends ``start <inspection id>
<pid>`` to it when it begins and ``end <inspection id> <pid>`` when it returns a result, so a test
can count how often each job ran and completed.
A ``light_calibration`` is handled as the real one does for the result's ``warnings`` (applied to
nominal lights of the same count, else a warning why not); its count of lights goes in
``details.json`` so a test can tell which calibration the job passed.
"""

from __future__ import annotations

import errno
import json
import os
import signal
import time
from dataclasses import dataclass
from pathlib import Path

from pipeline.formats import RESULT_FORMAT, CaptureError, ResultFile
from pipeline.io import Capture, load_capture, load_target

STAGES = ("load", "normals", "depth", "curvature", "deviation", "artifacts")


@dataclass(frozen=True)
class FakeResult:
    document: dict
    out_dir: Path


def inspect(
    capture, target, *, out_dir: Path, progress=None, light_calibration=None, frames=None
) -> FakeResult:
    delay = float(os.environ.get("PLATE_INSPECT_TEST_STAGE_DELAY_S", "0"))
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    inspection_id = out_dir.parent.name  # <data dir>/inspections/<id>/artifacts
    _record("start", inspection_id)
    cap = (  # as the real one
        capture if isinstance(capture, Capture) else load_capture(capture, frames=frames)
    )
    tgt = load_target(target)
    if "UNMEASURABLE" in cap.plate_id:
        raise CaptureError(f"{cap.plate_id}: no plate found in the photometric images")
    if "CRASH" in cap.plate_id:
        raise RuntimeError("simulated bug")
    if "PATHERROR" in cap.plate_id:
        leftover = Path(cap.source).resolve().parent / "bundle.partial"
        raise FileExistsError(errno.EEXIST, os.strerror(errno.EEXIST), str(leftover))
    if "HOG" in cap.plate_id:
        import numpy as np

        hog = np.empty(
            int(os.environ.get("PLATE_INSPECT_TEST_ALLOCATE_MB", "2048")) << 20, dtype=np.uint8
        )
        del hog
    for i, stage in enumerate(STAGES):
        if progress is not None:
            progress(stage, i / len(STAGES))
        if stage == "normals" and "KILLSELF" in cap.plate_id:
            os.kill(os.getpid(), signal.SIGKILL)
        time.sleep(delay)
    (out_dir / "deviation.png").write_bytes(b"\x89PNG fake")
    warnings = _light_warnings(cap.lights, light_calibration)
    document = ResultFile(
        format=RESULT_FORMAT,
        plate_id=cap.plate_id,
        radius_mm=tgt.radius_mm,
        principal_radii_mm=[tgt.radius_mm, None],
        target_radius_mm=tgt.radius_mm,
        radius_error_pct=0.0 if tgt.radius_mm else None,
        deviation_mm={"rms": 0.1, "max_abs": 0.3, "p95": 0.2},
        tolerance_mm=tgt.tolerance_mm,
        within_tolerance_pct=100.0,
        verdict="pass",
        timings_s={"total": delay * len(STAGES)},
        artifacts={"deviation_map": "deviation.png"},
        warnings=warnings or None,
    ).model_dump(mode="json")
    if document["warnings"] is None:
        del document["warnings"]
    details = {
        "light_calibration_n_lights": None if light_calibration is None else light_calibration.n
    }
    (out_dir / "details.json").write_text(json.dumps(details), encoding="utf-8")
    (out_dir / "result.json").write_text(json.dumps(document), encoding="utf-8")
    if progress is not None:
        progress(STAGES[-1], 1.0)
    _record("end", inspection_id)
    return FakeResult(document=document, out_dir=out_dir)


def _record(event: str, inspection_id: str) -> None:
    path = os.environ.get("PLATE_INSPECT_TEST_INVOCATIONS")
    if path:
        with open(path, "a", encoding="ascii") as fh:
            fh.write(f"{event} {inspection_id} {os.getpid()}\n")


def _light_warnings(lights, calibration) -> list[str]:
    if calibration is None or lights.any_point:
        return []
    if calibration.n != lights.n:
        return [
            f"the light calibration was not applied: it has {calibration.n} lights, the capture {lights.n} images"
        ]
    return ["a light calibration was applied to the capture's nominal light directions"]
