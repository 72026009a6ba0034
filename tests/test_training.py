"""The training machinery: a tiny model overfits, resume is exact, and the evaluation script
writes its table (distributed training: tests/test_distributed.py)."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from agents import RecurrentPolicy, make_model
from agents.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from envs.env import EventFlowEnv
from evflow_cli.commands import evaluate as evaluate_script
from evflow_cli.commands import train as train_script
from losses import EventBatch, hmc_loss
from tests.recordings import write_translating_recording

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))  # export_model, ablations and main are tested as scripts


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "dots.h5"
    return write_translating_recording(path, np.random.default_rng(3), sensor_size=(32, 32))


def test_tiny_model_overfits_one_fixed_batch(recording):
    env = EventFlowEnv(recording)
    obs, info = env.reset(seed=0)
    windows, images = [], []
    for _ in range(3):
        windows.append(info["window"])
        images.append(obs["count_image"])
        obs, *_, info = env.step(info["flow_gt"])
    torch.manual_seed(0)
    policy = RecurrentPolicy(make_model("unet-feedforward", base_width=4, flow_scaling=32.0))
    optimizer = torch.optim.Adam(policy.parameters(), lr=3e-3)
    batches = [EventBatch.from_windows([w]) for w in windows]
    zero = np.mean([float(hmc_loss(torch.zeros(1, 2, 32, 32), b, flow_scaling=32.0).loss) for b in batches])
    history = []
    for _ in range(40):
        policy.reset()
        loss = sum(hmc_loss(policy(torch.from_numpy(img)[None]), b, flow_scaling=32.0).loss for img, b in zip(images, batches)) / 3
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        history.append(float(loss.detach()))
    print(f"loss first {history[0]:.4f} last {history[-1]:.4f}; zero flow {zero:.4f}")
    assert history[-1] < history[0] - 0.1 * abs(history[0] - zero) - 1e-3
    assert min(history[-5:]) < history[0]


def _losses(out: Path) -> list[float]:
    return [json.loads(line)["loss"] for line in (out / "metrics.jsonl").read_text().splitlines() if "loss" in json.loads(line)]


def test_resume_reproduces_uninterrupted_run(recording, tmp_path):
    common = ["--device", "cpu", "--data", str(recording), "--model", "convgru-ev-flownet", "--width", "4", "--num-envs", "2",
              "--unroll", "3", "--val-data", "", "--no-progress", "--ckpt-every", "100", "--lr", "1e-3"]
    full, part = tmp_path / "full", tmp_path / "part"
    train_script.main(common + ["--steps", "6", "--out", str(full)])
    train_script.main(common + ["--steps", "3", "--out", str(part)])
    train_script.main(["--resume", "--device", "cpu", "--steps", "6", "--out", str(part), "--val-data", "", "--no-progress"])  # OUT/checkpoint.pt
    a, b = _losses(full), _losses(part)
    assert len(a) == len(b) == 6
    np.testing.assert_allclose(b, a, rtol=1e-6)  # episodes cross a sequence boundary in 6 x 3 windows


def test_sigterm_mid_run_saves_and_resume_matches_the_uninterrupted_run(recording, tmp_path):
    """What a scheduler or `timeout` does: SIGTERM while training. The run finishes its step, saves
    and exits cleanly; --resume then gives the uninterrupted run's losses, each step logged once."""
    common = ["--device", "cpu", "--data", str(recording), "--model", "convgru-ev-flownet", "--width", "4", "--num-envs", "2",
              "--unroll", "3", "--val-data", "", "--no-progress", "--lr", "1e-3", "--ckpt-every", "1000"]
    part, full = tmp_path / "part", tmp_path / "full"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, str(ROOT / "scripts" / "train.py"), *common, "--steps", "100000",
                             "--out", str(part)], env=env, stderr=subprocess.PIPE, text=True)
    metrics = part / "metrics.jsonl"
    deadline = time.time() + 240
    while proc.poll() is None and time.time() < deadline:
        if metrics.exists() and len(metrics.read_text().splitlines()) >= 2:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=240)
    assert proc.returncode == 0 and "SIGTERM: stopped at step" in err, err[-3000:]
    stopped = load_checkpoint(part / "checkpoint.pt")["step"]  # no periodic save yet: written on SIGTERM
    assert 2 <= stopped < 100000
    total = stopped + 3
    train_script.main(["--resume", "--device", "cpu", "--steps", str(total), "--out", str(part), "--val-data", "", "--no-progress"])
    train_script.main(common + ["--steps", str(total), "--out", str(full)])
    steps = [json.loads(line)["step"] for line in metrics.read_text().splitlines()]
    assert steps == list(range(1, total + 1))
    np.testing.assert_allclose(_losses(part), _losses(full), rtol=1e-6)


