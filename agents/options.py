"""Command lines generated from configuration dataclasses, so that every option is written once.

Every command (evflow_cli/commands) describes its options as a dataclass and builds its parser with
:func:`command_parser` (or :func:`add_options`); tests/test_options.py checks that no command adds
an option by hand. A field's type says how it parses (``Literal[...]``: a choice; ``bool``: a
switch, ``--no-NAME`` when it defaults to True; ``tuple``/``list``: several values; ``Path``: a
path), the string under it is its help, and ``metadata`` (see :func:`option`) covers the few fields
whose flag or value needs more: another spelling kept working (``aliases``), a positional
argument, a group of options of which one at most is given (``exclusive``), a value check.

Option groups that several commands share are dataclasses written once at the bottom of this
module (:class:`Windows`, :class:`RecordingOptions`, :class:`DeviceOptions`); a command's options
inherit them and ``--help`` shows each under its own heading.

Why our own ~300 lines over argparse rather than a library made for this (tyro, simple-parsing,
both installable): the project's validation is argparse's (``type=`` checks that name the option,
exit status 2, the one-line errors of evflow_cli/commands/cli.py, the ``SensorSize`` action) and its
users' scripts rely on the exact spellings (``--no-flips``, ``--model-kwarg``, ``--dt``); train.py's
``--preset`` and ``--resume`` read the parser's actions and defaults (``given_options``); and the
dependencies are kept to the numerical stack (a library would bring its own, and its own
spellings and error format, for what these functions already do).
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import json
import math
import os
import sys
import textwrap
import types
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from envs.readers.detect import FORMATS

__all__ = ["option", "field_docs", "choices_of", "check_choices", "add_options", "options_from_args", "to_argv",
           "command_parser", "parse_options", "OPTION_FIELD", "one_or_list", "default_device",
           "number", "positive_int", "non_negative_int", "positive_float", "non_negative_float", "fraction", "keep_fraction",
           "SensorSize", "sensor_size_option",
           "model_width", "WindowSize", "Windows", "SensorSizeOptions", "RecordingOptions", "ModelWidth", "Progress",
           "DeviceOptions"]


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


def torch_device(text: str) -> str:
    """``--device``: a torch device this machine has (cpu, cuda, cuda:1, mps), else an argparse
    error naming what is missing (not an AssertionError from deep inside torch later)."""
    import torch

    try:
        device = torch.device(text)
    except (RuntimeError, ValueError):
        raise argparse.ArgumentTypeError(f"expected a torch device (cpu, cuda, cuda:1), got {text!r}") from None
    if device.type == "cuda":
        if torch.version.cuda is None or not torch.cuda.is_available():
            why = "this torch is built without CUDA" if torch.version.cuda is None else "no CUDA device is visible"
            raise argparse.ArgumentTypeError(f"{text}: {why} (torch {torch.__version__}); use --device cpu")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise argparse.ArgumentTypeError(f"{text}: this machine has {torch.cuda.device_count()} CUDA device(s)")
    elif device.type == "mps" and not torch.backends.mps.is_available():
        raise argparse.ArgumentTypeError(f"{text}: no MPS device on this machine; use --device cpu")
    return text


torch_device.__name__ = "a torch device"

#: the numeric option types of the commands (evflow_cli/commands), each naming its accepted range
positive_int = number(int, 1, name="a positive integer")
non_negative_int = number(int, 0, name="an integer >= 0")
positive_float = number(float, 0, low_open=True, name="a finite number > 0")
non_negative_float = number(float, 0, name="a finite number >= 0")
fraction = number(float, 0, 1, high_open=True, name="a fraction in [0, 1)")
keep_fraction = number(float, 0, 1, low_open=True, name="a fraction in (0, 1]")


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


def option(default: Any = dataclasses.MISSING, *, default_factory: Any = dataclasses.MISSING, **cli) -> Any:
    """A dataclass field with how its command-line option differs from what its type implies:
    ``flag`` (its spelling), ``aliases`` (more spellings that keep working, e.g. a former name),
    ``positional=True`` (an argument without a flag), ``exclusive`` (a name: at most one option of
    the fields that share it may be given; with ``required=True`` on one of them, exactly one),
    argparse's ``nargs``, ``type``, ``action``, ``metavar``, ``const``, ``choices`` or ``required``,
    and ``convert`` (parsed value -> field value; it must also accept a field value)."""
    return dataclasses.field(default=default, default_factory=default_factory, metadata={"cli": cli})


def _own_field_docs(cls: type) -> dict[str, str]:
    body = ast.parse(textwrap.dedent(inspect.getsource(cls))).body[0].body
    return {node.target.id: " ".join(after.value.value.split()) for node, after in zip(body, body[1:])
            if isinstance(node, ast.AnnAssign) and isinstance(after, ast.Expr)
            and isinstance(getattr(after.value, "value", None), str)}


def field_docs(cls: type) -> dict[str, str]:
    """The string written under each field of dataclass ``cls`` or of the dataclasses it inherits
    (whitespace folded), by field name; a field declared again without a string keeps its base's."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if "__dataclass_fields__" in vars(klass):
            docs.update(_own_field_docs(klass))
    return docs


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


