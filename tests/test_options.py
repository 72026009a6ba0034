"""agents/options.py: the command lines written from the configuration dataclasses, the choice
checks, the presets, and every console command's --help."""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import re
import subprocess
import sys
from importlib.metadata import EntryPoint
from pathlib import Path

import pytest

from agents.learner import PRESETS, TrainConfig, preset_config, preset_options
from agents.options import OPTION_FIELD, WindowSize, choices_of, field_docs, parse_options
from evflow_cli.commands import train as train_command
from evflow_cli.commands.cli import COMMANDS
from evflow_cli.commands.evaluate import EvaluateOptions

ROOT = Path(__file__).resolve().parents[1]


def console_commands() -> dict[str, str]:
    """[project.scripts] of pyproject.toml: command -> module:function."""
    text = (ROOT / "pyproject.toml").read_text()
    section = text.split("[project.scripts]", 1)[1].split("\n[", 1)[0]
    return dict(re.findall(r'^(\S+) = "([^"]+)"', section, flags=re.M))


@pytest.mark.parametrize("cls, name", [(cls, name) for cls in (TrainConfig, EvaluateOptions)
                                        for name in sorted(choices_of(cls))])
def test_a_bad_value_of_every_choice_field_raises_naming_the_field_and_the_allowed_values(cls, name):
    with pytest.raises(ValueError) as err:
        cls(**{name: "nonsense"})
    message = str(err.value)
    assert f"{cls.__name__}.{name}" in message and "'nonsense'" in message
    assert all(repr(value) in message for value in choices_of(cls)[name])


def test_every_choice_field_is_a_literal_and_every_field_has_its_help():
    assert {"loss", "loss_mode", "vector", "decay", "input", "window", "teacher_pixels"} <= set(choices_of(TrainConfig))
    for cls in (TrainConfig, EvaluateOptions, WindowSize):
        docs = field_docs(cls)
        assert all(docs.get(name) for name in cls.__dataclass_fields__), set(cls.__dataclass_fields__) - set(docs)


def command_modules() -> list[str]:
    """Every command of evflow_cli/commands: the console commands (cli.COMMANDS) and every module a
    scripts/ file runs."""
    names = set(COMMANDS.values())
    for script in (ROOT / "scripts").glob("*.py"):
        names |= set(re.findall(r"from evflow_cli\.commands\.(\w+) import [\w, ]*\bmain\b", script.read_text()))
    return sorted(names)


