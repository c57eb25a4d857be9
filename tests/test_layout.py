"""The repository's layout rules: short functions in the pipeline, a pipeline that never imports the service,
the method's wings (each naming its public API, none reaching into another's private names), thin routes."""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PIPELINE = ROOT / "pipeline"
CHECKER = ROOT / "scripts" / "check_function_length.py"
SERVICE_PACKAGES = ("app", "web")
#: The method's wings inside ``pipeline/`` (docs/architecture.md).
WINGS = ("lights", "surface", "judge")
#: Modules directly in ``pipeline/``: the entry point and the stage chain on top, ``__init__`` included.
MAX_TOP_MODULES = 10
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


def test_at_most_ten_modules_sit_directly_in_the_pipeline():
    top = sorted(path.name for path in PIPELINE.glob("*.py"))
    assert len(top) <= MAX_TOP_MODULES, top
    assert {"run.py", "stages.py", "cli.py"} <= set(top)


def _private_imports(path: Path, own: str | None) -> list[str]:
    """``pipeline.<wing>`` private names (a leading underscore) that ``path`` imports from another wing."""
    found = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if not (isinstance(node, ast.ImportFrom) and node.level == 0 and node.module):
            continue
        parts = node.module.split(".")
        if parts[0] != "pipeline" or len(parts) < 2 or parts[1] not in WINGS or parts[1] == own:
            continue
        found += [f"{node.module}.{a.name}" for a in node.names if a.name.startswith("_")]
        found += [f"{node.module}" for part in parts[2:] if part.startswith("_")]
    return found


def test_no_wing_reaches_into_another_wings_private_names():
    offenders = {}
    for package in ("pipeline", *SERVICE_PACKAGES):
        for path in sorted((ROOT / package).rglob("*.py")):
            rel = path.relative_to(ROOT)
            own = rel.parts[1] if package == "pipeline" and rel.parts[1] in WINGS else None
            if found := _private_imports(path, own):
                offenders[str(rel)] = found
    assert offenders == {}


def test_each_wing_names_its_public_api_and_every_name_loads():
    """Each wing's ``__init__.pyi`` lists its public API; ``__init__.py`` loads those names lazily
    (lazy_loader): with ``EAGER_IMPORT`` set every name is imported at once and must resolve."""
    code = (
        "import importlib\n"
        f"for wing in {WINGS!r}:\n"
        "    module = importlib.import_module('pipeline.' + wing)\n"
        "    assert module.__all__, wing\n"
        "    missing = [n for n in module.__all__ if getattr(module, n, None) is None]\n"
        "    assert not missing, (wing, missing)\n"
        "print('ok')\n"
    )
    for wing in WINGS:
        assert (PIPELINE / wing / "__init__.pyi").is_file(), wing
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env={**os.environ, "EAGER_IMPORT": "1"},
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"
