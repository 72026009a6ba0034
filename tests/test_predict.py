"""evflow_cli.predict against the env-driven evaluation: same windows, same flows, same metrics."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from agents.evaluation import evaluate
from agents.policy import RecurrentPolicy
from agents.registry import make_model
from evflow_cli.predict import FLOW_FORMAT, predict, summary_table


class RecordingPolicy:
    """Forwards to a policy and keeps every flow it returned (what the evaluation saw)."""

    def __init__(self, policy: RecurrentPolicy) -> None:
        self.policy, self.flows = policy, []
        self.input_key, self.voxel_bins = policy.input_key, policy.voxel_bins

    def reset(self) -> None:
        self.policy.reset()

    def act(self, obs):
        flow = self.policy.act(obs)
        self.flows.append(flow)
        return flow


def tiny_policy() -> RecurrentPolicy:
    import torch

    torch.manual_seed(0)
    return RecurrentPolicy(make_model("plugin_example.tiny_flow:build", flow_scaling=4.0).eval())


@pytest.fixture
def plugin_path(monkeypatch):
    from pathlib import Path

    monkeypatch.syspath_prepend(str(Path(__file__).parent))


@pytest.mark.parametrize("window,size", [("frames", 1), ("time", 20_000)])
def test_predict_writes_the_flows_the_evaluation_produces(tmp_path, plugin_path, window, size):
    policy = tiny_policy()
    spy = RecordingPolicy(policy)
    runs = evaluate(spy, "synthetic-mini", window=window, window_size=size, progress=False)
    expected = runs[1]  # predict the second sequence; its flows follow the first one's in the spy
    flows = np.stack(spy.flows[runs[0].windows : runs[0].windows + expected.windows])
    out = tmp_path / "flow.h5"
    result = predict(policy, "synthetic-mini", out, window=window, window_size=size, sequence=1, per_event=True,
                     video=tmp_path / "preview.gif", progress=False, provenance={"kind": "test"})
    with h5py.File(out, "r") as f:
        assert f.attrs["format"] == FLOW_FORMAT and tuple(f.attrs["sensor_size"]) == (64, 64)
        assert f["flow"].dtype == np.float16 and f["flow"].chunks == (1, 2, 64, 64) and f["flow"].compression == "gzip"
        np.testing.assert_array_equal(f["flow"][:], flows.astype(np.float16))
        assert len(f["t_start"]) == expected.windows == result.windows
        assert (f["t_end"][:-1] == f["t_start"][1:]).all()
        offsets = f["event_offsets"][:]
        assert offsets[-1] == f["num_events"][:].sum() == len(f["event_flow"]) == result.events
    for key in ("hmc", "hmc_zero", "fwl", "rsat") + (("aee",) if window == "frames" else ()):
        assert result.mean(key) == pytest.approx(expected.mean(key), rel=1e-6), key
    assert result.video is not None and result.video.stat().st_size > 0
    table = summary_table(result)
    assert "zero flow" in table and f"{expected.mean('hmc'):.4f}" in table


def test_predict_split_writes_the_flows_the_split_evaluation_produces(tmp_path, plugin_path):
    from agents.wrappers import SubWindowPolicy

    policy, sunk = tiny_policy(), []
    runs = evaluate(SubWindowPolicy(policy, 3), "synthetic-mini", window_size=2, max_windows=4, progress=False,
                    flow_sink=lambda reader, window, flow: sunk.append(flow))
    out = tmp_path / "flow.h5"
    predict(policy, "synthetic-mini", out, window_size=2, split=3, progress=False, video=None)
    with h5py.File(out, "r") as f:
        assert f.attrs["split"] == 3 and len(f["flow"]) >= 4
        np.testing.assert_array_equal(f["flow"][:4], np.stack(sunk[:runs[0].windows][:4]).astype(np.float16))
    with pytest.raises(ValueError, match="split"):
        predict(policy, "synthetic-mini", tmp_path / "bad.h5", split=0, progress=False, video=None)


def test_predict_carries_the_recurrent_state(tmp_path, plugin_path):
    """A window's flow depends on the windows before it (the state is carried): the same window
    predicted as the first of a cut span (--start/--end, fresh state) differs."""
    policy = tiny_policy()
    out = tmp_path / "all.h5"
    predict(policy, "synthetic-mini", out, window="time", window_size=20_000, progress=False)
    cut = tmp_path / "cut.h5"
    predict(policy, "synthetic-mini", cut, window="time", window_size=20_000, start_s=0.1, end_s=0.2, progress=False)
    with h5py.File(out, "r") as a, h5py.File(cut, "r") as b:
        t0 = a["t_start"][0]
        assert b["t_start"][0] == t0 + 100_000 and b["t_end"][-1] <= t0 + 200_000 and len(b["t_start"]) == 5
        k = int(np.searchsorted(a["t_start"][:], b["t_start"][0]))
        assert not np.array_equal(a["flow"][k], b["flow"][0])  # fresh state at the cut's first window


def test_an_interrupted_prediction_leaves_no_file(tmp_path, plugin_path, monkeypatch):
    policy = tiny_policy()
    calls = []
    real = policy.act

    def interrupted(obs):
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return real(obs)

    monkeypatch.setattr(policy, "act", interrupted)
    out = tmp_path / "out" / "flow.h5"
    with pytest.raises(KeyboardInterrupt):
        predict(policy, "synthetic-mini", out, window="time", window_size=20_000, video=tmp_path / "out" / "v.gif",
                progress=False)
    assert len(calls) == 3 and not (tmp_path / "out").exists()  # no file, and not the folder it made either


def test_predict_script_on_a_prophesee_file_with_per_event_flow(tmp_path, plugin_path, monkeypatch, rng):
    import json

    from test_prophesee import evt3_words, raw_header, sorted_events, write

    from envs.readers import open_recording
    from tests.conftest import load_script

    monkeypatch.setenv("EVFLOW_CACHE", str(tmp_path / "cache"))
    x, y, t, p = sorted_events(rng, 5000, (48, 64), 1_000, 300_000, clustered=True)
    raw = write(tmp_path / "cam.raw", raw_header("EVT3", (48, 64)), evt3_words(x, y, t, p)[0])
    script = load_script("scripts/predict.py")
    out = tmp_path / "out" / "cam.flow.h5"
    assert script.main([str(raw), "--model", "plugin_example.tiny_flow:build", "--out", str(out), "--per-event",
                        "--window", "time", "--window-size", "25000", "--start", "0.05", "--json",
                        str(tmp_path / "out" / "summary.json"), "--no-progress"]) == 0
    assert sorted(f.name for f in out.parent.iterdir()) == ["cam.flow.h5", "cam.gif", "summary.json"]
    summary = json.loads((out.parent / "summary.json").read_text())
    assert summary["model"]["kind"] == "untrained" and summary["aee"] is None and summary["hmc"] > 0
    with h5py.File(out, "r") as f, open_recording(raw) as reader:
        assert f.attrs["window"] == "time" and f.attrs["window_size"] == 25_000
        assert f["t_start"][0] == t[0] + 50_000  # --start counts from the recording's first event
        flows, offsets, per_event = f["flow"][:], f["event_offsets"][:], f["event_flow"][:]
        for k, (t0, t1) in enumerate(zip(f["t_start"][:], f["t_end"][:])):
            ev = reader.events_between(int(t0), int(t1))
            np.testing.assert_array_equal(per_event[offsets[k] : offsets[k + 1]], flows[k][:, ev.y, ev.x].T)


def test_predict_refuses_to_overwrite(tmp_path, plugin_path):
    """An existing output is kept unless overwrite=True; the recording itself never is replaced."""
    from envs.readers import write_h5
    from tests.conftest import random_events

    recording = write_h5(tmp_path / "rec.h5", random_events(np.random.default_rng(0), 2000, (16, 16), (0, 100_000)))
    before = recording.read_bytes()
    policy = tiny_policy()
    for overwrite in (False, True):
        with pytest.raises(FileExistsError, match="is the input recording"):
            predict(policy, recording, recording, window="time", window_size=20_000, progress=False, overwrite=overwrite)
    assert recording.read_bytes() == before
    out = tmp_path / "flow.h5"
    predict(policy, recording, out, window="time", window_size=20_000, progress=False)
    with pytest.raises(FileExistsError, match="exists; pass overwrite=True"):
        predict(policy, recording, out, window="time", window_size=20_000, progress=False)
    assert predict(policy, recording, out, window="time", window_size=20_000, progress=False, overwrite=True).windows == 5


def test_the_default_model_and_mode_are_the_recorded_choice_named_in_the_provenance():
    from agents.pretrained import DEFAULT_PRETRAINED, default_choice, list_pretrained
    from evflow_cli.predict import load_policy

    choice = default_choice()
    assert choice["model"] == DEFAULT_PRETRAINED and DEFAULT_PRETRAINED in list_pretrained()
    assert "devval" in choice["chosen_on"] and choice["mode"]
    _, provenance = load_policy(None)
    assert provenance["name"] == choice["model"] and provenance["default"]["mode"] == choice["mode"]
    _, named = load_policy(DEFAULT_PRETRAINED)  # named explicitly: no claim about a choice
    assert "default" not in named


def test_predict_without_a_model_runs_the_default_in_its_mode(tmp_path, monkeypatch):
    """No --model: the default model, stepped once per ground-truth interval when default.json's
    mode says so (2-frame windows: 2 steps), the steps named in the file and the provenance; a
    model named explicitly, or --split given, runs as asked."""
    import json as json_module

    import agents.pretrained as pretrained
    from evflow_cli.commands import predict as predict_command

    monkeypatch.setattr(pretrained, "default_choice", lambda directory=None: {
        "model": pretrained.DEFAULT_PRETRAINED, "mode": "split dt", "chosen_on": "devval", "split": "dt"})
    common = ["synthetic-mini", "--window-size", "2", "--end", "0.2", "--no-video", "--no-progress"]

    def run(name: str, *extra: str) -> tuple[int, dict]:
        out, summary = tmp_path / f"{name}.h5", tmp_path / f"{name}.json"
        assert predict_command.main([*common, *extra, "--out", str(out), "--json", str(summary)]) == 0
        with h5py.File(out, "r") as f:
            return int(f.attrs["split"]), json_module.loads(summary.read_text())["model"]

    split, provenance = run("default")
    assert split == 2 and provenance["default"]["split"] == 2 and provenance["default"]["mode"] == "split dt"
    assert run("named", "--model", pretrained.DEFAULT_PRETRAINED)[0] == 1
    assert run("given", "--split", "3")[0] == 3


def _step(index: int, flow: np.ndarray, gt: np.ndarray | None = None):
    """A stand-in for a rollout's step: what the preview reads of it."""
    from types import SimpleNamespace

    h, w = flow.shape[1:]
    count = np.zeros((2, h, w), np.float32)
    count[0, ::2, ::2] = 1.0  # events on every other pixel
    window = SimpleNamespace(t_start=1_000_000 + 10_000 * index, t_end=1_010_000 + 10_000 * index, flow_gt=gt,
                             flow_gt_valid=None if gt is None else np.ones((h, w), bool))
    return SimpleNamespace(index=index, obs={"count_image": count}, flow=flow, window=window)


