"""The configuration reference, read off the pydantic models themselves.

Every file the project reads (an experiment, each registered representation's ``object``
section, the fit, bench, latency and sweep files) is a frozen pydantic model; each field's
description is the string literal under it (``use_attribute_docstrings``), its type, default
and range (``Field`` constraints, also inside ``Annotated`` parts of unions and tuples) are the
model's own. :func:`reference_rows` walks a model and its nested sections into one row per
dotted key; :func:`undocumented` lists the keys without a description, which fail the docs
build (``docs/hooks/config_reference.py`` lists the files' models and renders their rows as
docs/config.md: the list names models above this floor, so it lives in the docs build)."""

from __future__ import annotations

import json
import types
import typing
from typing import Any, NamedTuple

import annotated_types as at
from pydantic import BaseModel
from pydantic.fields import FieldInfo
from pydantic_core import to_jsonable_python


class Row(NamedTuple):
    """One key of a configuration file: its dotted path (``[]`` marks a list's items,
    ``.<key>`` a mapping's values), type, default, range and meaning."""

    path: str
    type: str
    default: str
    range: str
    description: str


def _parts(tp) -> tuple[Any, tuple]:
    """(origin, args) of a type, ``Annotated`` kept as its own origin."""
    if typing.get_origin(tp) is typing.Annotated:
        return typing.Annotated, (tp.__origin__, *tp.__metadata__)
    return typing.get_origin(tp), typing.get_args(tp)


def _is_model(tp) -> bool:
    return isinstance(tp, type) and issubclass(tp, BaseModel)


def type_name(tp) -> str:
    """A type as a reader writes it in YAML terms: ``[float, float, float]`` for a 3-tuple,
    ``"a" or "b"`` for a literal, ``section`` for a nested model, ``or`` between union members."""
    origin, args = _parts(tp)
    if origin is typing.Annotated:
        return type_name(args[0])
    if origin is typing.Literal:
        return " or ".join(json.dumps(a) for a in args)
    if origin in (typing.Union, types.UnionType):
        return " or ".join(type_name(a) for a in args)
    if origin is list:
        return f"list[{type_name(args[0])}]"
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            return f"list[{type_name(args[0])}]"
        return "[" + ", ".join(type_name(a) for a in args) + "]"
    if origin is dict:
        return f"mapping[{type_name(args[0])}, {type_name(args[1])}]"
    if tp is type(None):
        return "null"
    if tp is Any:
        return "any"
    if tp is dict:
        return "mapping"
    if _is_model(tp):
        return "section"
    return getattr(tp, "__name__", str(tp))


_BOUNDS = ((at.Ge, "ge", "≥"), (at.Gt, "gt", ">"), (at.Le, "le", "≤"), (at.Lt, "lt", "<"))


def bounds(metadata) -> str:
    """``Field`` constraints as ``≥ 1, ≤ 4096`` (empty without any)."""
    out = []
    for m in metadata:
        for cls, attr, sign in _BOUNDS:
            if isinstance(m, cls):
                out.append(f"{sign} {getattr(m, attr)}")
        if isinstance(m, FieldInfo):
            out.append(bounds(m.metadata))
    return ", ".join(x for x in out if x)


def _nested_bounds(tp, each: bool = False) -> list[str]:
    """The bounds inside a type: an ``Annotated`` member of a union, a tuple's elements
    (``each ≥ 0`` where they agree) or a list's items."""
    origin, args = _parts(tp)
    if origin is typing.Annotated:
        b = bounds(args[1:])
        return ([f"each {b}" if each else b] if b else []) + _nested_bounds(args[0], each)
    if origin in (list, tuple):
        return list(dict.fromkeys(x for a in args if a is not Ellipsis for x in _nested_bounds(a, True)))
    return [x for a in args for x in _nested_bounds(a, each)] if origin in (typing.Union, types.UnionType) else []


def range_of(field: FieldInfo) -> str:
    """A field's range: its own constraints and those inside its type."""
    parts = [bounds(field.metadata), *_nested_bounds(field.annotation)]
    return "; ".join(dict.fromkeys(p for p in parts if p))


def default_of(field: FieldInfo) -> str:
    """A field's default as YAML flow text (JSON), ``required`` without one; a nested
    section's default is its own keys' defaults."""
    if field.is_required():
        return "required"
    value = field.get_default(call_default_factory=True)
    if isinstance(value, BaseModel):
        return "its keys' defaults"
    if isinstance(value, list) and value and all(isinstance(v, BaseModel) for v in value):
        return f"{len(value)} item{'s' * (len(value) > 1)}, each with its keys' defaults"
    return json.dumps(to_jsonable_python(value))


def nested_models(tp, path: str) -> list[tuple[str, type[BaseModel]]]:
    """The models inside a field's type with the path their keys hang from: ``path[]`` for a
    list's items, ``path.<key>`` for a mapping's values."""
    origin, args = _parts(tp)
    if _is_model(tp):
        return [(path, tp)]
    if origin is typing.Annotated:
        return nested_models(args[0], path)
    if origin in (list, tuple):
        return [x for a in args if a is not Ellipsis for x in nested_models(a, path + "[]")]
    if origin is dict:
        return nested_models(args[1], path + ".<key>")
    return [x for a in args for x in nested_models(a, path)] if origin in (typing.Union, types.UnionType) else []


def reference_rows(model: type[BaseModel], prefix: str = "", shown: dict | None = None, _stack: tuple = ()) -> list[Row]:
    """One row per key of ``model`` and of its nested sections, depth first, keys in the
    order the model declares them. ``shown`` (model -> path) is shared across calls: a section
    whose model was listed before is referred to by that path instead of listed again; a
    model nested in itself (a CSG node's children) is listed once."""
    shown = {} if shown is None else shown
    rows = []
    for name, f in model.model_fields.items():
        path = prefix + name
        desc = " ".join((f.description or "").split())
        later = []
        for p, m in nested_models(f.annotation, path):
            if m in _stack or m is model:
                desc += f" Its items have the keys of `{shown.get(m, prefix.rstrip('.'))}`."
            elif m in shown and shown[m] != p:
                desc += f" Its keys are those of `{shown[m]}`."
            else:
                shown.setdefault(m, p)
                later.append((p, m))
        rows.append(Row(path, type_name(f.annotation), default_of(f), range_of(f), desc.strip()))
        for p, m in later:
            rows += reference_rows(m, p + ".", shown, _stack + (model,))
    return rows


def undocumented(model: type[BaseModel], prefix: str = "") -> list[str]:
    """The dotted paths of the keys of ``model`` and its nested sections that have no
    description (every one of them, each model walked once)."""
    missing, seen, todo = [], set(), [(prefix, model)]
    while todo:
        pre, m = todo.pop(0)
        if m in seen:
            continue
        seen.add(m)
        for name, f in m.model_fields.items():
            if not (f.description or "").strip():
                missing.append(pre + name)
            todo += [(p + ".", sub) for p, sub in nested_models(f.annotation, pre + name)]
    return missing