def test_resume_cuts_the_log_back_to_the_checkpoint(recording, tmp_path):
    """A run killed between checkpoints logged steps the checkpoint does not hold (and maybe half
    a line): the resumed run logs them again, so they are cut first and every step appears once."""
    common = ["--device", "cpu", "--data", str(recording), "--width", "4", "--num-envs", "1", "--unroll", "1", "--val-data", "",
              "--no-progress"]
    train_script.main(common + ["--steps", "2", "--out", str(tmp_path / "run")])
    metrics = tmp_path / "run" / "metrics.jsonl"
    with open(metrics, "a") as log:  # steps 3 and 4 after the step-2 checkpoint, then a kill mid-line
        log.write(json.dumps({"step": 3, "loss": 9.0}) + "\n" + json.dumps({"step": 4, "loss": 9.0}) + "\n" + '{"step": 5, "lo')
    train_script.main(["--resume", "--device", "cpu", "--steps", "5", "--out", str(tmp_path / "run"), "--val-data", "", "--no-progress"])
    rows = [json.loads(line) for line in metrics.read_text().splitlines()]
    assert [row["step"] for row in rows] == [1, 2, 3, 4, 5] and all(row["loss"] != 9.0 for row in rows)


def test_border_ramp_reaches_the_config_and_old_checkpoints_keep_the_plain_rule(recording, tmp_path):
    common = ["--device", "cpu", "--data", str(recording), "--model", "convgru-ev-flownet", "--width", "4", "--num-envs", "1",
              "--unroll", "2", "--val-data", "", "--no-progress"]
    train_script.main(common + ["--steps", "1", "--border-ramp", "5", "--out", str(tmp_path / "new")])
    assert load_checkpoint(tmp_path / "new" / "checkpoint.pt")["config"]["border_ramp"] == 5.0
    train_script.main(common + ["--steps", "1", "--out", str(tmp_path / "old")])
    path = tmp_path / "old" / "checkpoint.pt"
    payload = load_checkpoint(path)
    assert payload["config"]["border_ramp"] == 16.0  # the default
    del payload["config"]["border_ramp"]  # as written before the ramp existed
    save_checkpoint(path, payload)
    train_script.main(["--resume", "--device", "cpu", "--steps", "2", "--out", str(tmp_path / "old"), "--val-data", "", "--no-progress"])
    assert load_checkpoint(path)["config"]["border_ramp"] == 0.0


def test_bad_border_ramp_is_refused_before_anything_is_written(recording, tmp_path):
    with pytest.raises(ValueError, match="border_ramp"):
        EventFlowEnv(recording, border_ramp=-1.0)
    with pytest.raises(ValueError, match="border_ramp"):
        train_script.main(["--data", str(recording), "--width", "4", "--num-envs", "1", "--unroll", "2", "--steps", "1",
                           "--val-data", "", "--no-progress", "--border-ramp", "-2", "--out", str(tmp_path / "bad")])
    assert not (tmp_path / "bad").exists()


def test_init_fine_tunes_from_checkpoint_weights_and_names_a_mismatch(recording, tmp_path):
    common = ["--device", "cpu", "--data", str(recording), "--width", "4", "--num-envs", "1", "--unroll", "2", "--val-data", "",
              "--no-progress", "--lr", "1e-3"]
    train_script.main(common + ["--steps", "2", "--out", str(tmp_path / "a")])
    source = load_checkpoint(tmp_path / "a" / "checkpoint.pt")
    # --steps 0: the new run saves the weights it started from, with its own options.
    train_script.main(common + ["--steps", "0", "--loss", "at", "--init", str(tmp_path / "a" / "checkpoint.pt"),
                                "--out", str(tmp_path / "b")])
    tuned = load_checkpoint(tmp_path / "b" / "checkpoint.pt")
    assert tuned["step"] == 0 and tuned["config"]["loss"] == "at"
    for key, value in source["model"].items():
        torch.testing.assert_close(tuned["model"][key], value, rtol=0, atol=0)
    with pytest.raises(ValueError, match="--init .*checkpoint.pt"):
        train_script.main(common + ["--steps", "0", "--width", "8", "--init", str(tmp_path / "a" / "checkpoint.pt"),
                                    "--out", str(tmp_path / "c")])
    # a setting that shapes no weight may change: the same weights, the new setting stored
    train_script.main(common + ["--steps", "0", "--model-kwarg", "input_norm=nonzero-rms", "--init",
                                str(tmp_path / "a" / "checkpoint.pt"), "--out", str(tmp_path / "d")])
    normed = load_checkpoint(tmp_path / "d" / "checkpoint.pt")
    assert normed["model_config"]["input_norm"] == "nonzero-rms"
    for key, value in source["model"].items():
        torch.testing.assert_close(normed["model"][key], value, rtol=0, atol=0)