def test_the_preview_has_one_colour_scale_times_from_the_start_and_the_truth_where_there_is_one():
    from evflow_cli.predict import _Preview, preview_caption

    slow, fast = np.full((2, 32, 48), 1.0, np.float32), np.full((2, 32, 48), 6.0, np.float32)
    preview = _Preview(2, 10, None, False, t0=1_000_000)
    preview.add(_step(0, slow))
    preview.add(_step(1, fast, gt=fast))
    assert preview.scale() == pytest.approx(np.hypot(6.0, 6.0))  # the 99th percentile over both windows
    assert _Preview(2, 10, None, False, t0=0, flow_max=3.0).scale() == 3.0
    first, second = list(preview.frames())
    assert second.shape[1] > first.shape[1]  # the ground-truth tile, where the window has one
    assert preview.items == []  # each frame's data let go once drawn
    assert preview_caption(1_010_000, 1_020_000, 1_000_000).startswith("0.010-0.020 s from the recording's start")


def test_a_gif_shares_one_dithered_palette_and_keeps_the_colours(tmp_path):
    """A colour wheel's hues written to a GIF: every frame on the same palette, and the colours
    of 8 x 8 blocks within a few levels of the original's (dithering keeps local means; a coarse
    per-frame palette bands them)."""
    from PIL import Image

    from envs.visualize import flow_legend, save_animation

    wheel = flow_legend(128)
    frames = [wheel, np.ascontiguousarray(wheel[::-1])]
    path = save_animation(tmp_path / "wheel.gif", iter(frames), fps=5)
    with Image.open(path) as gif:
        palettes, decoded = [], []
        for k in range(gif.n_frames):
            gif.seek(k)
            palettes.append(gif.getpalette())
            decoded.append(np.asarray(gif.convert("RGB"), np.float32))
    assert len(decoded) == 2 and palettes[1] in (None, palettes[0])  # None: no palette of its own, the file's
    for original, back in zip(frames, decoded):
        blocks = lambda a: a[:128, :128].reshape(16, 8, 16, 8, 3).mean(axis=(1, 3))  # noqa: E731
        assert np.abs(blocks(original.astype(np.float32)) - blocks(back)).mean() < 3.0


