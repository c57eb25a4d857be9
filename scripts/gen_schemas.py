"""Writes the JSON Schemas of the file formats to docs/schemas/, generated from the pydantic models
that read them (pipeline/formats.py) and from the dataclasses of details.json (pipeline/judge/details.py).

    .venv/bin/python scripts/gen_schemas.py           # (re)write docs/schemas/*.schema.json
    .venv/bin/python scripts/gen_schemas.py --check   # exit 1 naming the stale files

The models are the truth: a schema is what pydantic says of them (draft 2020-12), so a change to a
model and its schema travel together (tests/test_schemas.py runs --check).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from pydantic import TypeAdapter

from pipeline import formats
from pipeline.judge.details import Details

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "docs" / "schemas"

#: File name stem -> (the type that reads it, a one-line title).
SCHEMAS: dict[str, tuple[Any, str]] = {
    "stereo-calibration": (
        formats.StereoCalibrationFile,
        "calibration.json (stereo-calibration/1)",
    ),
    "plate-capture": (formats.CaptureFile, "capture.json (plate-capture/1)"),
    "light-calibration": (formats.LightCalibrationFile, "lights.json (light-calibration/1)"),
    "cell-config": (formats.CellConfigFile, "cell.json (cell-config/1)"),
    "plate-target": (formats.TargetFile, "target.json (plate-target/1)"),
    "plate-result": (formats.ResultFile, "result.json (plate-result/1)"),
    "details": (Details, "details.json (the numbers behind a result)"),
}


def render(kind: Any, title: str) -> str:
    """The schema of ``kind`` as indented JSON text with a trailing newline."""
    schema = TypeAdapter(kind).json_schema(mode="validation")
    schema = {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": title, **schema}
    return json.dumps(schema, indent=2, sort_keys=False) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="only say which files are stale")
    args = parser.parse_args(argv)
    OUT.mkdir(parents=True, exist_ok=True)
    stale = []
    for stem, (kind, title) in SCHEMAS.items():
        path = OUT / f"{stem}.schema.json"
        text = render(kind, title)
        if path.exists() and path.read_text() == text:
            continue
        stale.append(path.relative_to(ROOT))
        if not args.check:
            path.write_text(text)
    if args.check and stale:
        print("stale (run scripts/gen_schemas.py):", *map(str, stale), sep="\n  ")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
