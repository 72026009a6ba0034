"""The ablation switches change exactly what they name, and the ablation runner resumes and
skips (evflow_cli/ablations.py, scripts/ablations.py)."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import sys
import time
from pathlib import Path

import pytest
import torch

from agents.layers import ConvGRU, STConvGRU
from agents.registry import make_model
from agents.teacher import TeacherSettings
from evflow_cli.ablations import CONFIGURATIONS, AblationRunner, Budget, RunnerStopped, needs_second_seed, read_rows

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))

import train as train_script  # noqa: E402

HEIGHT, WIDTH = 32, 48


def tiny(**switches) -> torch.nn.Module:
    torch.manual_seed(0)
    return make_model("ev-mgrflownet", base_width=2, in_channels=2, flow_scaling=8.0, **switches).eval()


def windows(n: int = 2) -> list[torch.Tensor]:
    generator = torch.Generator().manual_seed(1)
    return [(torch.rand(1, 2, HEIGHT, WIDTH, generator=generator) < 0.2).float() * 3 for _ in range(n)]


def parameter_shapes(model: torch.nn.Module) -> dict[str, tuple]:
    return {name: tuple(p.shape) for name, p in model.named_parameters()}


# -- without prior flows -----------------------------------------------------------------------

def test_without_prior_flows_the_decoder_is_fed_nothing_and_ignores_the_previous_flow():
    ablated = tiny(use_prior_flow=False)
    priors = []
    ablated.decoder.register_forward_pre_hook(lambda module, args: priors.append(args[2]))
    first, second = windows()
    with torch.no_grad():
        _, state = ablated(first, None)
        assert "prior_flow" not in state  # nothing of the previous flow is carried
        plain, _ = ablated(second, state)
        planted, _ = ablated(second, {**state, "prior_flow": 5 * torch.randn(1, 2, HEIGHT, WIDTH)})
    assert priors == [None, None, None]  # the FGD input is the fresh sequence's: zero
    assert ablated.decoder.refiners is None  # u_l = uhat_l
    for a, b in zip(plain, planted):
        assert torch.equal(a, b)


def test_the_full_model_uses_the_previous_flow():
    full = tiny()
    first, second = windows()
    with torch.no_grad():
        _, state = full(first, None)
        carried, _ = full(second, state)
        planted, _ = full(second, {**state, "prior_flow": 5 * torch.randn(1, 2, HEIGHT, WIDTH)})
    assert not torch.allclose(carried[-1], planted[-1])


def test_without_prior_flows_only_the_decoder_refiners_go():
    full, ablated = tiny(), tiny(use_prior_flow=False)
    full_shapes, ablated_shapes = parameter_shapes(full), parameter_shapes(ablated)
    assert set(ablated_shapes) < set(full_shapes)
    assert all(name.startswith("decoder.refiners.") for name in set(full_shapes) - set(ablated_shapes))
    assert all(full_shapes[name] == shape for name, shape in ablated_shapes.items())
    # same weights where they share them: the encoder's states are the same window after window
    missing, unexpected = ablated.load_state_dict(full.state_dict(), strict=False)
    assert not missing and all(name.startswith("decoder.refiners.") for name in unexpected)
    full_state, ablated_state = None, None
    with torch.no_grad():
        for x in windows(3):
            _, full_state = full(x, full_state)
            _, ablated_state = ablated(x, ablated_state)
            assert set(full_state) - set(ablated_state) == {"prior_flow"}
            for key in ablated_state:
                torch.testing.assert_close(ablated_state[key], full_state[key])


# -- without ST-ConvGRU ------------------------------------------------------------------------

def test_without_st_convgru_the_spatio_temporal_memory_path_is_absent():
    full, ablated = tiny(), tiny(use_st_convgru=False)
    assert isinstance(full.grus[0], STConvGRU) and full.deep_memory_up is not None
    assert type(ablated.grus[0]) is ConvGRU and ablated.deep_memory_up is None
    full_shapes, ablated_shapes = parameter_shapes(full), parameter_shapes(ablated)
    changed = (set(full_shapes) ^ set(ablated_shapes)) | {n for n in set(full_shapes) & set(ablated_shapes)
                                                           if full_shapes[n] != ablated_shapes[n]}
    assert changed and all(name.startswith(("grus.0.", "deep_memory_up.")) for name in changed)
    assert not any(name.startswith(("grus.0.gru_deep", "deep_memory_up")) for name in ablated_shapes)
    module1 = {}  # F1, module 1's output (the first skip), of the last call
    full.grus[0].register_forward_hook(lambda m, args, out: module1.__setitem__("full", out[0]))
    ablated.grus[0].register_forward_hook(lambda m, args, out: module1.__setitem__("ablated", out))
    with torch.no_grad():
        first, second = windows()
        _, full_state = full(first, None)
        _, ablated_state = ablated(first, None)
        assert set(full_state) == set(ablated_state) == {"encoder1", "encoder2", "encoder3", "encoder4", "prior_flow"}
        # module 1's output F1 depends on the deepest memory S4 only through the M path (eqs. 5-6)
        other_deep = {"encoder4": 3 * torch.randn_like(full_state["encoder4"])}
        outputs = {}
        for name, model, state in (("full", full, full_state), ("ablated", ablated, ablated_state)):
            model(second, state)
            carried = module1[name]
            model(second, {**state, **other_deep})
            outputs[name] = (carried, module1[name])
    assert not torch.allclose(*outputs["full"])
    assert torch.equal(*outputs["ablated"])


def test_without_st_convgru_the_prior_flow_stays():
    ablated = tiny(use_st_convgru=False)
    first, second = windows()
    with torch.no_grad():
        _, state = ablated(first, None)
        carried, _ = ablated(second, state)
        planted, _ = ablated(second, {**state, "prior_flow": 5 * torch.randn(1, 2, HEIGHT, WIDTH)})
    assert not torch.allclose(carried[-1], planted[-1])


def test_the_configurations_name_their_switches():
    assert CONFIGURATIONS["mgr-no-st"].model_kwargs == {"use_st_convgru": False}
    assert CONFIGURATIONS["mgr-no-prior"].model_kwargs == {"use_prior_flow": False}
    assert CONFIGURATIONS["mgr-no-both"].model_kwargs == {"use_st_convgru": False, "use_prior_flow": False}
    for name, config in CONFIGURATIONS.items():  # every configuration builds with its switches
        model = make_model(config.model, base_width=2, in_channels=5, **config.model_kwargs)
        for key, value in config.model_kwargs.items():
            assert getattr(model, key) is value, name
    with pytest.raises(ValueError, match="Configuration.loss"):
        type(CONFIGURATIONS["mgr-hmc"])("x", "x", "ev-flownet", "supervised")


# -- seeds -------------------------------------------------------------------------------------

def test_a_second_seed_where_the_difference_is_within_two_standard_deviations():
    full = [1.0, 1.1, 0.9]  # mean 1.0, sample std 0.1
    assert needs_second_seed([1.15], full)
    assert needs_second_seed([0.81], full)
    assert not needs_second_seed([1.25], full)
    assert not needs_second_seed([0.7], full)
    assert not needs_second_seed([1.0, 1.0], full)  # has its second seed
    with pytest.raises(ValueError):
        needs_second_seed([1.0], [1.0])


# -- the runner --------------------------------------------------------------------------------

TINY = Budget(teacher_steps=3, finetune_steps=2, train_data="synthetic-mini", val_data="synthetic-mini", val_every=2,
              val_windows=2, eval_splits=("synthetic-mini",), eval_dts=(1,), eval_windows=2, width=2, crop=32,
              num_envs=2, unroll=2, teacher_window_sizes=(1,), finetune_window_sizes=(1,),
              teacher=TeacherSettings(grids=(2,), steps=2), cost_size=(32, 32))


def test_the_runner_resumes_a_killed_configuration_and_skips_finished_ones(tmp_path):
    calls: list[list[str]] = []

    def killed_after_one_step(argv):
        calls.append(argv)
        return train_script.main([*argv, "--minutes", "0"])  # stops (and saves) after its first step

    def train(argv):
        calls.append(argv)
        return train_script.main(argv)

    out = tmp_path / "ablations"
    report = tmp_path / "results.md"
    report.write_text("# Results\n\nkept text\n")
    runner = AblationRunner(out, TINY, killed_after_one_step, seeds=(0,), only=["mgr-hmc"], log=lambda _: None)
    with pytest.raises(RunnerStopped, match="step 1 of 3"):
        runner.run(report)
    teacher = out / "mgr-hmc-s0" / "teacher"
    assert (teacher / "checkpoint.pt").exists() and not (teacher / "done.json").exists()
    assert read_rows(out / "rows.jsonl") == []

    calls.clear()
    runner = AblationRunner(out, TINY, train, seeds=(0,), only=["mgr-hmc"], log=lambda _: None)
    rows = runner.run(report)
    assert calls[0][0] == "--resume" and "--init" in calls[1]  # continued, then the fine-tuning stage
    steps = [json.loads(line)["step"] for line in (teacher / "metrics.jsonl").read_text().splitlines()
             if "loss" in json.loads(line)]
    assert steps == [1, 2, 3]  # each step once: resumed from step 1, not restarted
    assert [(r["config"], r["seed"]) for r in rows] == [("mgr-hmc", 0)]
    row = rows[0]
    assert math.isfinite(row["eval"]["synthetic-mini"]["dt1"]["aee"])
    assert row["parameters"] > 0 and row["gflop_per_window"] > 0 and row["latency_ms"] > 0
    # both stages (the fine-tuning stage's after the teacher's 3 steps); the killed run's step 1 stays
    assert [p[0] for p in row["validation"]] == [1, 2, 3, 5]
    assert (out / "curves" / "mgr-hmc.png").stat().st_size > 0
    text = report.read_text()
    assert "kept text" in text and "Table 2 layout" in text and "EV-MGRFlowNet, L_HMC | 0 |" in text

    calls.clear()
    AblationRunner(out, TINY, train, seeds=(0,), only=["mgr-hmc"], log=lambda _: None).run(report)
    assert calls == []  # finished: nothing trained again
    assert len((out / "rows.jsonl").read_text().splitlines()) == 1
    longer = AblationRunner(out, dataclasses.replace(TINY, teacher_steps=4), train, seeds=(0,), only=["mgr-hmc"])
    with pytest.raises(ValueError, match="another budget .*teacher_steps"):
        longer.run(report)
    assert calls == []
    # L_HMC targets given as L_AT ones (lambda_1 = 0) are refused, naming the difference
    mixed = AblationRunner(out, TINY, train, seeds=(0,), targets={"at": str(out / "targets" / "hmc.h5")})
    with pytest.raises(ValueError, match="lambda_1=1.0"):
        mixed.targets("at")


def test_the_record_outlives_the_run_folder(tmp_path):
    """Rows, budget, tables and curves go to the record folder (the repository's docs/ablations),
    handed to on_row after each row; a new machine (run folder gone) trains nothing already recorded."""
    record, committed = tmp_path / "record", []
    runner = AblationRunner(tmp_path / "run1", TINY, train_script.main, seeds=(0,), only=["mgr-hmc"],
                            log=lambda _: None, record=record, on_row=committed.append)
    runner.run()
    assert [(r["config"], r["seed"]) for r in read_rows(record / "rows.jsonl")] == [("mgr-hmc", 0)]
    assert not (tmp_path / "run1" / "rows.jsonl").exists()
    assert len(committed) == 1 and {f.name for f in committed[0]} == {"rows.jsonl", "budget.json", "tables.md",
                                                                        "mgr-hmc.png"}
    assert all(f.exists() for f in committed[0])

    def train(argv):
        pytest.fail(f"trained again: {argv}")

    again = AblationRunner(tmp_path / "run2", TINY, train, seeds=(0,), only=["mgr-hmc"], log=lambda _: None,
                           record=record, on_row=committed.append)
    assert len(again.run()) == 1 and len(committed) == 1


def test_a_stopped_stage_continues_on_a_fresh_clone_from_the_record(tmp_path, monkeypatch):
    """Like a campaign: a stage stopped on one machine is kept slim in the record
    (RECORD/unfinished/, handed to on_state) and continued by a runner whose run folder is new,
    from its step, with its validation lines; a finished teacher stage kept there is not trained
    (nor its targets needed) again; the row replaces the kept states."""
    from evflow_cli import ablations

    record, kept = tmp_path / "record", []

    def one_step(argv):
        return train_script.main([*argv, "--minutes", "0"])  # stops (and saves) after one step

    first = AblationRunner(tmp_path / "run1", TINY, one_step, seeds=(0,), only=["mgr-hmc"], log=lambda _: None,
                           record=record, on_state=kept.extend)
    with pytest.raises(RunnerStopped, match="step 1 of 3"):
        first.run()
    state = record / "unfinished" / "mgr-hmc-s0-teacher.pt"
    assert kept == [state]
    stored = torch.load(state, weights_only=True)
    assert stored["step"] == 1 and state.stat().st_size < 12 * 2**20  # (this tiny network's fits with its moments)

    calls: list[list[str]] = []

    def train_teacher_then_stop(argv):  # machine 2: the teacher stage to its end, the fine-tuning one step
        calls.append(argv)
        return train_script.main(argv if "--resume" in argv else [*argv, "--minutes", "0"])

    second = AblationRunner(tmp_path / "run2", TINY, train_teacher_then_stop, seeds=(0,), only=["mgr-hmc"],
                            log=lambda _: None, record=record, on_state=kept.extend)
    with pytest.raises(RunnerStopped, match="finetune: stopped at step 1 of 2"):
        second.run()
    teacher = tmp_path / "run2" / "mgr-hmc-s0" / "teacher"
    assert calls[0][0] == "--resume" and "--init" in calls[1]
    lines = [json.loads(line) for line in (teacher / "metrics.jsonl").read_text().splitlines()]
    assert [line["step"] for line in lines if "loss" in line] == [2, 3]  # continued from step 1
    assert [line["step"] for line in lines if "val_aee_model" in line] == [1, 2, 3]  # machine 1's step 1 kept
    assert torch.load(state, weights_only=True)["ablation"]["done"] is True
    assert (record / "unfinished" / "mgr-hmc-s0-finetune.pt").exists()

    def solve(*args, **kwargs):
        pytest.fail("solved the targets of a finished teacher stage")

    monkeypatch.setattr(ablations, "compute_teacher_targets", solve)
    (record / "targets" / "hmc.h5").unlink()  # a finished teacher stage needs no targets
    calls.clear()

    def train(argv):
        calls.append(argv)
        return train_script.main(argv)

    third = AblationRunner(tmp_path / "run3", TINY, train, seeds=(0,), only=["mgr-hmc"], log=lambda _: None,
                           record=record)
    rows = third.run()
    assert len(calls) == 1 and calls[0][0] == "--resume" and "finetune" in calls[0][calls[0].index("--out") + 1]
    assert [p[0] for p in rows[0]["validation"]] == [1, 2, 3, 4, 5]  # both stages, over the three machines
    assert not list((record / "unfinished").glob("*.pt"))  # the row replaces them


def test_a_sigterm_to_the_runner_reaches_its_stage(tmp_path):
    """``kill -TERM`` of the runner (a background run's pid) is passed on to the stage's process, which
    saves and returns, so the runner can keep the stage; before, the runner alone ended and the
    stage trained on unseen. The runner's own handlers are back afterwards."""
    import signal
    import threading

    from evflow_cli.commands.ablations import run_stage

    flag = tmp_path / "stage"
    stage = ("import pathlib, signal, sys, time\n"
             f"p = pathlib.Path({str(flag)!r})\n"
             "signal.signal(signal.SIGTERM, lambda *a: (p.write_text('saved'), sys.exit(0)))\n"
             "p.write_text('ready')\n"
             "time.sleep(20)\n"
             "p.write_text('trained on')\n")
    reached_runner_only = []
    outer = signal.signal(signal.SIGTERM, lambda *a: reached_runner_only.append(True))

    def terminate_when_ready():
        deadline = time.time() + 15
        while time.time() < deadline and not (flag.exists() and flag.read_text() == "ready"):
            time.sleep(0.02)
        os.kill(os.getpid(), signal.SIGTERM)

    try:
        threading.Thread(target=terminate_when_ready, daemon=True).start()
        run_stage([sys.executable, "-c", stage])
        assert flag.read_text() == "saved" and not reached_runner_only
        signal.getsignal(signal.SIGTERM)(signal.SIGTERM, None)  # the handler in place again is the caller's
        assert reached_runner_only == [True]
    finally:
        signal.signal(signal.SIGTERM, outer)


def test_solved_targets_are_kept_in_the_record_and_reused_by_a_new_machine(tmp_path, monkeypatch):
    """Targets solved in the run folder are copied into the record (the same values), handed to
    on_targets; a runner with a new run folder and the same record solves nothing."""
    from agents.teacher import TeacherTargets
    from evflow_cli import ablations

    record, kept = tmp_path / "record", []
    first = AblationRunner(tmp_path / "run1", TINY, train_script.main, seeds=(0,), log=lambda _: None, record=record,
                           on_targets=kept.extend)
    solved = first.targets("hmc")
    assert solved == tmp_path / "run1" / "targets" / "hmc.h5"
    assert kept == [record / "targets" / "hmc.h5"]
    original, copy = TeacherTargets(solved), TeacherTargets(kept[0])
    assert copy.config == original.config and original._index.keys() == copy._index.keys() and len(copy) > 0
    assert all(torch.equal(original._index[key].half().float(), copy._index[key]) for key in original._index)
    assert copy._index[next(iter(copy._index))].dtype == torch.float32  # float16 on disk, float32 to the run

    def solve(*args, **kwargs):
        pytest.fail("solved the targets again")

    monkeypatch.setattr(ablations, "compute_teacher_targets", solve)
    second = AblationRunner(tmp_path / "run2", TINY, train_script.main, seeds=(0,), log=lambda _: None, record=record,
                            on_targets=kept.extend)
    assert second.targets("hmc") == record / "targets" / "hmc.h5" and len(kept) == 1
    # the record's copy is checked against the budget like any other file
    other = dataclasses.replace(TINY, teacher=TeacherSettings(grids=(2,), steps=3))
    with pytest.raises(ValueError, match=r"targets/hmc.h5: not the hmc teacher's targets .*steps=2"):
        AblationRunner(tmp_path / "run3", other, train_script.main, seeds=(0,), record=record).targets("hmc")


def test_targets_already_in_the_run_folder_reach_the_record(tmp_path):
    """Solved before the record kept them (or killed before the copy): the next run copies them."""
    import shutil

    record, kept = tmp_path / "record", []
    solved = AblationRunner(tmp_path / "run1", TINY, train_script.main, seeds=(0,), log=lambda _: None).targets("hmc")
    (tmp_path / "run2" / "targets").mkdir(parents=True)
    shutil.copy(solved, tmp_path / "run2" / "targets" / "hmc.h5")
    runner = AblationRunner(tmp_path / "run2", TINY, lambda argv: pytest.fail("trained"), seeds=(0,),
                            log=lambda _: None, record=record, on_targets=kept.extend)
    assert runner.targets("hmc") == tmp_path / "run2" / "targets" / "hmc.h5"
    assert kept == [record / "targets" / "hmc.h5"] and kept[0].exists()
    runner.targets("hmc")
    assert len(kept) == 1  # once


def test_one_runner_per_folder(tmp_path):
    import fcntl

    tmp_path.joinpath("runner.lock").touch()
    with open(tmp_path / "runner.lock", "a") as held:
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        runner = AblationRunner(tmp_path, TINY, lambda argv: pytest.fail("trained"), seeds=(0,), only=["mgr-hmc"])
        with pytest.raises(RuntimeError, match="another ablation runner"):
            runner.run()


def test_the_stages_are_the_recipe_of_main_py():
    """Budget's two stages are scripts/main.py's CACHED_RECIPE and HMC_STAGE, but for what the
    ablations change on purpose: the model and loss of the configuration, the targets file, the
    decaying step size of the teacher stage, its peak (3e-4: at main.py's 1e-3 the decoder's
    first stage died in three of four network ablations) and the step counts."""
    import main as main_script

    def config(argv: list[str]) -> dict:
        return train_script.config_from_args(train_script.parse_args(argv)).to_dict()

    budget = Budget()
    recipe, ours = config(main_script.CACHED_RECIPE), config(budget.teacher_options(Path("targets.h5")))
    differ = {key for key in recipe if recipe[key] != ours[key]}
    assert differ == {"teacher_cache", "steps", "decay", "warmup_steps", "lr"}
    recipe, ours = config(main_script.HMC_STAGE), config(budget.finetune_options("hmc", Path("teacher.pt")))
    assert {key for key in recipe if recipe[key] != ours[key]} == {"steps"}


def test_targets_solved_otherwise_are_refused_even_where_the_recorded_keys_agree(tmp_path):
    """A file solved with the evidence prior (not named by files without it) or derived from
    other windows is not the budget's teacher, though every key the budget names matches."""
    from agents.teacher import compute_teacher_targets, derive_targets

    settings = dataclasses.replace(TINY.teacher, evidence_prior=5.0)
    held = compute_teacher_targets(TINY.train_data, tmp_path / "held.h5", window_sizes=(1, 2), settings=settings,
                                   max_windows=2)
    runner = AblationRunner(tmp_path / "run", TINY, lambda argv: pytest.fail("trained"), seeds=(0,),
                            log=lambda _: None, targets={"hmc": str(held)})
    with pytest.raises(ValueError, match=r"held.h5: not the hmc teacher's targets .*evidence_prior=5.0"):
        runner.targets("hmc")
    plain = compute_teacher_targets(TINY.train_data, tmp_path / "plain.h5", window_sizes=(1, 2),
                                    settings=TINY.teacher, max_windows=2)
    derived = derive_targets(plain, tmp_path / "derived.h5", from_size=2, window_sizes=(1,))
    runner = AblationRunner(tmp_path / "run", TINY, lambda argv: pytest.fail("trained"), seeds=(0,),
                            log=lambda _: None, targets={"hmc": str(derived)})
    with pytest.raises(ValueError, match=r"derived \(not solved with one setting\)"):
        runner.targets("hmc")
    ok = AblationRunner(tmp_path / "run", TINY, lambda argv: pytest.fail("trained"), seeds=(0,),
                        log=lambda _: None, targets={"hmc": str(plain)})
    assert ok.targets("hmc") == plain  # the budget's own settings pass


def test_a_folder_of_recordings_is_a_split_named_by_its_folder_and_read_first():
    """The budget's compass is a folder (../shared/devval): its columns say "devval", and the
    quality columns and the second-seed rule read it, the first split."""
    from evflow_cli.ablations import render_tables

    budget = dataclasses.replace(Budget(), eval_splits=("../shared/devval", "synthetic-test"), eval_dts=(1,))
    assert Budget().val_data == Budget().eval_splits[0] == "../shared/devval"

    def metrics(aee: float) -> dict:
        return {"aee": aee, "outlier_pct": 1.0, "cosine": 0.5, "hmc": 0.8, "fwl": 1.2, "rsat": 0.9}

    zero = {"../shared/devval": {"dt1": metrics(2.3)}, "synthetic-test": {"dt1": metrics(3.1)}}
    row = {"config": "mgr-hmc", "label": CONFIGURATIONS["mgr-hmc"].label, "seed": 0, "parameters": 10,
           "gflop_per_window": 0.1, "latency_ms": 1.0, "validation": [], "date": "2026-12-04",
           "eval": {"../shared/devval": {"dt1": metrics(1.234)}, "synthetic-test": {"dt1": metrics(0.567)}}}
    text = render_tables([row], zero, budget, seeds=(0,))
    assert "| AEE devval dt1 | AEE test dt1 | % out devval dt1 |" in text
    assert "| EV-MGRFlowNet, L_HMC | 0 | 1.234 | 0.567 |" in text
    assert "Seed 0 for every configuration so far" in text and "seed -" not in text  # one seed asked
    two = render_tables([row], zero, budget, seeds=(0, 1))
    assert "Seeds 0, 1 for the full model; the others seed 0, and seed 1 too where their devval dt1 AEE" in two
    rows = [dict(row, seed=seed) for seed in (0, 1)] + [dict(row, config="mgr-at", label="L_AT", seed=seed)
                                                        for seed in (0, 1)]
    every = render_tables(rows, zero, budget, seeds=(0, 1))  # every row ran both: no rule to quote
    assert "Seeds 0, 1 for every configuration." in every and "too where" not in every
    assert "Seeds 0, 1 for every configuration" not in render_tables(rows[:3], zero, budget, seeds=(0, 1))
    third = render_tables(rows + [dict(row, seed=2)], zero, budget, seeds=(0, 1, 2))
    assert "Seeds 0, 1 for every configuration, more where the seeds column lists them." in third
    assert "| EV-MGRFlowNet, L_HMC | 0, 1, 2 |" in third


def test_a_split_named_by_a_path_is_cached_inside_the_evaluation_folder(tmp_path, monkeypatch):
    """"../shared/devval" as a split once cached its scores beside the evaluation folder
    (eval/../shared/devval-dt1.json): a deleted evaluation folder then kept a stale score for one
    window length and recomputed the other. Each split's cache now lies inside the folder, under
    its own name."""
    import evflow_cli.ablations as ablations
    from agents.evaluation import SequenceResult

    scores = {"value": 1.0}

    def fake_evaluate(policy, split, *, window_size, **options):
        row = SequenceResult("seq", size=(4, 4), windowing="frames", windows=1)
        row.add("aee", scores["value"] * window_size)
        return [row]

    monkeypatch.setattr(ablations, "evaluate", fake_evaluate)
    budget = dataclasses.replace(TINY, eval_splits=("../shared/devval", "../other/devval", "synthetic-mini"), eval_dts=(1, 4))
    runner = AblationRunner(tmp_path / "run", budget, lambda argv: None, seeds=(0,), log=lambda _: None)
    folder = tmp_path / "run" / "config-s0" / "eval"
    first = runner._evaluate(folder, None)
    assert first["../shared/devval"]["dt4"]["aee"] == 4.0
    assert sorted(p.name for p in (tmp_path / "run" / "config-s0").iterdir()) == ["eval"]  # nothing beside it
    assert len(list(folder.iterdir())) == 6  # three splits, two window lengths, none sharing a file
    assert ablations.cache_name("a/b") != ablations.cache_name("a_b")
    assert ablations.cache_name("synthetic-test") == "synthetic-test"
    import shutil

    shutil.rmtree(folder)
    scores["value"] = 10.0  # another network: every score must be computed again
    again = runner._evaluate(folder, None)
    assert [again[s][d]["aee"] for s in budget.eval_splits for d in ("dt1", "dt4")] == [10.0, 40.0] * 3