#: the attribute :func:`add_options` sets on each argparse action it adds: the name of its field
#: (tests/test_options.py: every option of every command comes from a field)
OPTION_FIELD = "option_field"


def _shared_group(cls: type, name: str) -> str | None:
    """The ``GROUP`` title of the shared option group (a base dataclass of ``cls``) that declares
    field ``name``; None for a field ``cls`` declares itself."""
    for klass in cls.__mro__:
        if name in vars(klass).get("__annotations__", {}):
            return None if klass is cls else vars(klass).get("GROUP")
    return None


def _argument_kwargs(f: dataclasses.Field, hint, default, help: str) -> dict[str, Any]:
    """``add_argument``'s keywords for field ``f`` of type ``hint`` (Optional unwrapped) with
    ``default``: the dest, the help (its default appended), a flag's action or the type,
    choices and nargs the type implies, then the field's own ``cli`` settings."""
    cli = dict(f.metadata.get("cli", {}))
    for key in ("flag", "convert", "aliases", "positional", "exclusive"):
        cli.pop(key, None)
    kwargs: dict[str, Any] = {"dest": f.name, "help": help}
    if hint is bool:
        kwargs.update(action="store_false" if default else "store_true", default=default)
    else:
        if typing.get_origin(hint) is Literal:
            kwargs.update(choices=list(typing.get_args(hint)))
        elif hint in (int, float, str, Path):
            kwargs.update(type=hint)
        elif typing.get_origin(hint) in (tuple, list):
            item = typing.get_args(hint)[0]
            if typing.get_origin(item) is Literal:
                kwargs.update(nargs="+", choices=list(typing.get_args(item)))
            else:
                kwargs.update(nargs="+", type=item)
        kwargs.update(default=default)
        kwargs.update(cli)
        if kwargs.get("action") == "append":
            kwargs["default"] = []
    kwargs["help"] = kwargs["help"].replace("%", "%%")  # argparse formats the help with %
    shown = kwargs.get("default")
    if "action" not in kwargs and shown is not None and not (isinstance(shown, (str, list, tuple)) and not shown):
        shown = " ".join(map(str, shown)) if isinstance(shown, (list, tuple)) else str(shown)
        kwargs["help"] += f" (default: {shown.replace('%', '%%')})"
    return kwargs


def add_options(parser: argparse.ArgumentParser, cls: type, *, groups: dict[str, str] | None = None,
                defaults: dict[str, Any] | None = None) -> None:
    """Add one option per field of dataclass ``cls`` to ``parser`` (dest = the field's name): the
    fields ``cls`` declares in their order, then each shared group it inherits (a base dataclass
    with a ``GROUP`` title) under its title.

    groups: field name -> title of the argument group from that field on (``cls``'s own fields, in
    order); defaults: values that replace the dataclass defaults on this command line."""
    hints = typing.get_type_hints(cls)
    docs = field_docs(cls)
    own, shared = [], {}
    for f in dataclasses.fields(cls):
        title = _shared_group(cls, f.name)
        (own if title is None else shared.setdefault(title, [])).append(f)
    placed = [(f, groups[f.name] if groups and f.name in groups else None) for f in own]
    # the groups in the order the bases are written (dataclasses collect the last base's fields first)
    placed += [(f, title if i == 0 else None) for title, members in reversed(shared.items())
               for i, f in enumerate(members)]
    target = parser
    titled: dict[str, Any] = {}  # a shared group titled as one of the command's own joins it
    exclusive: dict[str, Any] = {}
    for f, title in placed:
        if title is not None:
            if title not in titled:
                titled[title] = parser.add_argument_group(title)
            target = titled[title]
        default = (defaults or {}).get(f.name, f.default if f.default is not dataclasses.MISSING else
                                       f.default_factory() if f.default_factory is not dataclasses.MISSING else None)
        hint = _unwrap_optional(hints[f.name])
        meta = f.metadata.get("cli", {})
        kwargs = _argument_kwargs(f, hint, default, docs.get(f.name, ""))
        container = target
        if "exclusive" in meta:
            if meta["exclusive"] not in exclusive:
                exclusive[meta["exclusive"]] = target.add_mutually_exclusive_group()
            container = exclusive[meta["exclusive"]]
            container.required = container.required or bool(kwargs.pop("required", False))
        if meta.get("positional"):
            del kwargs["dest"]
            action = container.add_argument(f.name, **kwargs)
        else:
            action = container.add_argument(_flag(f, default if hint is bool else None), *meta.get("aliases", ()),
                                             **kwargs)
        setattr(action, OPTION_FIELD, f.name)


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


