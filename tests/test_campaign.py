"""Campaigns: a run stopped by SIGTERM continues on a fresh clone from the committed state alone,
with the uninterrupted run's losses; the slim state drops Adam's moments only when over budget,
and then the step size warms up again; validation, export and the curve accumulate."""

import copy
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from agents.checkpoint import load_checkpoint
from agents.learner import Learner, TrainConfig
from evflow_cli.campaign import Campaign, _size, slim_state, unslim_state
from evflow_cli.commands import campaign as campaign_script
from tests.processes import holding
from tests.recordings import write_translating_recording

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "dots.h5"
    return write_translating_recording(path, np.random.default_rng(3), sensor_size=(32, 32))


def _recipe(recording, steps: int) -> list[str]:
    return ["--data", str(recording), "--model", "convgru-ev-flownet", "--width", "4", "--num-envs", "2",
            "--unroll", "3", "--lr", "1e-3", "--ckpt-every", "1000", "--steps", str(steps)]


def _new(root: Path, recording, steps: int, *extra: str) -> None:
    campaign_script.main(["new", "c", "--campaigns-dir", str(root), "--export", "c-model", "--val-data",
                          "--interval-minutes", "10", *extra, "--", *_recipe(recording, steps)])


def _resume(root: Path, runs: Path, *extra: str) -> int:
    return campaign_script.main(["resume", "c", "--campaigns-dir", str(root), "--runs", str(runs), "--quiet", "--threads", "1",
                                 "--weights-dir", str(root / "weights"), *extra])


def _losses(runs: Path) -> dict[int, float]:
    rows = [json.loads(line) for line in (runs / "c" / "train" / "metrics.jsonl").read_text().splitlines()]
    return {row["step"]: row["loss"] for row in rows if "loss" in row}


def test_sigterm_then_a_fresh_clone_continues_with_the_uninterrupted_losses(recording, tmp_path):
    steps = 8
    _new(tmp_path / "whole", recording, steps)
    assert _resume(tmp_path / "whole", tmp_path / "runs-whole") == 0
    whole = _losses(tmp_path / "runs-whole")
    assert sorted(whole) == list(range(1, steps + 1))

    # the same campaign, stopped by SIGTERM mid-run ...
    _new(tmp_path / "clone1", recording, steps)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, str(ROOT / "scripts" / "campaign.py"), "resume", "c", "--campaigns-dir",
                             str(tmp_path / "clone1"), "--runs", str(tmp_path / "runs1"), "--quiet", "--threads", "1"], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    metrics = tmp_path / "runs1" / "c" / "train" / "metrics.jsonl"
    deadline = time.time() + 240
    while proc.poll() is None and time.time() < deadline:
        if metrics.exists() and len(metrics.read_text().splitlines()) >= 2:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    out, _ = proc.communicate(timeout=240)
    assert proc.returncode == 0 and "SIGTERM: stopped; state saved" in out, out[-3000:]
    stopped = Campaign("c", tmp_path / "clone1").state_step()
    assert 2 <= stopped < steps, out[-3000:]

    # ... and continued on a "fresh clone": only the committed folder travels, no runs/ folder
    shutil.copytree(tmp_path / "clone1" / "c", tmp_path / "clone2" / "c")
    assert _resume(tmp_path / "clone2", tmp_path / "runs2") == 0
    resumed = _losses(tmp_path / "runs2")
    assert sorted(resumed) == list(range(stopped + 1, steps + 1))
    for step, loss in resumed.items():  # moments kept (a tiny network): bitwise on CPU
        assert loss == whole[step], (step, loss, whole[step])
    progress = Campaign("c", tmp_path / "clone2").progress()
    assert progress["stretches"] == 2 and progress["wall_s"] > 0


def _learner(recording, steps: int = 6) -> Learner:
    return Learner(TrainConfig(data=str(recording), model="convgru-ev-flownet", width=4, num_envs=2, unroll=3,
                               lr=1e-3, steps=steps, moment_warmup=4))


