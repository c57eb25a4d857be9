"""The repository's layout rules: short functions in the pipeline, and a pipeline that never imports the service."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PIPELINE = ROOT / "pipeline"
CHECKER = ROOT / "scripts" / "check_function_length.py"
SERVICE_PACKAGES = ("app", "web")


def test_no_pipeline_or_service_function_is_over_80_lines():
    out = subprocess.run(
        [sys.executable, str(CHECKER), str(PIPELINE), str(ROOT / "app")],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert out.returncode == 0, (
        f"functions over 80 lines (numba kernels exempt):\n{out.stdout}{out.stderr}"
    )
    assert out.stdout == ""


def test_the_checker_finds_a_long_function_and_exempts_numba_kernels(tmp_path):
    body = "\n".join(f"    x{i} = {i}" for i in range(81))
    (tmp_path / "long.py").write_text(
        f'import numba as nb\n\n\ndef long():\n    """Doc."""\n{body}\n\n\n'
        f"@nb.njit(cache=True)\ndef kernel():\n{body}\n"
    )
    out = subprocess.run(
        [sys.executable, str(CHECKER), str(tmp_path)], capture_output=True, text=True
    )
    assert out.returncode == 1
    assert out.stdout.splitlines() == [f"{tmp_path / 'long.py'}:4: long (82 lines)"]


def _imported_roots(path: Path) -> set[str]:
    """The top-level packages a module imports by absolute name."""
    roots = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            roots |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            roots.add(node.module.split(".")[0])
    return roots


def test_pipeline_never_imports_the_service():
    offenders = {
        str(path.relative_to(ROOT)): sorted(_imported_roots(path) & set(SERVICE_PACKAGES))
        for path in sorted(PIPELINE.rglob("*.py"))
    }
    assert {k: v for k, v in offenders.items() if v} == {}


def test_importing_every_pipeline_module_loads_no_service_module():
    code = (
        "import importlib, pkgutil, sys, pipeline\n"
        "for m in pkgutil.walk_packages(pipeline.__path__, 'pipeline.'):\n"
        "    importlib.import_module(m.name)\n"
        f"print(sorted(n for n in sys.modules if n.split('.')[0] in {SERVICE_PACKAGES!r}))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True
    )
    assert out.stdout.strip() == "[]"