def test_predict_scores_the_windows_asked_for_and_says_where_the_time_goes(tmp_path, plugin_path):
    from evflow_cli.predict import _spread

    assert _spread(10, 3) == {0, 4, 9} and _spread(5, None) == _spread(5, 9) == set(range(5)) and _spread(5, 0) == set()
    policy = tiny_policy()
    full = predict(policy, "synthetic-mini", tmp_path / "all.h5", window="time", window_size=20_000, progress=False,
                   score_windows=None)
    some = predict(policy, "synthetic-mini", tmp_path / "some.h5", window="time", window_size=20_000, progress=False,
                   score_windows=3)
    assert full.windows == some.windows > 3 and full.scored == full.windows and some.scored == 3
    picked = sorted(_spread(full.windows, 3))
    np.testing.assert_array_equal(some.per_window["hmc"][picked], full.per_window["hmc"][picked])  # the same values
    assert np.isnan(np.delete(some.per_window["hmc"], picked)).all()
    assert set(some.stages) == {"input", "flow", "metrics", "writing", "preview"}
    assert all(v >= 0 for v in some.stages.values()) and sum(some.stages.values()) <= some.seconds * 1.01
    assert full.stages["metrics"] > some.stages["metrics"] and "ms per window: input" in some.where_the_time_goes()
