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
#: Longest route (or websocket) handler, lines from its ``def`` to its last line, docstring excluded.
MAX_ROUTE_LINES = 40
#: Decorators (``@router.<name>(...)``, ``@app.<name>(...)``) that make a function a route or websocket.
ROUTE_DECORATORS = {
    "get", "post", "put", "patch", "delete", "head", "options", "trace",
    "api_route", "route", "websocket", "websocket_route",
}  # fmt: skip


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


def _is_route(function: ast.FunctionDef | ast.AsyncFunctionDef) -> bool:
    for decorator in function.decorator_list:
        call = decorator.func if isinstance(decorator, ast.Call) else decorator
        if isinstance(call, ast.Attribute) and call.attr in ROUTE_DECORATORS:
            return True
    return False


def _length_without_docstring(function: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """Lines from ``def`` to the function's last line, less its docstring's."""
    assert function.end_lineno is not None
    lines = function.end_lineno - function.lineno + 1
    first = function.body[0]
    if (
        isinstance(first, ast.Expr)
        and isinstance(first.value, ast.Constant)
        and isinstance(first.value.value, str)
    ):
        assert first.end_lineno is not None
        lines -= first.end_lineno - first.lineno + 1
    return lines


def _route_lengths() -> dict[str, int]:
    """Every route and websocket handler of the service packages: ``path:line name`` -> lines."""
    lengths = {}
    for package in SERVICE_PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            tree = ast.parse(path.read_text(), filename=str(path))
            for node in ast.walk(tree):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and _is_route(node):
                    where = f"{path.relative_to(ROOT)}:{node.lineno} {node.name}"
                    lengths[where] = _length_without_docstring(node)
    return lengths


def test_routes_are_thin():
    """A route parses, authorises and calls one service function: at most 40 lines, docstring apart."""
    lengths = _route_lengths()
    names = {where.rsplit(" ", 1)[1] for where in lengths}
    assert {"create_inspection", "put_target", "viewer_bridge", "result_page"} <= names
    long = {where: n for where, n in lengths.items() if n > MAX_ROUTE_LINES}
    assert long == {}, f"routes over {MAX_ROUTE_LINES} lines (docstring excluded): {long}"
