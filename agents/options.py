"""Command lines generated from configuration dataclasses, so that every option is written once.

A field's type says how it parses (``Literal[...]``: a choice; ``bool``: a switch, ``--no-NAME``
when it defaults to True; ``tuple``/``list``: several values), the string under it is its help,
and ``metadata`` (see :func:`option`) covers the few fields whose flag or value needs more.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import json
import textwrap
import types
import typing
from typing import Any, Literal

__all__ = ["option", "field_docs", "choices_of", "check_choices", "add_options", "options_from_args", "to_argv"]


def option(default: Any = dataclasses.MISSING, *, default_factory: Any = dataclasses.MISSING, **cli) -> Any:
    """A dataclass field with how its command-line option differs from what its type implies:
    ``flag`` (its spelling), argparse's ``nargs``, ``type``, ``action``, ``metavar``, ``const`` or
    ``choices``, and ``convert`` (parsed value -> field value; it must also accept a field value)."""
    return dataclasses.field(default=default, default_factory=default_factory, metadata={"cli": cli})


def field_docs(cls: type) -> dict[str, str]:
    """The string written under each field of dataclass ``cls`` (whitespace folded), by field name."""
    body = ast.parse(textwrap.dedent(inspect.getsource(cls))).body[0].body
    return {node.target.id: " ".join(after.value.value.split()) for node, after in zip(body, body[1:])
            if isinstance(node, ast.AnnAssign) and isinstance(after, ast.Expr)
            and isinstance(getattr(after.value, "value", None), str)}


def _flag(f: dataclasses.Field, default) -> str:
    """The option's spelling: metadata ``flag``, else --name (a switch on by default: --no-name)."""
    prefix = "--no-" if default is True else "--"
    return f.metadata.get("cli", {}).get("flag") or prefix + f.name.replace("_", "-")


def _unwrap_optional(hint):
    """``X | None`` -> X; anything else unchanged."""
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        if len(args) == 1:
            return args[0]
    return hint


def choices_of(cls: type) -> dict[str, tuple]:
    """The allowed values of every ``Literal[...]`` field of dataclass ``cls``."""
    hints = typing.get_type_hints(cls)
    return {f.name: typing.get_args(_unwrap_optional(hints[f.name])) for f in dataclasses.fields(cls)
            if typing.get_origin(_unwrap_optional(hints[f.name])) is Literal}


def check_choices(config) -> None:
    """ValueError naming the field, the bad value and the allowed ones, for a choice field of the
    dataclass instance ``config`` that holds none of its allowed values."""
    for name, allowed in choices_of(type(config)).items():
        value = getattr(config, name)
        if value not in allowed:
            raise ValueError(f"{type(config).__name__}.{name} must be one of {allowed}, got {value!r}")


def add_options(parser: argparse.ArgumentParser, cls: type, *, groups: dict[str, str] | None = None,
                defaults: dict[str, Any] | None = None) -> None:
    """Add one option per field of dataclass ``cls`` to ``parser`` (dest = the field's name).

    groups: field name -> title of the argument group from that field on (fields in order);
    defaults: values that replace the dataclass defaults on this command line."""
    hints = typing.get_type_hints(cls)
    docs = field_docs(cls)
    target = parser
    for f in dataclasses.fields(cls):
        if groups and f.name in groups:
            target = parser.add_argument_group(groups[f.name])
        cli = dict(f.metadata.get("cli", {}))
        default = (defaults or {}).get(f.name, f.default if f.default is not dataclasses.MISSING else
                                       f.default_factory() if f.default_factory is not dataclasses.MISSING else None)
        hint = _unwrap_optional(hints[f.name])
        cli.pop("flag", None)
        cli.pop("convert", None)
        kwargs: dict[str, Any] = {"dest": f.name, "help": docs.get(f.name, "")}
        if hint is bool:
            kwargs.update(action="store_false" if default else "store_true", default=default)
        else:
            if typing.get_origin(hint) is Literal:
                kwargs.update(choices=list(typing.get_args(hint)))
            elif hint in (int, float, str):
                kwargs.update(type=hint)
            elif typing.get_origin(hint) in (tuple, list):
                kwargs.update(nargs="+", type=typing.get_args(hint)[0])
            kwargs.update(default=default)
            kwargs.update(cli)
            if kwargs.get("action") == "append":
                kwargs["default"] = []
        kwargs["help"] = kwargs["help"].replace("%", "%%")  # argparse formats the help with %
        if kwargs.get("default") is not None and "action" not in kwargs:
            kwargs["help"] += " (default: %(default)s)"
        target.add_argument(_flag(f, default if hint is bool else None), **kwargs)


def options_from_args(cls: type, args: argparse.Namespace, **overrides):
    """An instance of dataclass ``cls`` from the options :func:`add_options` added."""
    hints = typing.get_type_hints(cls)
    values = {}
    for f in dataclasses.fields(cls):
        value = getattr(args, f.name)
        convert = f.metadata.get("cli", {}).get("convert")
        if convert is not None:
            value = convert(value)
        elif value is not None and typing.get_origin(_unwrap_optional(hints[f.name])) is tuple:
            value = tuple(value)
        values[f.name] = value
    return cls(**{**values, **overrides})


def to_argv(cls: type, values: dict[str, Any]) -> list[str]:
    """The command-line options that set ``values`` (field name -> value) of dataclass ``cls``."""
    fields = {f.name: f for f in dataclasses.fields(cls)}
    hints = typing.get_type_hints(cls)
    argv: list[str] = []
    for name, value in values.items():
        f = fields[name]
        if _unwrap_optional(hints[name]) is bool:
            argv += [_flag(f, f.default)] if value != f.default else []
            continue
        flag = _flag(f, None)
        if f.metadata.get("cli", {}).get("action") == "append":
            for key, item in dict(value).items():
                argv += [flag, f"{key}={json.dumps(item) if not isinstance(item, str) else item}"]
        elif isinstance(value, (list, tuple)):
            argv += [flag, *map(str, value)]
        else:
            argv += [flag, f"{value:g}" if isinstance(value, float) else str(value)]
    return argv
