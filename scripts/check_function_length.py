"""List the functions longer than a limit in the Python files under the given directories.

    .venv/bin/python scripts/check_function_length.py pipeline [app ...] [--max-lines 80]

A function's length is counted from its ``def`` line to its last line, comments, blank lines and
nested functions included, its docstring not (decorators neither): the house rule is about code
that does several things, and a numpydoc docstring is documentation the house rules ask for.
Functions compiled by numba (decorated with ``numba.njit``, ``nb.jit``, ``njit``, ... however numba
was imported) are exempt: a kernel's loops stay in one function so that numba can compile them as
one. Exit status 1 when any function is over the limit (each printed as ``path:line: name (N
lines)``), 0 otherwise.
"""

from __future__ import annotations

import argparse
import ast
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

#: The house rule: no function over this many lines.
MAX_LINES = 80


@dataclass(frozen=True)
class LongFunction:
    """A function over the limit.

    Attributes
    ----------
    path : Path
    line : int
        Line of its ``def``.
    name : str
        Qualified within its module (``Class.method``, ``outer.<locals>.inner``).
    lines : int
        Its length without its docstring.
    """

    path: Path
    line: int
    name: str
    lines: int

    def __str__(self) -> str:
        return f"{self.path}:{self.line}: {self.name} ({self.lines} lines)"


def _numba_names(tree: ast.Module) -> tuple[set[str], set[str]]:
    """The names numba is bound to in a module: (module aliases, names imported from it)."""
    modules, names = set(), set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            modules |= {a.asname or a.name for a in node.names if a.name == "numba"}
        elif isinstance(node, ast.ImportFrom) and node.module == "numba":
            names |= {a.asname or a.name for a in node.names}
    return modules, names


def _docstring_lines(function: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """The number of lines of a function's docstring (0 without one)."""
    first = function.body[0]
    if (
        isinstance(first, ast.Expr)
        and isinstance(first.value, ast.Constant)
        and isinstance(first.value.value, str)
    ):
        return first.end_lineno - first.lineno + 1
    return 0


def _is_numba(decorator: ast.expr, modules: set[str], names: set[str]) -> bool:
    """True if ``decorator`` (``@nb.njit``, ``@numba.njit(parallel=True)``, ``@njit``) comes from numba."""
    target = decorator.func if isinstance(decorator, ast.Call) else decorator
    if isinstance(target, ast.Name):
        return target.id in names
    while isinstance(target, ast.Attribute):
        target = target.value
    return isinstance(target, ast.Name) and target.id in modules


def long_functions(path: Path, max_lines: int = MAX_LINES) -> Iterator[LongFunction]:
    """The functions of one file over ``max_lines`` lines, numba kernels exempt.

    Parameters
    ----------
    path : Path
        A Python source file.
    max_lines : int

    Yields
    ------
    LongFunction
    """
    tree = ast.parse(path.read_text(), filename=str(path))
    modules, names = _numba_names(tree)

    def visit(node: ast.AST, prefix: str) -> Iterator[LongFunction]:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                qualname = prefix + child.name
                lines = child.end_lineno - child.lineno + 1 - _docstring_lines(child)
                if lines > max_lines and not any(
                    _is_numba(d, modules, names) for d in child.decorator_list
                ):
                    yield LongFunction(path, child.lineno, qualname, lines)
                yield from visit(child, qualname + ".<locals>.")
            elif isinstance(child, ast.ClassDef):
                yield from visit(child, prefix + child.name + ".")
            else:
                yield from visit(child, prefix)

    yield from visit(tree, "")


def check(directories: list[Path], max_lines: int = MAX_LINES) -> list[LongFunction]:
    """Every function over ``max_lines`` in the ``*.py`` files under ``directories``, in path order."""
    found = []
    for directory in directories:
        for path in sorted(Path(directory).rglob("*.py")):
            found += long_functions(path, max_lines)
    return found


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("directories", nargs="+", type=Path)
    parser.add_argument("--max-lines", type=int, default=MAX_LINES)
    args = parser.parse_args(argv)
    found = check(args.directories, args.max_lines)
    for item in found:
        print(item)
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main())