def command_parser(cls: type, description: str | None = None, *, epilog: str | None = None,
                   groups: dict[str, str] | None = None, defaults: dict[str, Any] | None = None,
                   parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    """A command's parser: one option per field of dataclass ``cls`` (:func:`add_options`), the
    command's docstring as its description and ``epilog`` below the options, both as written
    (their examples keep their lines). parser: a parser to fill instead (a subcommand's)."""
    if parser is None:
        parser = argparse.ArgumentParser(description=description, epilog=epilog,
                                         formatter_class=argparse.RawDescriptionHelpFormatter)
    add_options(parser, cls, groups=groups, defaults=defaults)
    return parser


def load_config(path: str | os.PathLike) -> dict[str, Any]:
    """A run config file as a dict: JSON (a run's own ``config.json``) or TOML (``.toml``).
    Keys may use - or _ (``window-size`` = ``window_size``); keys starting with _ are notes (a
    run's provenance), not options. ValueError naming the file otherwise."""
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as err:
        raise ValueError(f"--config {path}: cannot read it ({err})") from None
    try:
        if path.suffix.lower() == ".toml":
            try:
                import tomllib
            except ModuleNotFoundError:  # Python 3.10
                import tomli as tomllib  # type: ignore[no-redef]
            values = tomllib.loads(text)
        else:
            values = json.loads(text)
    except ModuleNotFoundError:
        raise ValueError(f"--config {path}: TOML needs Python >= 3.11 (or pip install tomli); "
                         "or write the config as JSON") from None
    except ValueError as err:  # JSONDecodeError and TOMLDecodeError are ValueErrors
        raise ValueError(f"--config {path}: not valid {'TOML' if path.suffix.lower() == '.toml' else 'JSON'} ({err})") from None
    if not isinstance(values, dict):
        raise ValueError(f"--config {path}: expected a table of option = value, got {type(values).__name__}")
    return {str(k).replace("-", "_"): v for k, v in values.items() if not str(k).startswith("_")}


def expand_config(parser: argparse.ArgumentParser, argv: list[str] | None) -> list[str]:
    """``argv`` with ``--config FILE`` replaced by the options the file sets, placed first so
    that options given on the command line win. A key that is no option of the command is an
    error naming it (a misspelt key would silently do nothing)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    paths = [argv[i + 1] for i, a in enumerate(argv[:-1]) if a == "--config"] + \
        [a.split("=", 1)[1] for a in argv if a.startswith("--config=")]
    if not paths:
        return argv
    rest, skip = [], False
    for a in argv:
        if skip:
            skip = False
        elif a == "--config":
            skip = True
        elif not a.startswith("--config="):
            rest.append(a)
    actions = {a.dest: a for a in parser._actions if a.option_strings and a.dest != "help"}
    front: list[str] = []
    for path in paths:
        values = load_config(path)
        unknown = sorted(k for k in values if k not in actions or k == "config")
        if unknown:
            raise ValueError(f"--config {path}: {unknown} not options of this command (see --help)")
        for key, value in values.items():
            action, flag = actions[key], max(actions[key].option_strings, key=len)
            if isinstance(action, (argparse._StoreTrueAction, argparse._StoreFalseAction)):
                if bool(value) != bool(action.default):
                    front.append(flag)
            elif value is None or value == action.default or value == {} or (
                    isinstance(value, list) and isinstance(action.default, tuple) and tuple(value) == action.default):
                continue
            elif isinstance(value, (list, tuple)):  # [] for an option taking none or more: the flag alone
                front += [flag, *map(str, value)] if value else [flag] if action.nargs in ("*", "?") else []
            elif isinstance(value, dict):  # KEY=VALUE items (an appending option, e.g. --model-kwarg)
                for k, v in value.items():
                    front += [flag, f"{k}={json.dumps(v)}"]
            else:
                front += [flag, str(value)]
    return front + rest


def parse_options(cls: type, argv: list[str] | None = None, parser: argparse.ArgumentParser | None = None, **kwargs):
    """The options of ``argv`` as an instance of ``cls`` (parsed by ``parser``, default
    ``command_parser(cls, **kwargs)``); a bad option exits as argparse does (status 2)."""
    parser = parser or command_parser(cls, **kwargs)
    if any(f.name == "config" for f in dataclasses.fields(cls)):
        argv = expand_config(parser, argv)
    return options_from_args(cls, parser.parse_args(argv))


def one_or_list(values):
    """Several command-line values as a list, one as itself (a field value passes unchanged)."""
    return values[0] if isinstance(values, list) and len(values) == 1 else values


def model_width(text: str | int) -> str | int:
    """'paper', 'cpu' or an integer base width (given as digits on the command line)."""
    return int(text) if str(text).isdigit() else text


def default_device() -> str:
    """cuda where torch sees a GPU, else cpu: the --device default of the commands that train or evaluate."""
    import torch

    return "cuda" if torch.cuda.is_available() else "cpu"


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


# Option groups shared by the commands: each concept written once. A command's options dataclass
# inherits the groups it takes (fields in a group are keyword arguments like the command's own).


@dataclass
class WindowSize:
    """How long each window is (the unit is the window mode's: :class:`Windows`)."""

    GROUP = "windows"

    window_size: int | list[int] | None = option(None, nargs="+", type=positive_int, convert=one_or_list,
                                                 aliases=("--dt",), metavar="N")
    """the window's length: ground-truth grid steps with --window frames (the paper's dt), microseconds with time, events with count (the env's defaults: 1, 10000, 15000). Several values: train draws one per episode, evaluate writes a table for each (default 1 and 4 where there is ground truth), teacher_targets solves each (default 1 2 3 4); predict takes one"""

    def window_sizes(self) -> list[int] | None:
        """``window_size`` as a list (None: the command's default)."""
        size = self.window_size
        return None if size is None else [size] if isinstance(size, int) else list(size)


@dataclass
class Windows(WindowSize):
    """How the commands cut a recording into windows (envs.windows): the mode and the length."""

    GROUP = "windows"

    window: Literal["frames", "time", "count"] = "frames"
    """how a window is cut: ground-truth frames (a recording without a ground-truth grid: its frame times, else fixed 30 Hz intervals; predict: time windows of --no-gt-window), a time span or an event count"""


@dataclass
class SensorSizeOptions:
    """The reader option of recordings that may not say their sensor size."""

    GROUP = "recordings"

    sensor_size: tuple[int, int] | Literal["auto"] | None = sensor_size_option()
    """H W (pixels, height first) or auto: the sensor size of recordings whose header gives none (Prophesee RAW / DAT, text); auto: the smallest known sensor holding every event, with a warning; files that store their geometry keep it"""

    def data_options(self) -> dict:
        """The reader options every recording of the command opens with (``--sensor-size``)."""
        return {} if self.sensor_size is None else {"sensor_size": self.sensor_size}


@dataclass
class RecordingOptions(SensorSizeOptions):
    """How the commands open recordings (envs.readers)."""

    GROUP = "recordings"

    format: str | None = option(None, choices=FORMATS)
    """force a reader (default: detected from the file)"""


@dataclass
class ModelWidth:
    """The width of a network a command builds from a registry name (a checkpoint or a shipped
    model stores its own)."""

    GROUP = "model"

    width: str | int = option("cpu", type=model_width)
    """'paper' (base width 32), 'cpu' (8) or an integer base width, of a network built from its registry name"""


@dataclass
class Progress:
    """Whether a command draws a progress bar (stderr)."""

    GROUP = "output"

    no_progress: bool = False
    """no progress bar"""


@dataclass
class DeviceOptions:
    """Where the tensors of a command live and how many CPU threads torch uses."""

    GROUP = "device"

    device: str = option("cpu", type=torch_device)
    """torch device: cpu, cuda, cuda:1..."""
    threads: int | None = option(None, type=positive_int)
    """torch CPU threads (default: torch's choice; 1 on a busy machine)"""

    def set_threads(self) -> None:
        """Apply ``--threads`` to torch (no value: leave torch's choice)."""
        if self.threads:
            import torch

            torch.set_num_threads(self.threads)
