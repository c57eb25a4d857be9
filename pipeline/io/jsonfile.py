"""Reading JSON files: depth, number and finiteness limits, one error naming the file and field."""

from __future__ import annotations

import json
import math
import os
import sys
from pathlib import Path
from typing import Any

from ..formats import (
    InputError,
)

MAX_JSON_DEPTH = 32


def read_json(path: str | os.PathLike[str], *, label: str | None = None) -> dict[str, Any]:
    """Read a JSON file that must hold one object.

    Parameters
    ----------
    path : str or Path
    label : str, optional
        How error messages name the file (default: the path).

    Returns
    -------
    dict
        The parsed object. ``NaN``/``Infinity`` literals parse (Python's json
        accepts them); the loaders reject non-finite numbers with their field.

    Raises
    ------
    InputError
        Missing, unreadable, empty, not UTF-8, not JSON, or not a JSON object.
    """
    path = Path(path)
    label = str(path) if label is None else label
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise InputError(label, "", "file not found") from None
    except IsADirectoryError:
        raise InputError(label, "", "expected a JSON file, got a folder") from None
    except OSError as exc:
        raise InputError(label, "", f"cannot read: {exc.strerror or exc}") from None
    return _parse_json(data, label)


def _parse_json(data: bytes, label: str) -> dict[str, Any]:
    if not data.strip():
        raise InputError(label, "", "file is empty, expected a JSON object")
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(label, "", f"not UTF-8 text (byte {exc.start})") from None
    try:
        doc = json.loads(text, parse_int=_parse_int)
    except json.JSONDecodeError as exc:
        raise InputError(
            label, "", f"not valid JSON: {exc.msg} at line {exc.lineno} column {exc.colno}"
        ) from None
    except RecursionError:
        raise InputError(
            label, "", f"objects and lists nested deeper than {MAX_JSON_DEPTH} levels"
        ) from None
    if not isinstance(doc, dict):
        raise InputError(label, "", f"expected a JSON object, got {_json_type(doc)}")
    _check_json_tree(doc, label)
    return doc


class _LongInteger:
    """Stands in for an integer literal too long for Python to convert (found with its field after parsing)."""

    def __init__(self, digits: int) -> None:
        self.digits = digits


def _parse_int(literal: str) -> int | _LongInteger:
    try:
        return int(literal)
    except ValueError:  # more digits than sys.get_int_max_str_digits()
        return _LongInteger(len(literal.lstrip("-")))


def _check_json_tree(doc: dict[str, Any], label: str) -> None:
    """Refuse nesting deeper than :data:`MAX_JSON_DEPTH` and over-long integers, naming the field.

    Walks the tree without recursion, so no document can exhaust the stack here.
    """
    stack: list[tuple[Any, str, int]] = [(doc, "", 1)]
    while stack:
        value, field, depth = stack.pop()
        if isinstance(value, _LongInteger):
            limit = sys.get_int_max_str_digits()
            raise InputError(
                label,
                field,
                f"expected a number of at most {limit} digits, got one of {value.digits}",
            )
        if isinstance(value, dict):
            items = [(f"{field}.{key}" if field else str(key), item) for key, item in value.items()]
        elif isinstance(value, list):
            items = [(f"{field}[{i}]", item) for i, item in enumerate(value)]
        else:
            continue
        if depth > MAX_JSON_DEPTH:
            raise InputError(
                label, field, f"objects and lists nested deeper than {MAX_JSON_DEPTH} levels"
            )
        stack.extend((item, name, depth + 1) for name, item in items)


def _json_type(value: object) -> str:
    if value is None:
        return "null"
    names = {
        bool: "a boolean",
        int: "a number",
        float: "a number",
        str: "a string",
        list: "a list",
        dict: "an object",
    }
    return names.get(type(value), type(value).__name__)


def _reject_non_finite(value: object, label: str, field: str = "") -> None:
    """Raise on the first NaN/Infinity anywhere in a parsed JSON document."""
    if isinstance(value, float) and not math.isfinite(value):
        raise InputError(label, field, f"expected a finite number, got {value}")
    if isinstance(value, dict):
        for key, item in value.items():
            _reject_non_finite(item, label, f"{field}.{key}" if field else str(key))
    elif isinstance(value, (list, tuple)):
        for i, item in enumerate(value):
            _reject_non_finite(item, label, f"{field}[{i}]")