def parser_actions(parser: argparse.ArgumentParser):
    """Every option and argument of ``parser`` and of its subcommands' parsers, -h aside."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for subparser in action.choices.values():
                yield from parser_actions(subparser)
        elif not isinstance(action, argparse._HelpAction):
            yield action


@pytest.mark.parametrize("name", command_modules())
def test_every_command_builds_its_parser_from_an_options_dataclass(name, capsys):
    """One mechanism: each option of each command is a field of its options dataclass, added by
    agents.options.add_options (which marks the action with its field), with the help written
    under the field; none is added by hand."""
    module = importlib.import_module(f"evflow_cli.commands.{name}")
    actions = list(parser_actions(module.build_parser()))
    assert actions, name
    for action in actions:
        assert getattr(action, OPTION_FIELD, None) == action.dest, f"{name}: {action.option_strings or action.dest}"
        assert action.help, f"{name}: {action.option_strings or action.dest} has no help"
    with pytest.raises(SystemExit) as stop:
        module.main(["--help"])
    assert stop.value.code == 0 and "usage:" in capsys.readouterr().out


def test_the_window_length_has_one_name_across_the_commands(tmp_path):
    """--window-size (frames per window with --window frames; --dt, the paper's name, is the same
    option) in train, evaluate, predict and teacher_targets, declared once (agents.options.WindowSize)."""
    from evflow_cli.commands import campaign, evaluate, predict, teacher_targets

    for module in (train_command, evaluate, predict, teacher_targets):
        parser = module.build_parser()
        flags = [action.option_strings for action in parser._actions if action.dest == "window_size"]
        assert flags == [["--window-size", "--dt"]], (module.__name__, flags)
        assert {"dt", "window_sizes"}.isdisjoint(action.dest for action in parser._actions)
    for name in command_modules():
        for cls in vars(importlib.import_module(f"evflow_cli.commands.{name}")).values():
            if isinstance(cls, type) and dataclasses.is_dataclass(cls) and cls is not WindowSize \
                    and "window_size" in cls.__dataclass_fields__:
                assert "window_size" not in vars(cls).get("__annotations__", {}), f"{cls.__name__} declares it again"
                assert issubclass(cls, WindowSize)
    assert "window_size" not in vars(TrainConfig).get("__annotations__", {}) and issubclass(TrainConfig, WindowSize)

    evaluate_options = parse_options(evaluate.EvaluateOptions, ["--dt", "1", "4"], evaluate.build_parser())
    assert evaluate_options.window_sizes() == [1, 4] == parse_options(
        evaluate.EvaluateOptions, ["--window-size", "1", "4"], evaluate.build_parser()).window_sizes()
    assert train_command.config_from_args(train_command.parse_args(["--dt", "1", "2"])).window_size == [1, 2]
    assert parse_options(teacher_targets.TeacherTargetsOptions, ["--out", "t.h5", "--window-size", "2"],
                         teacher_targets.build_parser()).window_sizes() == [2]
    assert parse_options(predict.PredictOptions, ["rec.h5", "--window", "time", "--window-size", "5000"],
                         predict.build_parser()).window_size == 5000
    parsed = campaign.build_parser().parse_args(["new", "c", "--export", "m", "--val-dt", "2"])
    assert parsed.val_window_size == [2]


def test_predict_takes_one_window_size(capsys):
    from evflow_cli.commands import predict

    with pytest.raises(SystemExit) as stop:
        predict.main(["rec.h5", "--window-size", "1", "4"])
    assert stop.value.code == 2 and "--window-size: predict runs one window size, got 1 4" in capsys.readouterr().err


def test_old_spellings_keep_working_and_numbers_are_checked(capsys):
    """Options renamed or newly checked by the move to option dataclasses: the old spelling still
    parses; a bad number is refused naming the option, as everywhere else."""
    from evflow_cli.commands import generate, teacher_targets

    with pytest.raises(SystemExit):
        teacher_targets.build_parser().parse_args(["--out", "t.h5", "--batch-size", "0"])
    assert "argument --batch-size: expected a positive integer, got 0" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        generate.build_parser().parse_args(["--split", "synthetic-mini"])
    assert "one of the arguments --out --cache is required" in capsys.readouterr().err
    options = generate.parse_args(["--split", "synthetic-mini", "--cache"])
    assert options.cache and options.out is None and options.format == "evflow-h5"


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_a_preset_spelled_out_as_options_is_the_preset(name):
    spelled = train_command.config_from_args(train_command.parse_args(preset_options(name)))
    assert spelled == train_command.config_from_args(train_command.parse_args(["--preset", name]))
    assert spelled == preset_config(name, device=spelled.device)


def test_the_command_line_keeps_its_spellings():
    args = train_command.parse_args(["--no-flips", "--model-kwarg", "use_st_convgru=false", "--data", "a", "b",
                                     "--window-size", "2", "--crop", "8", "8", "--width", "16", "--teacher-grids", "2"])
    cfg = train_command.config_from_args(args)
    assert cfg.flips is False and cfg.model_kwargs == {"use_st_convgru": False} and cfg.data == ["a", "b"]
    assert cfg.window_size == 2 and cfg.crop == (8, 8) and cfg.width == 16 and cfg.teacher_grids == (2,)
    with pytest.raises(SystemExit):
        train_command.parse_args(["--loss", "hmx"])


def test_the_console_commands_are_the_registry():
    """pyproject.toml's [project.scripts] names exactly the commands of cli.COMMANDS, each as
    ``evflow_cli.commands.cli:<module>``, and each module is a command with its ``main``."""
    assert console_commands() == {name: f"evflow_cli.commands.cli:{module}" for name, module in COMMANDS.items()}
    from evflow_cli.commands import cli

    for name, value in console_commands().items():  # resolved as an installer's script resolves it
        module = COMMANDS[name]
        assert callable(importlib.import_module(f"evflow_cli.commands.{module}").main), module
        assert EntryPoint(name, value, "console_scripts").load().__name__ == module and module in dir(cli)
    with pytest.raises(AttributeError):
        cli.bench_update  # a module of evflow_cli/commands that is no console command  # noqa: B018


@pytest.mark.parametrize("command", sorted(console_commands()))
def test_every_console_command_prints_its_help(command, capsys):
    module, function = console_commands()[command].split(":")
    with pytest.raises(SystemExit) as stop:
        getattr(importlib.import_module(module), function)(["--help"])
    assert stop.value.code == 0 and "usage:" in capsys.readouterr().out


def test_the_scripts_still_run_as_files():
    for script in ("train", "evaluate", "predict", "convert", "generate_synthetic", "benchmark", "teacher_targets", "ship",
                   "export_model", "ablations", "main", "param_counts"):
        out = subprocess.run([sys.executable, str(ROOT / "scripts" / f"{script}.py"), "--help"], capture_output=True,
                             text=True, check=True).stdout
        assert out.startswith("usage:"), script


def test_loss_weights_name_the_loss_they_serve():
    from losses import LossWeights

    weights = LossWeights(lambda_1=0.5)
    assert weights.of("hmc")["lambda_1"] == 0.5 and "lambda_1" not in weights.of("at")
    with pytest.raises(ValueError, match=r"loss must be one of \('hmc', 'at'\), got 'hmx'"):
        weights.of("hmx")
    assert TrainConfig(lambda_2=0.1).weights.lambda_2 == 0.1


def test_every_default_of_the_loss_spec_is_the_specs_own():
    """The loss's defaults are written once, in LossSpec (the contrast-maximisation solver's
    once, in CMAX_WEIGHTS): every function and config that takes them defaults to those values,
    and the env's keywords default to None, the spec's."""
    import inspect

    from agents.cmax import CMaxSettings
    from agents.teacher import TeacherSettings
    from envs.env import EventFlowEnv
    from losses import CMAX_WEIGHTS, LossSpec, LossWeights, accumulated_hmc_loss, at_loss, hmc_loss

    paper = LossSpec()
    assert LossWeights is LossSpec
    assert (paper.lambda_1, paper.lambda_2, paper.alpha, paper.loss) == (1.0, 1e-3, 0.6, "hmc")  # eq. 17's values
    for fn in (hmc_loss, at_loss, accumulated_hmc_loss):
        defaults = inspect.signature(fn).parameters
        for name in ("lambda_1", "lambda_2", "alpha", "border_ramp"):
            if name in defaults:
                assert defaults[name].default == getattr(paper, name), (fn, name)
    env_defaults = inspect.signature(EventFlowEnv).parameters
    for name in ("loss", "lambda_1", "lambda_2", "alpha", "border_penalty", "border_ramp", "loss_spec"):
        assert env_defaults[name].default is None, name
    assert TrainConfig().loss_spec == TrainConfig().weights == paper == EventFlowEnv("synthetic-mini").loss_spec
    assert (PRESETS["paper"]["lambda_1"], PRESETS["paper"]["lambda_2"]) == (paper.lambda_1, paper.lambda_2)
    assert CMAX_WEIGHTS == LossSpec(lambda_2=1e-2)
    assert CMaxSettings().loss_spec == TeacherSettings().loss_spec == CMaxSettings().weights == CMAX_WEIGHTS
    assert TrainConfig().teacher_lambda_2 == CMAX_WEIGHTS.lambda_2