def test_logged_baselines_match_a_network_at_zero_flow(recording, tmp_path):
    """A network whose flow heads are all zero outputs zero flow, and scores what zero flow
    scores: its logged L_HMC equals zero flow's, its distance to the teacher is the teacher's
    own magnitude."""
    common = ["--device", "cpu", "--data", str(recording), "--model", "ev-flownet", "--width", "4", "--num-envs", "2", "--unroll", "2",
              "--steps", "2", "--lr", "0", "--head-init", "0", "--val-data", "", "--no-progress"]
    rows = {}
    for loss in ("hmc", "teacher"):
        train_script.main(common + ["--loss", loss, "--teacher-steps", "5", "--out", str(tmp_path / loss)])
        rows[loss] = [json.loads(line) for line in (tmp_path / loss / "metrics.jsonl").read_text().splitlines()
                      if "loss" in json.loads(line)]
    for row in rows["hmc"] + rows["teacher"]:
        assert row["model_hmc"] == pytest.approx(row["zero_flow_loss"], rel=1e-6)
    for row in rows["teacher"]:
        assert row["zero_flow_teacher"] > 0.05  # the translating dots move: the teacher is not zero
        assert row["loss"] == pytest.approx(row["zero_flow_teacher"], rel=1e-6)


def test_voxel_grid_input_trains_and_evaluates(recording, tmp_path):
    train_script.main(["--data", str(recording), "--input", "voxel_grid", "--voxel-bins", "3", "--width", "4",
                       "--num-envs", "1", "--unroll", "2", "--steps", "1", "--out", str(tmp_path / "vox"),
                       "--val-data", "", "--no-progress"])
    payload = load_checkpoint(tmp_path / "vox" / "checkpoint.pt")
    assert payload["model_config"]["in_channels"] == 3 and payload["config"]["input"] == "voxel_grid"
    evaluate_script.main(["--checkpoint", str(tmp_path / "vox" / "checkpoint.pt"), "--data", str(recording), "--dt", "1",
                          "--out", str(tmp_path / "ev"), "--max-windows", "2", "--no-progress", "--pictures", "0"])
    assert json.loads((tmp_path / "ev" / "results.json").read_text())["overall"]["dt1"]["windows"] == 2


def test_checkpoint_write_is_atomic_and_checked(tmp_path):
    path = save_checkpoint(tmp_path / "c.pt", {"model_name": "ev-flownet", "model_config": {}, "model": {}})
    before = path.read_bytes()
    with pytest.raises(Exception):  # noqa: B017 - whatever pickle raises, the old file stays
        save_checkpoint(path, {"model_name": "x", "model_config": {}, "model": {}, "bad": lambda: 0})
    assert path.read_bytes() == before and [p.name for p in tmp_path.iterdir()] == ["c.pt"]
    (tmp_path / "junk.pt").write_bytes(b"garbage")
    with pytest.raises(CheckpointError, match="junk.pt"):
        load_checkpoint(tmp_path / "junk.pt")


