"""pydantic's validation errors translated to one InputError naming the file and the field."""

from __future__ import annotations

import json
import re
import types
from collections.abc import Iterable
from typing import Annotated, Any, TypeVar, Union, get_args, get_origin

import pydantic
from pydantic import BaseModel
from pydantic_core import ErrorDetails

from ..formats import (
    InputError,
)
from .jsonfile import _reject_non_finite

_Model = TypeVar("_Model", bound=BaseModel)


def _unwrap(tp: Any) -> Any:
    """Strip ``Annotated[...]`` and ``X | None`` down to the type pydantic walks into."""
    while True:
        origin = get_origin(tp)
        if origin is Annotated:
            tp = get_args(tp)[0]
            continue
        if origin in (Union, types.UnionType):
            args = [a for a in get_args(tp) if a is not type(None)]
            if len(args) == 1:
                tp = args[0]
                continue
        return tp


def _is_model(tp: object) -> bool:
    return isinstance(tp, type) and issubclass(tp, BaseModel)


def _union_member(members: Iterable[Any], tag: object) -> Any:
    """The member of a union that pydantic's loc element ``tag`` names (class name or discriminator)."""
    for member in members:
        member = _unwrap(member)
        if getattr(member, "__name__", None) == tag:
            return member
        if (
            _is_model(member)
            and "type" in member.model_fields
            and tag in get_args(_unwrap(member.model_fields["type"].annotation))
        ):
            return member
    return None


def _walk_loc(model: type[BaseModel], loc: Iterable[int | str]) -> tuple[str, Any, Any]:
    """Dotted field path of a pydantic error ``loc``; union branch tags are dropped.

    Returns ``(field, type at the end of loc, type holding the last element)``.
    """
    parts: list[str] = []
    tp: Any = model  # a model, a list[...] or union annotation, or None past the schema
    parent: Any = None
    for item in loc:
        tp = _unwrap(tp)
        if isinstance(item, int):
            parts.append(f"[{item}]")
            args = get_args(tp)
            parent, tp = tp, (args[0] if get_origin(tp) is list and args else None)
            continue
        if _is_model(tp) and item in tp.model_fields:
            parts.append(f".{item}" if parts else item)
            parent, tp = tp, tp.model_fields[item].annotation
            continue
        if get_origin(tp) in (Union, types.UnionType):
            member = _union_member(get_args(tp), item)
            if member is not None:
                tp = member
                continue
        parts.append(f".{item}" if parts else str(item))
        parent, tp = tp, None
    return "".join(parts), _unwrap(tp) if tp is not None else None, parent


def _short(value: object, limit: int = 60) -> str:
    text = (
        json.dumps(value)
        if isinstance(value, (dict, list, str, int, float, bool, type(None)))
        else repr(value)
    )
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _describe_error(model: type[BaseModel], err: ErrorDetails) -> tuple[str, str]:
    field, end_tp, parent = _walk_loc(model, err["loc"])
    kind = err["type"]
    ctx = err.get("ctx") or {}
    if kind == "missing":
        return field, "missing required key"
    if kind == "extra_forbidden":
        allowed = ", ".join(parent.model_fields) if _is_model(parent) else "?"
        return field, f"unknown key (allowed here: {allowed})"
    if kind == "literal_error":
        return field, f"expected {ctx.get('expected')}, got {_short(err.get('input'))}"
    if kind == "union_tag_invalid":
        key, tag = ctx.get("discriminator", "type"), ctx.get("tag")
        return field, f"unknown {key} {tag!r}, expected one of {ctx.get('expected_tags')}"
    if kind == "value_error":
        reason = str(ctx["error"]) if "error" in ctx else err["msg"].removeprefix("Value error, ")
        # A model-level check names the key it is about: "lights: expected ...".
        m = re.match(r"^(\w+): (.*)$", reason)
        if m and _is_model(end_tp) and m.group(1) in end_tp.model_fields:
            field = f"{field}.{m.group(1)}" if field else m.group(1)
            reason = m.group(2)
        return field, reason
    reason = err["msg"]
    if "input" in err and kind not in ("missing",):
        reason += f", got {_short(err['input'])}"
    return field, reason


def _validate(
    model: type[_Model],
    doc: dict[str, Any],
    *,
    label: str,
    expected_format: str,
    prefix: str = "",
) -> _Model:
    """Validate ``doc`` against ``model``; the first problem becomes an InputError."""
    fmt_field = prefix + "format"
    if "format" not in doc:
        raise InputError(label, fmt_field, f"missing required key, expected {expected_format!r}")
    if doc["format"] != expected_format:
        raise InputError(
            label,
            fmt_field,
            f"unknown format {_short(doc['format'])}, expected {expected_format!r}",
        )
    _reject_non_finite(doc, label, prefix.rstrip("."))
    try:
        return model.model_validate(doc)
    except pydantic.ValidationError as exc:
        errors = exc.errors()
        field, reason = _describe_error(model, errors[0])
        if len(errors) > 1:
            more = len(errors) - 1
            reason += f" (and {more} more problem{'s' if more > 1 else ''})"
        raise InputError(label, prefix + field, reason) from None
