"""The settings schema engine: YAML in, validated frozen dataclasses out.

A section of a settings file maps onto a frozen dataclass; its fields *are* the schema:
type hints give the type, ``field(metadata=...)`` gives the documentation (``doc``),
bounds (``ge``, ``gt``, ``le``, ``lt``, applied to numbers and to every element of a list)
and list lengths (``len``). Any problem raises one :class:`~calib.errors.ScenarioError`
naming the file, the key path, the value and what is allowed; unknown keys get a
did-you-mean; YAML syntax errors and duplicate keys give the line. Scenario files
(:mod:`bench.config.scenario`), hw configs (:mod:`bench.config.hw`), plan files
(:mod:`bench.config.plan_file`) and sweep files (:mod:`bench.jobs.sweep`) are read with
:func:`read_yaml`, bench's one YAML reader.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import types
import typing
from typing import Any, Literal

import yaml

from calib.errors import ScenarioError

# --------------------------------------------------------------------------- YAML reading


__all__ = [
    "apply_overrides",
    "bounds_text",
    "build_section",
    "did_you_mean",
    "read_yaml",
    "type_text",
]


class _StrictLoader(yaml.SafeLoader):
    """Safe loader that refuses duplicate keys (PyYAML silently keeps the last one)."""


def _construct_mapping(loader: _StrictLoader, node: yaml.MappingNode) -> dict[Any, Any]:
    mapping: dict[Any, Any] = {}
    for key_node, value_node in node.value:
        key = loader.construct_object(key_node)
        if key in mapping:
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key {key!r}", key_node.start_mark
            )
        mapping[key] = loader.construct_object(value_node, deep=True)
    return mapping


_StrictLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _construct_mapping)


def read_yaml(path: str) -> Any:
    try:
        with open(path, encoding="utf-8") as fh:
            text = fh.read()
    except FileNotFoundError:
        raise ScenarioError("no such file", source=path) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ScenarioError(f"cannot read the file ({exc})", source=path) from None
    try:
        return yaml.load(text, Loader=_StrictLoader)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
        line = mark.line + 1 if mark is not None else None
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ScenarioError(f"invalid YAML: {problem}", source=path, line=line) from None


# --------------------------------------------------------------------------- validation


def did_you_mean(key: str, allowed: typing.Iterable[str]) -> str:
    close = difflib.get_close_matches(key, list(allowed), n=1)
    return f"; did you mean {close[0]!r}?" if close else ""


def type_text(tp: Any, meta: dict[str, Any]) -> str:
    """Human description of what a field accepts (also used in the docs)."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        inner = [a for a in args if a is not type(None)]
        text = " or ".join(type_text(a, meta) for a in inner)
        return f"{text} or null" if type(None) in args else text
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in args)
    if origin is tuple:
        n = meta.get("len") if args[-1] is Ellipsis else len(args)
        if typing.get_origin(args[0]) is Literal:
            return "list of values from " + ", ".join(repr(a) for a in typing.get_args(args[0]))
        elem = type_text(args[0], {})
        return f"list of {n} {elem}s" if n else f"list of {elem}s"
    return {float: "number", int: "integer", bool: "true/false", str: "string"}[tp]


def bounds_text(meta: dict[str, Any]) -> str:
    ops = {"ge": "≥", "gt": ">", "le": "≤", "lt": "<"}
    return ", ".join(f"{ops[k]} {meta[k]:g}" for k in ops if k in meta)


def _check_bounds(x: float, meta: dict[str, Any]) -> bool:
    return not (
        ("ge" in meta and x < meta["ge"])
        or ("gt" in meta and x <= meta["gt"])
        or ("le" in meta and x > meta["le"])
        or ("lt" in meta and x >= meta["lt"])
    )


def _coerce(value: Any, tp: Any, meta: dict[str, Any], where: dict[str, Any]) -> Any:
    """Validate ``value`` against a field type; return the value to store."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)

    def fail(what: str) -> typing.NoReturn:
        allowed = type_text(tp, meta)
        bounds = bounds_text(meta)
        raise ScenarioError(
            what, value=value, allowed=allowed + (f", {bounds}" if bounds else ""), **where
        )

    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        # A named setting (a Literal member) first, then the value's own type.
        named = [a for a in inner if typing.get_origin(a) is Literal]
        if isinstance(value, str) and any(value in typing.get_args(a) for a in named):
            return value
        other = [a for a in inner if typing.get_origin(a) is not Literal]
        if not other or (named and isinstance(value, str) and str not in other):
            names = [str(v) for a in named for v in typing.get_args(a)]
            fail("not an allowed value" + did_you_mean(str(value), names))
        return _coerce(value, other[0], meta, where)
    if origin is Literal:
        if value not in args:
            fail("not an allowed value" + did_you_mean(str(value), map(str, args)))
        return value
    if origin is tuple:
        if not isinstance(value, list | tuple):
            fail("expected a list")
        n = meta.get("len") if args[-1] is Ellipsis else len(args)
        if n is not None and len(value) != n:
            fail(f"expected {n} values, got {len(value)}")
        elem_tp = args[0]
        if typing.get_origin(elem_tp) is Literal:
            for v in value:
                if v not in typing.get_args(elem_tp):
                    fail(f"{v!r} is not an allowed value")
            return tuple(value)
        return tuple(_coerce_scalar(v, elem_tp, meta, fail) for v in value)
    return _coerce_scalar(value, tp, meta, fail)


def _coerce_scalar(value: Any, tp: Any, meta: dict[str, Any], fail: Any) -> Any:
    if tp is bool:
        if not isinstance(value, bool):
            fail("expected true or false")
        return value
    if tp is str:
        if not isinstance(value, str):
            fail("expected a string")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            fail("expected an integer")
    elif tp is float:
        if isinstance(value, bool) or not isinstance(value, int | float):
            fail("expected a number")
        if not math.isfinite(value):
            fail("expected a finite number")
        value = float(value)
    if not _check_bounds(value, meta):
        fail("out of range")
    return value


def build_section(cls: type, data: Any, section: str, source: str) -> Any:
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ScenarioError("expected a mapping of keys", source=source, key=section, value=data)
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs = {}
    for key, value in data.items():
        path = f"{section}.{key}"
        if key not in fields:
            raise ScenarioError(
                "unknown key" + did_you_mean(str(key), fields),
                source=source,
                key=path,
                allowed=", ".join(fields),
            )
        kwargs[key] = _coerce(
            value, hints[key], dict(fields[key].metadata), {"source": source, "key": path}
        )
    return cls(**kwargs)


def apply_overrides(data: Any, overrides: typing.Sequence[str], source: str) -> dict[str, Any]:
    """Apply ``key.path=value`` overrides (values parsed as YAML) to a parsed mapping."""
    data = dict(data or {})
    for item in overrides:
        if "=" not in item:
            raise ScenarioError("an override must read key.path=value", source="--set", key=item)
        path, _, text = item.partition("=")
        keys = path.strip().split(".")
        try:
            value = yaml.load(text, Loader=_StrictLoader)
        except yaml.YAMLError:
            raise ScenarioError(
                "value is not valid YAML", source="--set", key=path, value=text
            ) from None
        node = data
        for k in keys[:-1]:
            child = node.get(k)
            child = dict(child) if isinstance(child, dict) else {}
            node[k] = child
            node = child
        node[keys[-1]] = value
    return data