def test_evaluate_script_writes_table_and_pictures(recording, tmp_path):
    train_script.main(["--data", str(recording), "--width", "4", "--num-envs", "1", "--unroll", "2", "--steps", "1",
                       "--out", str(tmp_path / "run"), "--val-data", "", "--no-progress"])
    out = tmp_path / "eval"
    evaluate_script.main(["--checkpoint", str(tmp_path / "run" / "checkpoint.pt"), "--zero", "--data", str(recording),
                          "--out", str(out), "--max-windows", "3", "--no-progress", "--json", str(tmp_path / "r.json")])
    table = (out / "table.md").read_text()
    assert "| zero flow |" in table and "| run |" in table and "4 x ground-truth intervals" in table
    results = json.loads((tmp_path / "r.json").read_text())
    assert results["method"] == "run" and set(results["overall"]) >= {"dt1", "dt4", "fwl", "rsat"}
    zero = results["baselines"]["zero flow"]["sequences"]["dots"]
    assert zero["fwl"] == pytest.approx(1.0) and zero["rsat"] == pytest.approx(1.0)
    speed = np.hypot(200, 100)  # px/s of the recording's known motion
    assert zero["dt1"]["aee"] == pytest.approx(speed * 0.03, rel=1e-5)
    assert zero["dt4"]["aee"] == pytest.approx(speed * 0.12, rel=1e-5)  # 4 frames: chained ground truth
    assert any(p.name.endswith("_w000.png") for p in (out / "pictures" / "dt1" / "run").iterdir())


def test_evaluate_without_ground_truth_reports_fwl_only(tmp_path):
    from envs.readers import write_h5
    from tests.recordings import translating_dots

    events, span = translating_dots(np.random.default_rng(0), sensor_size=(32, 32))
    path = write_h5(tmp_path / "nogt.h5", events, t_start_us=span[0], t_end_us=span[1])
    evaluate_script.main(["--zero", "--data", str(path), "--out", str(tmp_path / "e"), "--no-progress", "--pictures", "0"])
    results = json.loads((tmp_path / "e" / "results.json").read_text())
    seq = results["sequences"]["nogt"]
    assert seq["fwl"] == pytest.approx(1.0) and seq["dt1"]["windows"] == 10  # 33.333 ms time windows over 300 ms
    for metrics in (seq["dt1"], results["overall"]["dt1"]):  # only the metrics that have values, as in the table
        assert set(metrics) == {"hmc", "hmc_zero", "fwl", "rsat", "ms", "windows"} and None not in metrics.values()
    table = (tmp_path / "e" / "table.md").read_text().strip().splitlines()
    title = "**windows of 1 x fixed 33333 us intervals (no ground truth, no frames): 10 windows of 1 sequence**"
    assert table[0] == title and table[1] == ""
    assert table[2] == "| method | L_HMC | L_HMC zero | seq. L_HMC < zero | FWL | RSAT | ms/win |"
    assert len(table) == 5 and all(" - " not in row and "AEE" not in row for row in table)  # no empty column, nothing else


def test_bad_checkpoints_and_models_are_named(recording, tmp_path):
    from agents.checkpoint import load_model
    from agents.protocol import ModelLoadError

    run = tmp_path / "run"
    train_script.main(["--data", str(recording), "--width", "4", "--num-envs", "1", "--unroll", "1", "--steps", "1",
                       "--out", str(run), "--val-data", "", "--no-progress"])
    with pytest.raises(CheckpointError, match="holds model 'ev-mgrflownet', not 'ev-flownet'"):
        evaluate_script.main(["--checkpoint", str(run / "checkpoint.pt"), "--model", "ev-flownet", "--data", str(recording),
                              "--out", str(tmp_path / "ev")])  # never the checkout's runs/eval: it may exist
    payload = load_checkpoint(run / "checkpoint.pt")
    payload["model_config"]["base_width"] = 8  # weights of a width-4 net, config of a width-8 one
    save_checkpoint(tmp_path / "mismatch.pt", payload)
    with pytest.raises(CheckpointError, match="weights do not fit model 'ev-mgrflownet'"):
        load_model(tmp_path / "mismatch.pt")
    with pytest.raises(ModelLoadError, match="unknown model 'no-such-net'"):
        train_script.main(["--model", "no-such-net", "--data", str(recording), "--steps", "1", "--out", str(tmp_path / "x")])


