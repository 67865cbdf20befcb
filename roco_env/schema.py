"""One declarative validation mechanism for every configuration value.

A setting is a dataclass field declared once with :func:`spec`: its type (the
annotation), its default and what is allowed (``choices`` or an interval
``[low, high]``, either end open). :func:`build` turns a plain mapping into
such a dataclass, checking every key and value; the messages name the place
(a file, ``override``, a policy), the dotted key and what is allowed. A field
declared ``path=True`` names a file or folder: given a ``base`` folder (a scenario
file's), :func:`build` resolves a relative value against it. Scenario
files, overrides, noise-model and detector parameters (:mod:`roco_env.scenario`)
and alignment-policy parameters all go through it.

Accepted as given by users: numpy scalars (``np.int64(2)``, ``np.float32(.4)``,
``np.bool_(True)``) become Python numbers; an int is a valid float; a tuple is a
valid list. :func:`load_yaml` reads YAML with the YAML 1.2 number rules, so
``1e1`` is the float 10.0 (PyYAML's YAML 1.1 rules read it as a string).
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import types
import typing
from collections.abc import Callable, Hashable, Mapping
from typing import Any

import numpy as np
import yaml

__all__ = ["ConfigError", "build", "check_value", "load_yaml", "spec"]


class ConfigError(ValueError):
    """A configuration value is invalid; the message names where, the key and why."""


def spec(default: Any, *, choices: tuple | Callable[[], tuple] | None = None, low: float | None = None,
         high: float | None = None, low_open: bool = False, high_open: bool = False,
         path: bool = False, doc: str = "") -> Any:
    """A dataclass field carrying its allowed values: ``choices`` (a tuple, or a function
    returning one when it is checked: a stage registry's names), or ``low``..``high``
    (closed ends unless ``low_open`` / ``high_open``; either bound may be omitted);
    ``path``: a string naming a file or folder (see :func:`build`)."""
    meta = {"choices": choices, "low": low, "high": high, "low_open": low_open,
            "high_open": high_open, "path": path, "doc": doc}
    if isinstance(default, (list, dict, tuple)):
        return dataclasses.field(default_factory=lambda: type(default)(default), metadata=meta)
    return dataclasses.field(default=default, metadata=meta)


def allowed_text(meta: Mapping[str, Any]) -> str:
    """The allowed values of a field, as its error messages write them."""
    if meta.get("choices") is not None:
        return f"one of {list(allowed_choices(meta))}"
    low, high = meta.get("low"), meta.get("high")
    left = "(" if meta.get("low_open") or low is None else "["
    right = ")" if meta.get("high_open") or high is None else "]"
    return f"{left}{'-inf' if low is None else low}, {'inf' if high is None else high}{right}"


def allowed_choices(meta: Mapping[str, Any]) -> tuple | None:
    """A field's ``choices`` as a tuple (a function of them called now), None if it has none."""
    choices = meta.get("choices")
    return choices() if callable(choices) else choices


def build(cls: type, data: Any, where: str, prefix: str = "",
          base: str | os.PathLike | None = None) -> Any:
    """An instance of dataclass ``cls`` from ``data`` (a mapping; missing keys keep their
    defaults), nested dataclasses included. Raises :class:`ConfigError`.

    base: the folder relative values of ``path`` fields are relative to (a scenario
    file's folder); None keeps them as given (relative to the working directory)."""
    if not isinstance(data, Mapping):
        raise ConfigError(f"{where}: {prefix.rstrip('.') or 'top level'} must be a mapping of "
                            f"keys; got {type(data).__name__} ({data!r})")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    hints = typing.get_type_hints(cls)
    unknown = sorted(set(data) - set(fields), key=str)
    if unknown:
        raise ConfigError(unknown_key_message(where, prefix + str(unknown[0]),
                                                [prefix + name for name in fields]))
    values = {}
    for name, value in data.items():
        key, hint = prefix + name, hints[name]
        if dataclasses.is_dataclass(hint):
            values[name] = build(hint, value, where, key + ".", base)
        else:
            values[name] = check_value(value, hint, fields[name].metadata, where, key)
            if base is not None and fields[name].metadata.get("path"):
                values[name] = resolved_path(values[name], base)
    return cls(**values)


def resolved_path(value: str | None, base: str | os.PathLike) -> str | None:
    """A path field's value with a relative path joined to the folder ``base`` (made
    absolute, so the result does not depend on a later working directory); None, an
    empty string and absolute paths stay as they are."""
    if not value or os.path.isabs(value):
        return value
    return os.path.join(os.path.abspath(base), value)


def unknown_key_message(where: str, key: str, allowed: list[str]) -> str:
    return f"{where}: unknown key {key!r}; allowed: {', '.join(allowed) or 'none (no keys here)'}"


_EXPECTS = {bool: "true or false", int: "an integer", float: "a number", str: "a string",
            list: "a list", tuple: "a list", dict: "a mapping"}


def check_value(value: Any, hint: Any, meta: Mapping[str, Any], where: str, key: str) -> Any:
    """``value`` checked against the annotation ``hint`` and the field's allowed values;
    returns it as the plain Python type (numpy scalars converted)."""
    union = isinstance(hint, types.UnionType) or typing.get_origin(hint) is typing.Union
    allowed_types = typing.get_args(hint) if union else (hint,)
    if value is None:
        if type(None) in allowed_types:
            return None
        raise ConfigError(f"{where}: {key} must not be null")
    base = next(t for t in allowed_types if t is not type(None))
    base = typing.get_origin(base) or base
    if isinstance(value, np.generic):
        value = value.item()
    if base is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if base in (list, tuple) and isinstance(value, (list, tuple)):
        value = base(value)
    if not isinstance(value, base) or (base in (int, float) and isinstance(value, bool)):
        raise ConfigError(f"{where}: {key} expects {_EXPECTS.get(base, base.__name__)}; "
                            f"got {value!r} ({type(value).__name__})")
    if base is float and not math.isfinite(value):
        raise ConfigError(f"{where}: {key}={value!r} must be finite")
    choices, low, high = allowed_choices(meta), meta.get("low"), meta.get("high")
    if choices is not None and value not in choices:
        raise ConfigError(f"{where}: {key}={value!r} is not allowed; choose "
                            f"{allowed_text(meta)}")
    below = low is not None and (value <= low if meta.get("low_open") else value < low)
    above = high is not None and (value >= high if meta.get("high_open") else value > high)
    if below or above:
        raise ConfigError(f"{where}: {key}={value!r} is out of range; allowed "
                            f"{allowed_text(meta)}")
    return value


class _Loader(yaml.SafeLoader):
    """PyYAML's safe loader plus the YAML 1.2 exponent floats YAML 1.1 reads as strings
    (``1e1``, ``2.5e0``: no dot or no exponent sign), refusing duplicate mapping keys
    (YAML requires unique keys; PyYAML would keep the last one silently)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        first_line: dict = {}
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":  # `<<: *anchor`; explicit keys win
                continue
            key = self.construct_object(key_node, deep=deep)
            if not isinstance(key, Hashable):  # the base class says what is wrong with it
                continue
            if key in first_line:
                raise yaml.constructor.ConstructorError(
                    "while constructing a mapping", node.start_mark,
                    f"found duplicate key {key!r} (first on line {first_line[key]})",
                    key_node.start_mark)
            first_line[key] = key_node.start_mark.line + 1
        return super().construct_mapping(node, deep=deep)


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float", re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),
    list("-+0123456789"))


def load_yaml(text: str) -> Any:
    """Parse YAML text safely (no object construction) with YAML 1.2 number rules."""
    return yaml.load(text, Loader=_Loader)  # noqa: S506 - _Loader is a SafeLoader
