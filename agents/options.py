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
import math
import textwrap
import types
import typing
from typing import Any, Literal

__all__ = ["option", "field_docs", "choices_of", "check_choices", "add_options", "options_from_args", "to_argv",
           "number", "positive_int", "non_negative_int", "positive_float", "non_negative_float", "fraction",
           "SensorSize", "sensor_size_option", "SENSOR_SIZE_HELP"]


def number(kind: type, low: float | None = None, high: float | None = None, *, low_open: bool = False,
           high_open: bool = False, name: str | None = None):
    """An argparse ``type=``: parses ``kind`` (int or float) and refuses NaN, infinity and values
    outside [low, high] (an open end with ``low_open`` / ``high_open``; None: unbounded). argparse
    names the option: ``argument --dt-ratio: expected a finite number > 0, got nan``.

    name: how the accepted values read in the message (default: built from the range)."""
    noun = "an integer" if kind is int else "a finite number"
    bounds = [f"{'>' if low_open else '>='} {low:g}" if low is not None else "",
              f"{'<' if high_open else '<='} {high:g}" if high is not None else ""]
    if name is None:
        name = f"{noun} {' and '.join(b for b in bounds if b)}".strip()

    def parse(text: str):
        try:
            value = kind(text)
        except (TypeError, ValueError):
            raise argparse.ArgumentTypeError(f"expected {name}, got {text!r}") from None
        inside = (math.isfinite(value) and (low is None or (value > low if low_open else value >= low))
                  and (high is None or (value < high if high_open else value <= high)))
        if not inside:
            raise argparse.ArgumentTypeError(f"expected {name}, got {value!r}")
        return value

    parse.__name__ = name  # argparse's own messages name the type
    return parse


#: the numeric option types of the commands (agents/commands), each naming its accepted range
positive_int = number(int, 1, name="a positive integer")
non_negative_int = number(int, 0, name="an integer >= 0")
positive_float = number(float, 0, low_open=True, name="a finite number > 0")
non_negative_float = number(float, 0, name="a finite number >= 0")
fraction = number(float, 0, 1, high_open=True, name="a fraction in [0, 1)")


class SensorSize(argparse.Action):
    """``--sensor-size H W`` (pixels, stored as the tuple (H, W)) or ``--sensor-size auto`` (stored
    as "auto": the readers pick the smallest known sensor holding every event, and warn); anything
    else is refused by argparse, naming the option."""

    def __init__(self, option_strings, dest, nargs=None, **kwargs) -> None:
        kwargs.setdefault("metavar", "SIZE")  # argparse shows "SIZE [SIZE ...]": the help says "H W or auto"
        super().__init__(option_strings, dest, nargs="+", **kwargs)

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        from envs.events import MAX_SENSOR_SIDE

        if list(values) == ["auto"]:
            setattr(namespace, self.dest, "auto")
            return
        if len(values) != 2 or not all(v.isdigit() and 0 < int(v) <= MAX_SENSOR_SIDE for v in values):
            raise argparse.ArgumentError(self, f"expected H W (whole pixels in [1, {MAX_SENSOR_SIDE}], height "
                                               f"first) or 'auto', got {' '.join(values)!r}")
        setattr(namespace, self.dest, (int(values[0]), int(values[1])))


def sensor_size_option() -> Any:
    """The ``sensor_size`` field of a command's options (:class:`SensorSize`): None (the files'
    own geometry), (H, W) or "auto"; handed to the readers as ``data_options``."""
    return option(None, action=SensorSize)


#: the help of every command's --sensor-size
SENSOR_SIZE_HELP = ("H W (pixels, height first) or auto: the sensor size of recordings whose header gives none "
                    "(Prophesee RAW / DAT, text); auto: the smallest known sensor holding every event, with a "
                    "warning; files that store their geometry keep it")


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