def test_export_and_load_pretrained_by_name(recording, tmp_path, monkeypatch):
    import export_model as export_script

    import agents.pretrained as pretrained

    train_script.main(["--data", str(recording), "--input", "voxel_grid", "--voxel-bins", "3", "--width", "4",
                       "--num-envs", "1", "--unroll", "2", "--steps", "2", "--out", str(tmp_path / "run"),
                       "--val-data", "", "--no-progress"])
    weights = tmp_path / "weights"
    weights.mkdir()
    export_script.main([str(tmp_path / "run" / "checkpoint.pt"), "--name", "tiny", "--command", "train.py ...",
                        "--dir", str(weights)])
    assert pretrained.list_pretrained(weights) == ["tiny"]
    info = pretrained.pretrained_info("tiny", weights)
    assert info["input"] == "voxel_grid" and info["budget"]["optimizer_steps"] == 2 and info["command"] == "train.py ..."
    slim = load_checkpoint(weights / "tiny.pt")
    assert "optimizer" not in slim and "env_states" not in slim  # weights only
    # the shipped actor gives exactly the trained model's flow on an env observation
    monkeypatch.setattr(pretrained, "WEIGHTS_DIR", weights)
    monkeypatch.setattr(pretrained, "DEFAULT_PRETRAINED", "tiny")
    policy = RecurrentPolicy.from_pretrained()
    from agents.checkpoint import load_model
    model, _ = load_model(tmp_path / "run" / "checkpoint.pt")
    with torch.no_grad():  # the shipped file holds float16 weights
        for p in model.parameters():
            p.copy_(p.half().float())
    reference = RecurrentPolicy(model, input_key="voxel_grid", voxel_bins=3)
    env = EventFlowEnv(recording, observations=("voxel_grid",), voxel_bins=3)
    obs, _ = env.reset(seed=0)
    for _ in range(3):
        action = policy.act(obs)
        np.testing.assert_allclose(action, reference.act(obs), rtol=1e-6, atol=1e-6)
        obs, *_ = env.step(action)
    # --init NAME: fine-tuning starts from the shipped weights
    train_script.main(["--data", str(recording), "--input", "voxel_grid", "--voxel-bins", "3", "--width", "4",
                       "--num-envs", "1", "--steps", "0", "--init", "tiny", "--out", str(tmp_path / "tuned"),
                       "--val-data", "", "--no-progress"])
    for key, value in load_checkpoint(tmp_path / "tuned" / "checkpoint.pt")["model"].items():
        torch.testing.assert_close(value, model.state_dict()[key], rtol=0, atol=0)
    with pytest.raises(FileNotFoundError, match="--init nope: no such checkpoint, nor a shipped model .*tiny"):
        train_script.main(["--data", str(recording), "--steps", "0", "--init", "nope", "--out", str(tmp_path / "bad"),
                           "--val-data", "", "--no-progress"])
    assert not (tmp_path / "bad").exists()  # nothing written
    monkeypatch.setattr(sys, "argv", ["evaluate.py"])
    evaluate_script.main(["--pretrained", "--data", str(recording), "--dt", "1", "--out", str(tmp_path / "ev"),
                          "--max-windows", "2", "--no-progress", "--pictures", "0"])
    assert "tiny (pretrained)" in (tmp_path / "ev" / "table.md").read_text()
    with pytest.raises(KeyError, match="no pretrained model 'nope'"):
        RecurrentPolicy.from_pretrained("nope")


def test_head_init_starts_every_builtin_model_near_zero_flow():
    from agents.learner import init_flow_heads

    x = torch.rand(2, 2, 32, 48) * 3
    for name in ("ev-mgrflownet", "convgru-ev-flownet", "ev-flownet", "xlif-ev-flownet", "unet-feedforward",
                 "unet-convgru", "unet-xlif-encoder"):
        torch.manual_seed(0)
        model = make_model(name, base_width=4, flow_scaling=32.0, in_channels=2)
        init_flow_heads(model, 1e-3)
        flows, state = model(x, None)
        flows, _ = model(x, state)  # second window: the prior flow path too
        assert max(float(f.detach().abs().max()) for f in flows) < 0.5, name  # px, vs up to 32 with the default init
    with pytest.raises(ValueError, match="decoder.heads"):
        init_flow_heads(torch.nn.Linear(2, 2), 1e-3)


