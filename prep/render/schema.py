"""Tables (a parsed TOML document or JSON object) read into dataclasses by their type hints.

:func:`build` makes an instance of a dataclass from a table: every key must be an init field (an unknown one is
refused with the closest valid key and the list of them), each value is checked against the field's type hint
and converted by :func:`convert` (arrays to tuples, integers to floats where the hint is float, tables to nested
dataclasses), and a ``ValueError`` the dataclass raises is put on the key it names. What the format accepts is
read from the dataclasses, so a new field or shape needs no change here. Every problem is a :class:`TableError`
whose message starts at the key path (``meshes[0].obj``) and echoes the value found in TOML notation
(:func:`show`); the reader (``scenefile.py``) prefixes the file name.
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import math
import re
import sys
import types
import typing
from typing import Any, Literal, Union

from prep.bounds import is_integer, is_number


class TableError(Exception):
    """A problem at a key path; the reader prefixes the file name."""


_BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")


def key_text(key: str) -> str:
    return key if _BARE_KEY.fullmatch(key) else json.dumps(key, ensure_ascii=False)


def join_key(path: str, key: str) -> str:
    return f"{path}.{key_text(key)}" if path else key_text(key)


def show(value) -> str:
    """A value as the file wrote it (TOML notation; JSON's null as null), at most 120 characters."""
    try:
        text = "null" if value is None else toml_value(value)
    except TypeError:
        text = repr(value)
    return text if len(text) <= 120 else text[:117] + "..."


def type_hints(cls) -> dict:
    """The resolved type hints of a dataclass; a hint that does not resolve (a name only a type checker
    sees) becomes Any, which passes values through for the dataclass to judge."""
    try:
        return typing.get_type_hints(cls)
    except Exception:
        pass
    out = {}
    for klass in reversed(cls.__mro__):
        module = sys.modules.get(klass.__module__)
        for name, hint in vars(klass).get("__annotations__", {}).items():
            if isinstance(hint, str):
                try:
                    hint = eval(hint, dict(vars(module)) if module else {}, dict(vars(klass)))  # noqa: S307
                except Exception:
                    hint = Any
            out[name] = hint
    return out


def init_fields(cls) -> list:
    return [f for f in dataclasses.fields(cls) if f.init]


def is_required(f) -> bool:
    return f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING


def _is_union(hint) -> bool:
    return typing.get_origin(hint) in (Union, types.UnionType)


def describe(hint) -> str:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if _is_union(hint):
        return " or ".join(describe(a) for a in args)
    if hint is type(None):
        return "no value"
    if hint is bool:
        return "true or false"
    if hint is int:
        return "an integer"
    if hint is float:
        return "a finite number"
    if hint is str:
        return "a string"
    if origin is Literal:
        return "one of " + ", ".join(show(a) for a in args)
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            return f"an array of {describe(args[0])}s"
        if args and all(a == args[0] for a in args):
            return f"{len(args)} {_plural(args[0])}"
        return "an array of " + ", ".join(describe(a) for a in args)
    if origin is list:
        return f"an array (each {describe(args[0])})" if args else "an array"
    if origin is dict or (dataclasses.is_dataclass(hint) and isinstance(hint, type)):
        return "a table"
    return getattr(hint, "__name__", str(hint))


def _plural(hint) -> str:
    return {float: "finite numbers", int: "integers", str: "strings"}.get(hint, f"values ({describe(hint)})")


def _category(value) -> str:
    if isinstance(value, dict):
        return "table"
    if isinstance(value, (list, tuple)):
        return "array"
    return "scalar"


def _hint_category(hint) -> str | None:
    origin = typing.get_origin(hint)
    if origin is dict or (dataclasses.is_dataclass(hint) and isinstance(hint, type)):
        return "table"
    if origin in (list, tuple):
        return "array"
    if hint in (bool, int, float, str, type(None)) or origin is Literal:
        return "scalar"
    return None


def convert(value, hint, path: str, extra_keys: dict | None = None):
    """``value`` as read from the file, checked against the type hint ``hint`` and converted (arrays to
    tuples where the hint is a tuple, integers to floats where it is float, tables to dataclasses).
    Hints this does not know pass the value through for the dataclass to judge; ``extra_keys`` as for
    :func:`build`."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    wrong = TableError(f"{path} = {show(value)}: expected {describe(hint)}")
    if hint is Any or hint is object:
        return value
    if _is_union(hint):
        members = [a for a in args if _hint_category(a) in (_category(value), None)]
        if value is None and type(None) in args:
            return None
        if len(members) == 1:
            return convert(value, members[0], path, extra_keys)
        errors = []
        for member in members:
            try:
                return convert(value, member, path, extra_keys)
            except TableError as exc:
                errors.append(exc)
        raise errors[0] if len(errors) == 1 else wrong
    if hint is type(None):
        if value is None:
            return None
        raise wrong
    if hint is bool:
        if isinstance(value, bool):
            return value
        raise wrong
    if hint is int:
        if is_integer(value):
            return value
        raise wrong
    if hint is float:
        if is_number(value) and math.isfinite(value):
            return float(value)
        raise wrong
    if hint is str:
        if isinstance(value, str):
            return value
        raise wrong
    if origin is Literal:
        if any(value == a and type(value) is type(a) for a in args):
            return value
        raise wrong
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise wrong
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(convert(v, args[0], f"{path}[{i}]", extra_keys) for i, v in enumerate(value))
        if args:
            if len(value) != len(args):
                raise wrong
            try:
                return tuple(convert(v, a, f"{path}[{i}]", extra_keys) for i, (v, a) in enumerate(zip(value, args)))
            except TableError:
                raise wrong from None
        return tuple(value)
    if origin is list:
        if not isinstance(value, (list, tuple)):
            raise wrong
        return [convert(v, args[0], f"{path}[{i}]", extra_keys) if args else v for i, v in enumerate(value)]
    if origin is dict:
        if not isinstance(value, dict):
            raise wrong
        return {k: convert(v, args[1], join_key(path, k), extra_keys) if len(args) == 2 else v
                for k, v in value.items()}
    if dataclasses.is_dataclass(hint) and isinstance(hint, type):
        return build(hint, value, path, extra_keys=extra_keys)
    return value


def field_of(message: str, cls, names) -> str | None:
    """The field a dataclass's ValueError is about: ``Cls.field`` anywhere in the message, or a field
    name followed by "must" (the convention of scene.py's messages); None when neither is there."""
    m = re.search(rf"\b{re.escape(cls.__name__)}\.(\w+)", message)
    if m and m.group(1) in names:
        return m.group(1)
    for m in re.finditer(r"\b(\w+) must\b", message):
        if m.group(1) in names:
            return m.group(1)
    return None


def build(cls, table, path: str, defaults: dict | None = None, also_valid: tuple = (),
          extra_keys: dict | None = None):
    """An instance of the dataclass ``cls`` from the table ``table`` at ``path``; ``defaults`` fill
    fields the table lacks; ``also_valid`` are keys the caller took out of the table (listed as valid);
    ``extra_keys`` maps a dataclass to the keys its tables may have beyond its fields, which the caller
    takes out before they are built (listed as valid there, at any depth)."""
    if not isinstance(table, dict):
        raise TableError(f"{path} = {show(table)}: expected a table (the fields of {cls.__name__})")
    fields = init_fields(cls)
    names = [f.name for f in fields]
    defaults = defaults or {}
    also_valid = tuple(also_valid) or (extra_keys or {}).get(cls, ())
    for key, value in table.items():
        if key not in names:
            close = difflib.get_close_matches(key, names + list(also_valid), n=1)
            hint = f" (did you mean {close[0]}?)" if close else ""
            where = f"of {path}" if path else "at the top level"
            raise TableError(f"unknown key {join_key(path, key)} = {show(value)}{hint}; valid keys {where}: "
                             f"{', '.join(names + list(also_valid))}")
    hints = type_hints(cls)
    kwargs = {}
    for f in fields:
        if f.name in table:
            kwargs[f.name] = convert(table[f.name], hints.get(f.name, Any), join_key(path, f.name), extra_keys)
        elif f.name in defaults:
            kwargs[f.name] = defaults[f.name]
        elif is_required(f):
            required = ", ".join(g.name for g in fields if is_required(g) and g.name not in defaults)
            raise TableError(f"{path or 'the top level'} lacks key {f.name} (required: {required})")
    try:
        return cls(**kwargs)
    except (ValueError, TypeError) as exc:
        message = str(exc)
        name = field_of(message, cls, [n for n in names if n in table])
        if name is None:
            raise TableError(f"{path}: {message}" if path else message) from None
        raise TableError(f"{join_key(path, name)} = {show(table[name])}: {message}") from None


def toml_str(s: str) -> str:
    return json.dumps(s, ensure_ascii=False).replace("\x7f", "\\u007f")


def toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)  # the shortest text that reads back as the same float
    if isinstance(v, str):
        return toml_str(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{key_text(k)} = {toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(f"cannot write a {type(v).__name__} to TOML: {v!r}")
