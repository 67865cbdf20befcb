"""Command-line options generated from a :func:`~roco_env.schema.spec` dataclass.

:class:`SpecFlags` adds one ``--option`` per field to an argparse parser (``noise_low`` ->
``--noise-low``): help from the field's ``doc``, its allowed values and its default; the
value type from the annotation; a bool as ``--x`` / ``--no-x``; a fixed-length tuple as
exactly that many values; a list or a ``tuple[T, ...]`` as one or more values. It reads the
options given back into the dataclass through :func:`~roco_env.schema.build` (options not
given keep the dataclass's defaults, so every check and message is the dataclass's), and
writes the options that reproduce an instance (the command a run records). A field holding
a nested dataclass gets no option (it keeps its default).
"""

from __future__ import annotations

import argparse
import dataclasses
import typing
from collections.abc import Iterable, Mapping
from typing import Any

from roco_env.schema import allowed_choices, allowed_text, build, optional_type

__all__ = ["SpecFlags"]


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def _generated(name: str, value: Any) -> str:
    """The generated option that sets field ``name`` to the scalar ``value``."""
    if isinstance(value, bool):
        return _flag(name) if value else "--no-" + _flag(name)[2:]
    return f"{_flag(name)}={value}"


def _default(field: dataclasses.Field) -> Any:
    if field.default_factory is not dataclasses.MISSING:
        return field.default_factory()
    return field.default


def _shown(value: Any) -> str:
    if isinstance(value, (list, tuple)):
        return " ".join(map(str, value)) or "none"
    return "none" if value is None else str(value)


class SpecFlags:
    """The command-line options of the spec dataclass ``cls`` (module docstring).

    where: names the command in error messages (``build``'s ``where``); required: fields
    that must be given; aliases: further flags that set a field to a constant,
    ``{flag: (field, value)}``, e.g. ``{"--freeze-encoder": ("train_encoder", False)}``
    (flags older than the generated ones; :meth:`argv` writes them for that value).
    """

    def __init__(self, cls: type, where: str, *, required: Iterable[str] = (),
                 aliases: Mapping[str, tuple[str, Any]] | None = None) -> None:
        self.cls, self.where = cls, where
        self.required = frozenset(required)
        self.aliases = dict(aliases or {})
        hints = typing.get_type_hints(cls)
        self._fields = [(field, optional_type(hints[field.name])[0])
                        for field in dataclasses.fields(cls)
                        if not dataclasses.is_dataclass(hints[field.name])]

    def add_to(self, parser: argparse.ArgumentParser) -> None:
        """One option per field, plus the aliases."""
        for field, kind in self._fields:
            parser.add_argument(_flag(field.name), dest=field.name, default=None,
                                required=field.name in self.required,
                                help=self._help(field).replace("%", "%%"),
                                **self._parsing(field, kind))
        for flag, (name, value) in self.aliases.items():
            parser.add_argument(flag, dest=name, action="store_const", const=value,
                                help=f"the same as {_generated(name, value)}")

    def parse(self, args: argparse.Namespace) -> Any:
        """The checked dataclass of the options given (the others keep their defaults);
        raises :class:`~roco_env.schema.ConfigError` naming the field and what is allowed."""
        given = {field.name: getattr(args, field.name) for field, _ in self._fields
                 if getattr(args, field.name, None) is not None}
        return build(self.cls, given, self.where)

    def argv(self, config: Any) -> list[str]:
        """The options that reproduce ``config`` (None and empty lists left out: they can
        only be the default)."""
        out: list[str] = []
        for field, _ in self._fields:
            value = getattr(config, field.name)
            if isinstance(value, (list, tuple)):
                out += [_flag(field.name), *map(str, value)] if value else []
            elif value is not None:
                out.append(self._spelled(field.name, value))
        return out

    def _spelled(self, name: str, value: Any) -> str:
        """One scalar option as written on the command line (an alias where one sets it)."""
        alias = [flag for flag, target in self.aliases.items() if target == (name, value)]
        return alias[0] if alias else _generated(name, value)

    def _parsing(self, field: dataclasses.Field, kind: Any) -> dict[str, Any]:
        """argparse's type, nargs, action and choices for a field of type ``kind``."""
        origin, items = typing.get_origin(kind) or kind, typing.get_args(kind)
        if origin is bool:
            return {"action": argparse.BooleanOptionalAction}
        if origin in (list, tuple):
            fixed = origin is tuple and items and Ellipsis not in items
            return {"nargs": len(items) if fixed else "+", "type": items[0] if items else str}
        choices = allowed_choices(field.metadata)
        return {"type": origin,
                "choices": None if choices is None else [c for c in choices if c is not None]}

    def _help(self, field: dataclasses.Field) -> str:
        meta = field.metadata
        notes = [] if field.name in self.required else [f"default {_shown(_default(field))}"]
        if meta.get("choices") is not None or meta.get("low") is not None \
                or meta.get("high") is not None:
            notes.append(allowed_text(meta))
        return f"{meta.get('doc', '')} ({'; '.join(notes)})" if notes else meta.get("doc", "")
