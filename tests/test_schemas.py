"""The JSON Schemas in docs/schemas/ are those the models generate, and real files meet them."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import jsonschema_rs
import pytest

ROOT = Path(__file__).resolve().parents[1]
SCHEMAS = ROOT / "docs" / "schemas"


def _validator(stem: str) -> jsonschema_rs.Validator:
    return jsonschema_rs.validator_for(json.loads((SCHEMAS / f"{stem}.schema.json").read_text()))


def test_committed_schemas_are_up_to_date():
    out = subprocess.run(
        [sys.executable, "scripts/gen_schemas.py", "--check"],
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    assert out.returncode == 0, out.stdout + out.stderr


@pytest.fixture(scope="module")
def inspected(tmp_path_factory) -> Path:
    """A small simulated bundle, inspected by the CLI (result.json and details.json written)."""
    root = tmp_path_factory.mktemp("schemas")
    bundle, out = root / "bundle", root / "out"
    cli = [sys.executable, "-m", "pipeline.cli"]
    subprocess.run([*cli, "simulate", "capture", str(bundle), "--size", "160x128"], check=True)
    subprocess.run(
        [*cli, "inspect", str(bundle), "--target", str(bundle / "target.json"), "--out", str(out)],
        check=True,
    )
    return root


@pytest.mark.parametrize(
    ("stem", "path"),
    [
        ("stereo-calibration", "bundle/calibration.json"),
        ("plate-capture", "bundle/capture.json"),
        ("plate-target", "bundle/target.json"),
        ("plate-result", "out/result.json"),
        ("details", "out/details.json"),
    ],
)
def test_files_written_by_the_pipeline_meet_their_schema(inspected, stem, path):
    document = json.loads((inspected / path).read_text())
    errors = [e.message for e in _validator(stem).iter_errors(document)]
    assert errors == []


def test_a_schema_refuses_what_the_loader_refuses(inspected):
    capture = json.loads((inspected / "bundle/capture.json").read_text())
    capture["unexpected_key"] = 1
    assert not _validator("plate-capture").is_valid(capture)