def test_slim_state_keeps_moments_under_budget_and_restarts_them_with_a_warmup(recording):
    torch.manual_seed(0)
    learner = _learner(recording)
    for _ in range(3):
        learner.update()
    payload = copy.deepcopy(learner.state_dict())  # the live tensors move on with the next updates
    kept, dropped = slim_state(payload, budget=2**30)
    assert dropped == "nothing" and kept["optimizer"]["state"]
    weights = sum(v.numel() * 4 for v in payload["model"].values())
    slim, dropped = slim_state(payload, budget=int(weights * 1.5) + 2**20)  # room for weights, not moments
    assert dropped == "moments" and slim["optimizer"]["state"] == {}
    with pytest.raises(ValueError, match="without Adam's moments and episodes"):
        slim_state(payload, budget=weights // 2)

    reference = [learner.update()["loss"] for _ in range(3)]  # the uninterrupted steps 4-6
    resumed = _learner(recording)
    resumed.load_state_dict(slim)
    assert resumed.rewarm_from == 3
    assert resumed.optimizer.param_groups[0]["lr"] == pytest.approx(1e-3 / 4)  # step 1 of 4 of the warm-up
    rows = [resumed.update() for _ in range(3)]
    assert rows[0]["loss"] == reference[0]  # same weights, same windows: the first loss is the same
    np.testing.assert_allclose([r["loss"] for r in rows], reference, rtol=0.05)
    assert [r["lr"] for r in rows] == pytest.approx([1e-3 / 4, 2e-3 / 4, 3e-3 / 4])  # each update's own
    again = _learner(recording)
    again.load_state_dict(resumed.state_dict())  # the warm-up's origin survives a full checkpoint
    assert again.rewarm_from == 3


def test_a_tight_budget_halves_then_drops_the_episodes_in_progress(recording):
    torch.manual_seed(0)
    learner = _learner(recording)
    learner.update()
    payload = copy.deepcopy(learner.state_dict())
    no_moments = _size(slim_state(payload, budget=2**30)[0]) - _size(payload["optimizer"])
    half, dropped = slim_state(payload, budget=no_moments - 1)  # just too big without the moments
    assert dropped == "moments, half episodes"
    assert all(v.dtype == torch.float16 for v in half["policy_state"].values())
    restored = unslim_state(half)
    for key, value in payload["policy_state"].items():  # float32 again, within float16's rounding
        assert restored["policy_state"][key].dtype == torch.float32
        torch.testing.assert_close(restored["policy_state"][key], value, rtol=1e-3, atol=1e-4)
    np.testing.assert_allclose(restored["obs"]["voxel_grid" if "voxel_grid" in payload["obs"] else "count_image"],
                               payload["obs"]["voxel_grid" if "voxel_grid" in payload["obs"] else "count_image"],
                               rtol=1e-3, atol=1e-3)
    resumed = _learner(recording)
    resumed.load_state_dict(restored)  # continues from the stored windows
    assert resumed.step == 1 and resumed.update()["step"] == 2
    bare, dropped = slim_state(payload, budget=_size(half) - 1)
    assert dropped == "moments, episodes" and "obs" not in bare and "env_states" not in bare
    fresh = _learner(recording)
    fresh.load_state_dict(unslim_state(bare))  # fresh episodes, the weights and step continue
    assert fresh.step == 1 and fresh.update()["step"] == 2


def test_validation_exports_the_best_and_the_curve_accumulates(recording, tmp_path):
    root, runs = tmp_path / "campaigns", tmp_path / "runs"
    campaign_script.main(["new", "c", "--campaigns-dir", str(root), "--export", "c-model", "--val-data",
                          str(recording), "--val-dt", "1", "--reference", "zero", "--interval-minutes", "10", "--",
                          *_recipe(recording, 2)])
    assert _resume(root, runs) == 0
    campaign = Campaign("c", root, runs)
    rows = campaign.curve()
    assert [r["step"] for r in rows] == [2] and rows[0]["exported"]
    reference = json.loads(campaign.reference_path.read_text())
    assert rows[0]["score"] == pytest.approx(rows[0]["aee"]["dt1"] / reference["aee"]["dt1"], rel=1e-4)
    record = json.loads((root / "weights" / "c-model.json").read_text())
    assert record["validation"]["score"] == rows[0]["score"] and record["campaign"] == "c"
    exported = load_checkpoint(root / "weights" / "c-model.pt")["model"]
    assert all(v.dtype == torch.float16 for v in exported.values() if v.is_floating_point())
    # a longer recipe continues the same curve (a later stretch), the reference is not recomputed
    spec = json.loads(campaign.spec_path.read_text())
    spec["train"][spec["train"].index("--steps") + 1] = "4"
    campaign.spec_path.write_text(json.dumps(spec))
    stamp = campaign.reference_path.stat().st_mtime_ns
    assert campaign_script.main(["resume", "c", "--campaigns-dir", str(root), "--runs", str(tmp_path / "fresh"),
                                 "--quiet", "--weights-dir", str(root / "weights")]) == 0
    rows = Campaign("c", root).curve()
    assert [r["step"] for r in rows] == [2, 4] and [r["stretch"] for r in rows] == [1, 2]
    assert campaign.reference_path.stat().st_mtime_ns == stamp
    # a reference cut short (a kill, a full disk) is derived data: computed again, not a raw JSONDecodeError
    text = campaign.reference_path.read_text()
    campaign.reference_path.write_text(text[: len(text) // 2])
    spec["train"][spec["train"].index("--steps") + 1] = "6"
    campaign.spec_path.write_text(json.dumps(spec))
    assert campaign_script.main(["resume", "c", "--campaigns-dir", str(root), "--runs", str(tmp_path / "fresh"),
                                 "--quiet", "--weights-dir", str(root / "weights")]) == 0
    assert json.loads(campaign.reference_path.read_text())["aee"] == json.loads(text)["aee"]
    assert [r["step"] for r in Campaign("c", root).curve()] == [2, 4, 6]


def test_an_export_another_campaign_starts_from_is_left_alone(recording, tmp_path):
    """A campaign whose export is another campaign's init writes EXPORT-latest instead: the
    shipped file the other configuration names stays byte for byte."""
    root, runs = tmp_path / "campaigns", tmp_path / "runs"
    campaign_script.main(["new", "c", "--campaigns-dir", str(root), "--export", "c-model", "--val-data",
                          str(recording), "--val-dt", "1", "--reference", "zero", "--interval-minutes", "10", "--",
                          *_recipe(recording, 2)])
    (root / "d").mkdir()
    (root / "d" / "campaign.json").write_text(json.dumps({"name": "d", "init": "c-model"}))
    weights = root / "weights"
    weights.mkdir()
    (weights / "c-model.pt").write_bytes(b"the lineage's file")
    assert _resume(root, runs) == 0
    assert (weights / "c-model.pt").read_bytes() == b"the lineage's file"
    record = json.loads((weights / "c-model-latest.json").read_text())
    assert record["campaign"] == "c" and "c-model is the init of d" in record["note"]
    assert Campaign("c", root, runs).curve()[0]["exported"]


def test_a_score_in_the_shipped_mode_rescores_the_export_before_it_competes(recording, tmp_path, monkeypatch):
    """val_split "dt": the score is taken from evaluate.py's --split dt row (the network stepped
    once per ground-truth interval), the one pass kept beside it; when a running campaign switches
    to it, its export is scored in the new mode first and only rows of that mode compete. The
    validations run with the campaign's --threads, like its training."""
    threads = []
    evaluate = campaign_script._evaluate

    def recorded(args, out, device, env=None):
        threads.append((env or os.environ).get("OMP_NUM_THREADS"))
        return evaluate(args, out, device, env)

    monkeypatch.setattr(campaign_script, "_evaluate", recorded)
    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    root, runs = tmp_path / "campaigns", tmp_path / "runs"
    campaign_script.main(["new", "c", "--campaigns-dir", str(root), "--export", "c-model", "--val-data",
                          str(recording), "--val-dt", "2", "--reference", "zero", "--interval-minutes", "10", "--",
                          *_recipe(recording, 2)])
    assert _resume(root, runs) == 0
    campaign = Campaign("c", root, runs)
    (one_pass,) = campaign.curve()
    assert "mode" not in one_pass and one_pass["exported"]
    spec = json.loads(campaign.spec_path.read_text())
    spec["val_split"] = "dt"
    spec["train"][spec["train"].index("--steps") + 1] = "4"
    campaign.spec_path.write_text(json.dumps(spec))
    assert _resume(root, tmp_path / "fresh") == 0
    rows = Campaign("c", root).curve()
    assert [r["step"] for r in rows] == [2, 2, 4] and [r.get("mode") for r in rows] == [None, "split dt", "split dt"]
    rescored, later = rows[1], rows[2]
    assert rescored["rescored"] and not rescored["exported"]
    # the export is the float16 copy of step 2: its one pass repeats step 2's score within rounding
    assert rescored["aee_one_pass"]["dt2"] == pytest.approx(one_pass["aee"]["dt2"], rel=2e-2)
    reference = json.loads(campaign.reference_path.read_text())["aee"]["dt2"]
    for row in (rescored, later):
        assert row["score"] == pytest.approx(row["aee"]["dt2"] / reference, rel=1e-4)
        assert row["aee"]["dt2"] != pytest.approx(row["aee_one_pass"]["dt2"], rel=1e-6)  # two steps, not one
    assert later["exported"] == (later["score"] < rescored["score"])
    assert campaign.best("split dt")["score"] == min(rescored["score"], later["score"])
    assert campaign.best()["score"] == one_pass["score"]  # one-pass rows compete only among themselves
    record = json.loads((root / "weights" / "c-model.json").read_text())
    assert record["validation"]["mode"] == ("split dt" if later["exported"] else "one pass")
    assert threads == ["1"] * 4  # the reference (once), step 2, the rescored export, step 4: on the campaign's 1 thread


@pytest.mark.parametrize("mode", ["dt", "finish"])
def test_a_shipped_model_is_scored_in_the_mode_too(recording, tmp_path, mode):
    """The initial weights of a campaign are often a shipped model (``--pretrained NAME``, whose rows
    evaluate.py names after it): with val_split its stepped row ("dt") or its row finished by the
    default's short solve ("finish") is found and scored as well."""
    from evflow_cli.campaign import CampaignSpec

    runs = tmp_path / "runs"
    spec = CampaignSpec(name="c", export="c-model", train=[], val_data=[str(recording)], val_dt=[2],
                        reference="zero", val_split=mode)
    campaign = Campaign("c", tmp_path / "campaigns", runs)
    campaign.dir.mkdir(parents=True)
    row = campaign_script.validate(campaign, spec, ["--pretrained", "ev-mgrflownet-cpu-synthetic"], "init", "cpu",
                                   print, {**os.environ, "OMP_NUM_THREADS": "1"})
    results = json.loads((runs / "c" / "val" / "init" / "results.json").read_text())
    from agents.pretrained import default_finish
    from agents.wrappers.refine import Finish

    finishes = " / ".join(Finish.from_dict(f).label() for f in default_finish())  # e.g. fine:3 / coarse3:2+cmax:20/16000
    label = {"dt": " + split dt", "finish": f" + finish {finishes}"}[mode]
    stepped = results["baselines"][f"ev-mgrflownet-cpu-synthetic (pretrained){label}"]["overall"]["dt2"]["aee"]
    assert row["mode"] == {"dt": "split dt", "finish": "finish"}[mode] and row["aee"]["dt2"] == stepped
    assert row["aee_one_pass"]["dt2"] == results["overall"]["dt2"]["aee"] != stepped


def test_anneal_continues_the_recipe_from_the_export_with_a_decaying_step_size(recording, tmp_path):
    """``anneal NAME`` describes a new campaign: NAME's recipe (its steps, warm-up and decay replaced
    in either spelling), from NAME's export, validated against the same reference; resumed, its step
    size rises over the warm-up and falls along a cosine to zero."""
    root, runs = tmp_path / "campaigns", tmp_path / "runs"
    campaign_script.main(["new", "c", "--campaigns-dir", str(root), "--export", "c-model", "--val-data",
                          str(recording), "--val-dt", "1", "--reference", "zero", "--interval-minutes", "10", "--",
                          *_recipe(recording, 2), "--warmup-steps=7"])
    weights = ["--weights-dir", str(root / "weights")]
    with pytest.raises(SystemExit, match="no export yet"):
        campaign_script.main(["anneal", "c", "--campaigns-dir", str(root), *weights])
    assert _resume(root, runs) == 0
    assert campaign_script.main(["anneal", "c", "--campaigns-dir", str(root), *weights, "--steps", "4",
                                 "--warmup-steps", "2", "--lr", "5e-4"]) == 0
    spec = json.loads((root / "c-cooldown" / "campaign.json").read_text())
    recipe = spec["train"]
    assert spec["export"] == "c-model-cooldown" and spec["init"] == str(root / "weights" / "c-model.pt")
    assert sorted(a for a in recipe if a.startswith(("--steps", "--warmup-steps", "--decay", "--lr"))) == \
        ["--decay", "--lr", "--steps", "--warmup-steps"]  # each once: replaced, not repeated
    assert recipe[recipe.index("--steps") + 1] == "4" and float(recipe[recipe.index("--lr") + 1]) == 5e-4
    assert recipe[recipe.index("--warmup-steps") + 1] == "2" and recipe[recipe.index("--decay") + 1] == "cosine"
    assert (root / "c-cooldown" / "reference.json").read_bytes() == (root / "c" / "reference.json").read_bytes()
    with pytest.raises(SystemExit, match="exists"):
        campaign_script.main(["anneal", "c", "--campaigns-dir", str(root), *weights])
    with pytest.raises(SystemExit, match="a name of its own"):
        campaign_script.main(["anneal", "c", "--into", "c", "--campaigns-dir", str(root), *weights])
    with pytest.raises(SystemExit, match="fewer than --steps"):
        campaign_script.main(["anneal", "c", "--into", "c2", "--campaigns-dir", str(root), *weights, "--steps", "5",
                              "--warmup-steps", "5"])
    with holding(runs / "c"):  # a live process holds the source campaign
        with pytest.raises(SystemExit, match="is running here"):
            campaign_script.main(["anneal", "c", "--into", "c2", "--campaigns-dir", str(root), "--runs", str(runs),
                                  *weights])
    assert campaign_script.main(["resume", "c-cooldown", "--campaigns-dir", str(root), "--runs", str(runs), "--quiet",
                                 "--threads", "1", *weights]) == 0
    rows = [json.loads(line) for line in (runs / "c-cooldown" / "train" / "metrics.jsonl").read_text().splitlines()]
    lrs = [row["lr"] for row in rows if "lr" in row]
    # the step size of update k (0-based): 5e-4 * min(1, (k + 1) / 2) * (1 + cos(pi k / 4)) / 2
    expected = [5e-4 * min(1.0, (k + 1) / 2) * 0.5 * (1 + np.cos(np.pi * k / 4)) for k in range(4)]
    assert lrs == pytest.approx(expected, rel=1e-6)
    # it started from the export: its first validation is not the campaign's initial weights
    record = json.loads((root / "weights" / "c-model-cooldown.json").read_text())
    assert record["campaign"] == "c-cooldown" and "annealed from its export c-model" in record["note"]


def test_refusals(recording, tmp_path, capsys):
    with pytest.raises(SystemExit, match="--out"):
        campaign_script.main(["new", "c", "--campaigns-dir", str(tmp_path), "--export", "x", "--", "--out", "elsewhere"])
    with pytest.raises(SystemExit):  # train.py refuses --revive without the --init the campaign would give it
        campaign_script.main(["new", "r", "--campaigns-dir", str(tmp_path), "--export", "x", "--", "--revive", "2"])
    assert "--revive re-initialises the dormant channels of the --init weights" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()
    campaign_script.main(["new", "r", "--campaigns-dir", str(tmp_path), "--export", "x", "--init", "some-weights",
                          "--", "--revive", "2", "--steps", "10"])
    assert json.loads((tmp_path / "r" / "campaign.json").read_text())["train"] == ["--revive", "2", "--steps", "10"]
    # annealing it starts from weights already revived: the recipe goes on without --revive
    campaign_script.main(["anneal", "r", "--campaigns-dir", str(tmp_path), "--runs", str(tmp_path / "runs"),
                          "--init", "other-weights", "--steps", "4", "--warmup-steps", "1"])
    annealed = json.loads((tmp_path / "r-cooldown" / "campaign.json").read_text())
    assert "--revive" not in annealed["train"] and annealed["init"] == "other-weights"
    with pytest.raises(FileNotFoundError, match="no campaign 'nope'"):
        campaign_script.main(["resume", "nope", "--campaigns-dir", str(tmp_path), "--runs", str(tmp_path / "r")])
    _new(tmp_path, recording, 2)
    spec_path = tmp_path / "c" / "campaign.json"
    good = spec_path.read_text()
    spec_path.write_text(json.dumps({**json.loads(good), "val_split": "4"}))
    with pytest.raises(ValueError, match=r"campaign.json: val_split must be \"dt\", \"finish\" or null, got '4'"):
        campaign_script.main(["resume", "c", "--campaigns-dir", str(tmp_path), "--runs", str(tmp_path / "r")])
    assert not (tmp_path / "r" / "c" / "train").exists()  # refused before any training
    spec_path.write_text(good)
    (tmp_path / "r" / "c").mkdir(parents=True)
    (tmp_path / "r" / "c" / "campaign.pid").write_text(str(os.getppid()))  # an old pid file means nothing now
    with holding(tmp_path / "r" / "c") as holder:  # a live process holds the campaign
        with pytest.raises(SystemExit, match=f"already running \\(pid {holder.pid}\\)"):
            campaign_script.main(["resume", "c", "--campaigns-dir", str(tmp_path), "--runs", str(tmp_path / "r")])
    # its holder gone (killed), the lock is free: stop signals nobody
    assert campaign_script.main(["stop", "c", "--campaigns-dir", str(tmp_path), "--runs", str(tmp_path / "r")]) == 0
    assert "not running here" in capsys.readouterr().out




def test_device_leg_on_cpu_writes_state_and_weights_to_its_output(recording, tmp_path):
    """scripts/device_train.sh as a GPU machine runs it, here with --device cpu and a short budget."""
    root = tmp_path / "campaigns"
    campaign_script.main(["new", "c", "--campaigns-dir", str(root), "--export", "c-model", "--val-data",
                          str(recording), "--val-dt", "1", "--reference", "zero", "--interval-minutes", "10", "--",
                          *_recipe(recording, 100000)])
    out = tmp_path / "out"
    env = {**os.environ, "CAMPAIGNS": str(root), "RUNS": str(tmp_path / "runs"), "PYTHON": sys.executable,
           "OMP_NUM_THREADS": "1"}
    done = subprocess.run(["bash", str(ROOT / "scripts" / "device_train.sh"), "c", "0.1", str(out), "--device", "cpu",
                           "--workers", "1"], env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    assert Campaign("c", out / "campaigns").state_step() > 0
    assert Campaign("c", root).state_step() is None  # the home copy is untouched until it is taken in
    assert (out / "weights" / "c-model.pt").exists() and "campaign_commit.py c --from" in done.stdout
    bad = subprocess.run(["bash", str(ROOT / "scripts" / "device_train.sh"), "nope", "1", str(out)], env=env,
                         capture_output=True, text=True)
    assert bad.returncode == 2 and "no campaign" in bad.stderr