@pytest.mark.parametrize("stage", ["hmc", "teacher"])
def test_main_job_runs_end_to_end_on_mini_data(tmp_path, capsys, stage):
    import main as main_script

    out = tmp_path / "main"
    # the hmc stage starts from the shipped model (CPU width); the teacher stage from scratch
    extra = ["--width", "4", "--teacher-steps", "2"] if stage == "teacher" else []
    main_script.main(["--demo-minutes", "1", "--demo-steps", "2", "--demo-val-every", "1", "--demo-stage", stage,
                      "--eval-data", "synthetic-mini", "--demo-val-data", "synthetic-mini", "--out", str(out),
                      "--eval-windows", "2", *(["--no-cmax"] if stage == "hmc" else []),
                      "--", "--data", "synthetic-mini", "--num-envs", "2", "--unroll", "2", *extra])
    printed = capsys.readouterr().out
    assert ("teacher ratio" in printed) == (stage == "teacher")
    assert ("from the shipped model" in printed) == (stage == "hmc")
    table = (out / "eval" / "synthetic-mini" / "table.md").read_text()
    assert "| zero flow |" in table and ("| contrast maximisation (no network) |" in table) == (stage == "teacher")
    assert "(the default's mode) |" in table and ", network alone |" in table
    assert "Columns: AEE, the average endpoint error" in printed  # the legend under the tables
    rows = [json.loads(line) for line in (out / "demo" / "metrics.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows if "val_aee_model" in r] == [0, 1, 2]  # the start, every step, the end
    assert (out / "demo" / "checkpoint.pt").exists() and "at step 0 -> " in printed
    assert "L_HMC ratio" in printed and "scripts/train.py --preset teacher-cached" in printed


def test_main_jobs_demo_verdict_and_picture(tmp_path, capsys):
    """The verdict reads the validation rows: learned when the last AEE is below the first and
    below zero flow's; the picture is a PNG (with the plots extra)."""
    from evflow_cli.commands.main_job import SCRATCH_DEMO, demo_verdict, plot_demo
    from evflow_cli.commands.train import build_parser, config_from_args

    metrics = tmp_path / "metrics.jsonl"
    zero = {"val_aee_zero": 2.0, "val_hmc_zero": 1.2}
    lines = [{"step": 0, "val_aee_model": 2.5, "val_hmc_model": 1.3, **zero},
             {"step": 1, "loss": 1.0, "zero_flow_teacher": 1.0, "zero_flow_loss": 1.0},
             {"step": 2, "val_aee_model": 1.5, "val_hmc_model": 1.1, **zero}]
    metrics.write_text("".join(json.dumps(r) + "\n" for r in lines))
    assert demo_verdict(metrics) is True
    assert "2.500 at step 0 -> 1.500 at step 2 (0.75x zero flow's 2.000): below its start, below zero flow's" in (
        capsys.readouterr().out)
    lines[-1]["val_aee_model"] = 2.2  # below its start, above zero flow's
    metrics.write_text("".join(json.dumps(r) + "\n" for r in lines))
    assert demo_verdict(metrics) is False and "NOT below zero flow's" in capsys.readouterr().out
    pytest.importorskip("matplotlib")
    assert plot_demo(metrics, tmp_path / "demo.png").read_bytes()[:4] == b"\x89PNG"
    cfg = config_from_args(build_parser().parse_args(SCRATCH_DEMO))  # the demo's recipe is a valid run
    assert cfg.model == "ev-flownet" and cfg.loss == "teacher" and Path(cfg.teacher_cache).is_file()


def test_ev_flownet_trains_on_its_four_channel_input():
    """Zhu's EV-FlowNet reads the observation "count_time_image" (counts and latest timestamps
    per polarity): the learner builds it with 4 input channels and steps it."""
    from agents.learner import Learner, TrainConfig

    learner = Learner(TrainConfig(model="ev-flownet", input="count_time_image", width=2, data="synthetic-mini",
                                  num_envs=1, unroll=2))
    try:
        assert learner.policy.model.in_channels == 4 and learner.obs["count_time_image"].shape[1] == 4
        before = [p.detach().clone() for p in learner.policy.parameters()]
        stats = learner.update()
    finally:
        learner.close()
    assert np.isfinite(stats["loss"])
    assert any(not torch.equal(a, b) for a, b in zip(before, learner.policy.parameters()))


def test_threads_sets_torch_threads_and_is_a_run_option(recording, tmp_path):
    """--threads N sets torch's CPU threads for the run; it is not part of what the run learns, so
    a resume may change it."""
    before = torch.get_num_threads()
    common = ["--device", "cpu", "--data", str(recording), "--width", "4", "--num-envs", "1", "--unroll", "2",
              "--val-data", "", "--no-progress", "--out", str(tmp_path / "a")]
    try:
        torch.set_num_threads(2)
        train_script.main(common + ["--steps", "1", "--threads", "1"])
        assert torch.get_num_threads() == 1
        assert "threads" not in load_checkpoint(tmp_path / "a" / "checkpoint.pt")["config"]
        train_script.main(common + ["--steps", "2", "--resume", "--threads", "2"])
        assert torch.get_num_threads() == 2 and load_checkpoint(tmp_path / "a" / "checkpoint.pt")["step"] == 2
    finally:
        torch.set_num_threads(before)
