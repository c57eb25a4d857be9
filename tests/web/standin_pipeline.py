"""A stand-in for ``pipeline.run.inspect`` in browser tests while the real one is not importable.

It walks the stages with progress reports and writes analytic cylinder artifacts
(:func:`tests.web.plates.write_artifacts`); it measures nothing. The browser test
says which entry it ran with.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

from tests.web.plates import write_artifacts

STAGES = ("load", "normals", "depth", "curvature", "deviation", "artifacts")


@dataclass(frozen=True)
class StandInResult:
    document: dict
    out_dir: Path


def inspect(capture, target, *, out_dir: Path, progress=None) -> StandInResult:
    target_doc = json.loads(Path(target).read_text())
    capture_doc = json.loads((Path(capture) / "capture.json").read_text())
    for k, stage in enumerate(STAGES):
        if progress is not None:
            progress(stage, k / len(STAGES))
        time.sleep(0.4)
    folder = write_artifacts(
        Path(out_dir),
        plate_id=capture_doc["plate_id"],
        radius_mm=float(target_doc["shape"].get("radius_mm", 5000.0)),
        measured_radius_mm=1.01 * float(target_doc["shape"].get("radius_mm", 5000.0)),
        tolerance_mm=float(target_doc["tolerance_mm"]),
    )
    document = json.loads((folder / "result.json").read_text())
    if progress is not None:
        progress("done", 1.0)
    return StandInResult(document=document, out_dir=folder)
