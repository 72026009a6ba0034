import dataclasses
from collections import Counter

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from gymnasium.vector import AutoresetMode

from envs.env import EventFlowEnv
from envs.readers import H5Reader
from envs.windows import Window
from losses import EventBatch, hmc_loss, window_loss, zero_flow_loss
from tests.recordings import write_translating_recording


@pytest.fixture
def recording(tmp_path):
    return write_translating_recording(tmp_path / "dots.h5", np.random.default_rng(5))


def test_check_env_on_h5_file(recording):
    env = EventFlowEnv(recording, observations=("count_image", "voxel_grid", "events"), max_events=500)
    check_env(env, skip_render_check=True)


def test_episode_delivers_every_event_once_in_order(recording):
    env = EventFlowEnv(recording, window="time", window_size=7_000)
    obs, info = env.reset(seed=0)
    ts, bounds, truncated = [info["window"].events.t], [(info["window"].t_start, info["window"].t_end)], False
    while not truncated:
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert not terminated
        if not truncated:
            ts.append(info["window"].events.t)
            bounds.append((info["window"].t_start, info["window"].t_end))
    with H5Reader(recording) as reader:
        np.testing.assert_array_equal(np.concatenate(ts), reader.events_range(0, reader.num_events).t)
        assert bounds[0][0] == reader.t_start and bounds[-1][1] == reader.t_end
    assert all(a[1] == b[0] for a, b in zip(bounds, bounds[1:]))


def test_reward_equals_hmc_on_info_events(recording):
    env = EventFlowEnv(recording)
    obs, info = env.reset(seed=1)
    rng = np.random.default_rng(0)
    for _ in range(4):
        action = rng.normal(0, 2, env.action_space.shape).astype(np.float32)
        window = info["window"]
        batch = EventBatch.from_windows([window])
        zero = hmc_loss(torch.zeros(1, *env.action_space.shape), batch, flow_scaling=env.flow_scaling)
        # the env's border rule: + 1.0 x zero-flow loss x share of splat weight pushed out, ramped over 16 px
        expected = hmc_loss(torch.from_numpy(action)[None], batch, flow_scaling=env.flow_scaling,
                            border_penalty=1.0 * zero.per_sample, border_ramp=16.0)
        obs, reward, _, _, info = env.step(action)
        assert isinstance(reward, float)
        assert reward == pytest.approx(-float(expected.loss), rel=1e-6)
        assert info["reward_components"]["at"] == pytest.approx(float(expected.components["at"][0]), rel=1e-6)


def test_training_batched_loss_is_minus_the_reward(tmp_path):
    """The learner's batched path (the B envs' windows of ``info["window"]`` padded into one
    EventBatch, their zero-flow loss once, ``window_loss`` with TrainConfig's weights and readings,
    the WindowLoss objective) gives each window the env's -reward for the same flow, border rule
    included; one window scored alone gives the same."""
    from agents.learner import TrainConfig
    from agents.objectives import RolloutWindow, loss_options, make_objective, windows_from_info

    recordings = [write_translating_recording(tmp_path / f"r{i}.h5", np.random.default_rng(i), velocity=v)
                  for i, v in enumerate(((200.0, 60.0), (-90.0, 300.0)))]
    num_envs = 3  # windows of different lengths: the batch pads them
    envs = gymnasium.vector.SyncVectorEnv(
        [lambda i=i: EventFlowEnv(recordings, window="time", window_size=9_000 + 6_000 * i, random_start=True,
                                  flips=True) for i in range(num_envs)],
        autoreset_mode=AutoresetMode.SAME_STEP)  # as the learner's
    cfg = TrainConfig(num_envs=num_envs)
    height, width = envs.single_action_space.shape[1:]
    flow_scaling = float(max(height, width))  # the learner's and the env's default
    options = loss_options(cfg, flow_scaling)
    objective = make_objective(cfg, flow_scaling)
    rng = np.random.default_rng(3)
    _, info = envs.reset(seed=0)
    charged = False
    for _ in range(5):
        # per env a different constant push (0, 12 and 40 px: some events leave the frame) plus noise
        push = np.array([0.0, 12.0, -40.0], np.float32).reshape(num_envs, 1, 1, 1)
        flows = torch.from_numpy(push + rng.normal(0, 2, (num_envs, 2, height, width)).astype(np.float32))
        windows = windows_from_info(info, num_envs)
        assert all(isinstance(w, Window) for w in windows) and len({len(w.events) for w in windows}) > 1
        batch = EventBatch.from_windows(windows)
        zero = zero_flow_loss(flows, batch, cfg.weights, **options)
        batched = window_loss(flows, batch, cfg.weights, zero_flow=zero.per_sample, **options)
        trained, _ = objective([RolloutWindow([flows], batch, zero, info)])
        paper = window_loss(flows, batch, dataclasses.replace(cfg.weights, border_penalty=0.0), **options)
        charged |= bool((batched.per_sample > paper.per_sample * (1 + 1e-3)).any())
        _, reward, _, _, info = envs.step(flows.numpy())
        np.testing.assert_allclose(batched.per_sample.numpy(), -reward, rtol=1e-6)
        assert float(trained) == pytest.approx(float(np.mean(-reward)), rel=1e-6)
        for i, window in enumerate(windows):  # one at a time, with its own zero-flow reference
            alone = window_loss(flows[i : i + 1], window, cfg.weights, **options)
            assert float(alone.loss) == pytest.approx(-float(reward[i]), rel=1e-6)
    assert charged  # the border rule was part of what matched
    envs.close()


def test_reward_parity_without_border_rule_is_the_paper_loss(recording):
    env = EventFlowEnv(recording, border_penalty=0.0)
    _, info = env.reset(seed=1)
    action = np.random.default_rng(1).normal(0, 3, env.action_space.shape).astype(np.float32)
    window = info["window"]
    expected = hmc_loss(torch.from_numpy(action)[None], EventBatch.from_windows([window]), flow_scaling=env.flow_scaling)
    _, reward, *_ = env.step(action)
    assert reward == pytest.approx(-float(expected.loss), rel=1e-6)


@pytest.mark.parametrize("data", ["file", "synthetic-mini"])
def test_pushing_events_out_of_the_frame_does_not_pay(recording, data):
    # an action bound far beyond the frame, so that a constant action can push every event out
    env = EventFlowEnv(str(recording) if data == "file" else data, flow_limit=1e4)
    paper = EventFlowEnv(str(recording) if data == "file" else data, flow_limit=1e4, border_penalty=0.0)
    huge = np.full(env.action_space.shape, env.flow_limit, np.float32)  # every event leaves the frame
    zero = np.zeros(env.action_space.shape, np.float32)
    half = np.full(env.action_space.shape, env.height / 2, np.float32)  # about half the events leave
    for sequence in range(len(env.sources)):
        rewards, kept = {}, {}
        for name, e in (("env", env), ("paper", paper)):
            for action_name, action in (("huge", huge), ("half", half), ("zero", zero)):
                e.reset(options={"sequence": sequence})
                _, rewards[name, action_name], *_, info = e.step(action)
                kept[action_name] = info["reward_components"]["kept"]
        assert rewards["env", "zero"] == rewards["paper", "zero"]  # nothing leaves with zero flow
        zero_loss = -rewards["paper", "zero"]
        for action_name in ("huge", "half"):
            assert rewards["env", action_name] < rewards["env", "zero"]
            # the rule's term: 1.0 x zero-flow loss x sum over s of the share pushed out, each
            # event's share ramped by how far out it lands: the whole share once 16 px beyond
            penalty = rewards["paper", action_name] - rewards["env", action_name]
            full = 2 * zero_loss * (1 - kept[action_name])
            assert 0 < penalty <= full * (1 + 1e-5)
            if action_name == "huge":
                assert penalty == pytest.approx(full, rel=1e-2)
        assert kept["huge"] < 0.05 and kept["half"] < 0.9


def test_ground_truth_beats_zero_flow(recording):
    env = EventFlowEnv(recording)
    _, info = env.reset(seed=0)
    totals = {"gt": 0.0, "zero": 0.0}
    for _ in range(6):
        window = info["window"]
        batch = EventBatch.from_windows([window])
        for name, flow in (("gt", info["flow_gt"]), ("zero", np.zeros_like(info["flow_gt"]))):
            totals[name] += float(hmc_loss(torch.from_numpy(flow)[None], batch, flow_scaling=env.flow_scaling).loss)
        _, _, _, truncated, info = env.step(info["flow_gt"])
        if truncated:
            break
    assert totals["gt"] < totals["zero"]


def test_flips_transform_events_and_ground_truth(recording):
    plain = EventFlowEnv(recording)
    flipped = EventFlowEnv(recording, flips=("h", "v", "p"))
    _, a = plain.reset(options={"sequence": 0})
    for seed in range(200):  # find a seed where all three flips are drawn
        _, b = flipped.reset(seed=seed, options={"sequence": 0})
        if all(flipped._flips.values()):
            break
    assert all(flipped._flips.values())
    w = plain.width
    h = plain.height
    np.testing.assert_array_equal(b["window"].events.x, w - 1 - a["window"].events.x)
    np.testing.assert_array_equal(b["window"].events.y, h - 1 - a["window"].events.y)
    np.testing.assert_array_equal(b["window"].events.p, -a["window"].events.p)
    np.testing.assert_array_equal(b["flow_gt"][:, ::-1, ::-1], -a["flow_gt"])


def test_crop_shifts_events_and_ground_truth(recording):
    full = EventFlowEnv(recording)
    cropped = EventFlowEnv(recording, crop=(5, 7, 20, 30))
    _, a = full.reset(options={"sequence": 0})
    _, b = cropped.reset(options={"sequence": 0})
    keep = (a["window"].events.x >= 7) & (a["window"].events.x < 37) & (a["window"].events.y >= 5) & (a["window"].events.y < 25)
    np.testing.assert_array_equal(b["window"].events.x, a["window"].events.x[keep] - 7)
    np.testing.assert_array_equal(b["flow_gt"], a["flow_gt"][:, 5:25, 7:37])
    assert cropped.action_space.shape == (2, 20, 30)


def test_random_crop_moves_per_episode_and_matches_a_fixed_crop(recording):
    env = EventFlowEnv(recording, crop=(20, 30), random_crop=True)
    full = EventFlowEnv(recording)
    _, a = full.reset(options={"sequence": 0})
    origins = set()
    for seed in range(8):
        _, b = env.reset(seed=seed, options={"sequence": 0})
        top, left = env._origin
        origins.add((top, left))
        assert 0 <= top <= full.height - 20 and 0 <= left <= full.width - 30
        fixed = EventFlowEnv(recording, crop=(top, left, 20, 30))
        _, c = fixed.reset(options={"sequence": 0})
        for key in ("x", "y", "t", "p"):
            np.testing.assert_array_equal(getattr(b["window"].events, key), getattr(c["window"].events, key))
        np.testing.assert_array_equal(b["flow_gt"], a["flow_gt"][:, top : top + 20, left : left + 30])
        # a checkpointed episode continues with the same crop
        env.step(np.zeros(env.action_space.shape, np.float32))
        state = env.episode_state()
        other = EventFlowEnv(recording, crop=(20, 30), random_crop=True)
        other.restore_episode_state(state)
        _, _, _, _, i1 = env.step(np.zeros(env.action_space.shape, np.float32))
        _, _, _, _, i2 = other.step(np.zeros(env.action_space.shape, np.float32))
        np.testing.assert_array_equal(i1["window"].events.x, i2["window"].events.x)
    assert len(origins) > 3
    with pytest.raises(ValueError, match="random_crop"):
        EventFlowEnv(recording, random_crop=True)


def test_event_keep_thins_each_episode_at_its_own_rate_and_keeps_the_motion(recording):
    """event_keep: every window keeps a subset of its events, about the episode's probability of
    them, drawn log-uniformly per episode within the range; the ground truth is untouched and a
    restored episode loads the same thinned windows."""
    full = EventFlowEnv(recording, window="time", window_size=10_000)
    _, a = full.reset(options={"sequence": 0})
    env = EventFlowEnv(recording, window="time", window_size=10_000, event_keep=(0.1, 0.8))
    rates = []
    for seed in range(40):
        _, b = env.reset(seed=seed, options={"sequence": 0})
        keep = env._keep[0]
        assert 0.1 <= keep <= 0.8
        rates.append(keep)
        original = Counter(zip(*(getattr(a["window"].events, k).tolist() for k in "xytp")))
        thinned = Counter(zip(*(getattr(b["window"].events, k).tolist() for k in "xytp")))
        assert not thinned - original  # a sub-multiset: nothing added, nothing moved
        assert np.all(np.diff(b["window"].events.t) >= 0)
        n = len(a["window"].events.t)
        assert abs(thinned.total() - keep * n) < 5 * np.sqrt(n * keep * (1 - keep)) + 1  # binomial(n, keep)
        np.testing.assert_array_equal(b["flow_gt"], a["flow_gt"])
    # log-uniform: about half of the draws below the geometric mean of the range
    assert 10 <= sum(r < np.sqrt(0.1 * 0.8) for r in rates) <= 30
    env.step(np.zeros(env.action_space.shape, np.float32))
    state = env.episode_state()
    other = EventFlowEnv(recording, window="time", window_size=10_000, event_keep=(0.1, 0.8))
    other.restore_episode_state(state)
    assert other.current_window is not None
    np.testing.assert_array_equal(other.current_window.events.t, env.current_window.events.t)
    _, _, _, _, i1 = env.step(np.zeros(env.action_space.shape, np.float32))
    _, _, _, _, i2 = other.step(np.zeros(env.action_space.shape, np.float32))
    np.testing.assert_array_equal(i1["window"].events.x, i2["window"].events.x)
    # 1 keeps everything and draws nothing: the episodes of a plain env, random crops and flips too
    plain = EventFlowEnv(recording, window="time", window_size=10_000, crop=(20, 30), random_crop=True, flips=True)
    same = EventFlowEnv(recording, window="time", window_size=10_000, crop=(20, 30), random_crop=True, flips=True,
                        event_keep=(1.0, 1.0))
    for seed in range(5):
        _, c = same.reset(seed=seed)
        _, d = plain.reset(seed=seed)
        for _ in range(3):
            np.testing.assert_array_equal(c["window"].events.x, d["window"].events.x)
            np.testing.assert_array_equal(c["crop"], d["crop"])
            _, _, _, _, c = same.step(np.zeros(same.action_space.shape, np.float32))
            _, _, _, _, d = plain.step(np.zeros(plain.action_space.shape, np.float32))
    for bad in (0.0, 1.5, (0.5, 0.2), (0.1, 0.2, 0.3), True):
        with pytest.raises(ValueError, match="event_keep"):
            EventFlowEnv(recording, event_keep=bad)


def test_window_size_list_draws_one_size_per_episode(recording):
    env = EventFlowEnv(recording, window="time", window_size=[4_000, 9_000])
    seen = set()
    for seed in range(10):
        _, info = env.reset(seed=seed)
        size = info["window"].t_end - info["window"].t_start
        assert size in (4_000, 9_000)
        _, _, _, truncated, info = env.step(np.zeros(env.action_space.shape, np.float32))
        assert truncated or info["window"].t_end - info["window"].t_start == size  # one size per episode
        seen.add(size)
    assert seen == {4_000, 9_000}
    with pytest.raises(ValueError, match="window_size"):
        EventFlowEnv(recording, window="time", window_size=[])


def test_same_seed_same_episode(recording, tmp_path):
    other = write_translating_recording(tmp_path / "other.h5", np.random.default_rng(9), velocity=(10.0, 5.0))
    env = EventFlowEnv([recording, other], window="time", window_size=10_000, random_start=True)
    first = [env.reset(seed=s)[1] for s in (3, 3)]
    assert first[0]["sequence"] == first[1]["sequence"] and first[0]["window"].t_start == first[1]["window"].t_start
    starts = {(info["sequence"], info["window"].t_start) for info in (env.reset(seed=s)[1] for s in range(12))}
    assert len(starts) > 3


def test_options_choose_sequence_and_start(recording):
    env = EventFlowEnv(recording, window="time", window_size=10_000)
    _, info = env.reset(options={"sequence": "dots", "start": 55_000})
    assert info["window"].t_start == 55_000 and info["sequence"] == "dots"
    with pytest.raises(ValueError, match="unknown sequence 'nope'"):
        env.reset(options={"sequence": "nope"})


def test_bad_actions_are_named(recording):
    env = EventFlowEnv(recording)
    with pytest.raises(RuntimeError, match="before reset"):
        env.step(np.zeros(env.action_space.shape, np.float32))
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"shape \(2, 48, 64\)"):
        env.step(np.zeros((2, 64, 48), np.float32))
    with pytest.raises(ValueError, match="dtype int64"):
        env.step(np.zeros(env.action_space.shape, np.int64))
    bad = np.zeros(env.action_space.shape, np.float32)
    bad[1, 3, 4] = np.nan
    with pytest.raises(ValueError, match=r"non-finite value at index \(1, 3, 4\)"):
        env.step(bad)


def test_missing_and_malformed_files_are_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.h5 does not exist"):
        EventFlowEnv(tmp_path / "missing.h5")
    junk = tmp_path / "junk.h5"
    junk.write_bytes(b"not an hdf5 file at all" * 10)
    with pytest.raises(Exception, match="junk.h5"):
        EventFlowEnv(junk)


def test_render_is_side_by_side(recording):
    env = EventFlowEnv(recording, render_mode="rgb_array")
    env.reset(seed=0)
    env.step(np.ones(env.action_space.shape, np.float32))
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.shape == (48, 128, 3)
    assert (frame[:, 64:] != 255).any()  # a non-zero flow is coloured


def test_make_and_make_vec(recording):
    env = gymnasium.make("EventFlow-v0", data=str(recording), max_episode_steps=3)
    env.reset(seed=0)
    for _ in range(3):
        *_, truncated, _ = env.step(env.action_space.sample())
    assert truncated
    for mode in ("sync", "async"):
        vec = gymnasium.make_vec("EventFlow-v0", num_envs=2, vectorization_mode=mode, data=str(recording),
                                 window="time", window_size=9_000, random_start=True)
        obs, _ = vec.reset(seed=0)
        assert obs["count_image"].shape == (2, 2, 48, 64)
        obs, reward, term, trunc, info = vec.step(np.zeros((2, 2, 48, 64), np.float32))
        assert reward.shape == (2,) and np.all(reward < 0)
        assert all(len(info["window"][i].events.x) == len(info["window"][i].events.t) for i in range(2))
        vec.close()


def test_check_env_on_synthetic_default():
    env = gymnasium.make("EventFlow-v0", data="synthetic-mini")
    check_env(env.unwrapped, skip_render_check=True)
    assert env.unwrapped.flow_scaling == 64.0


def test_default_env_needs_no_files():
    env = gymnasium.make("EventFlow-v0")
    obs, info = env.reset(seed=0)
    assert obs["count_image"].shape == (2, 128, 128) and "flow_gt" in info


def test_ground_truth_action_beats_zero_on_synthetic_test_split():
    env = EventFlowEnv("synthetic-test", crop=(128, 128))
    rewards = {"gt": [], "zero": []}
    for sequence in (0, 3, 6, 9):  # slow to fast motion, both resolutions (256 ones centre-cropped, as asked)
        for name in rewards:
            _, info = env.reset(options={"sequence": sequence})
            for _ in range(4):
                action = info["flow_gt"] if name == "gt" else np.zeros(env.action_space.shape, np.float32)
                _, reward, _, truncated, info = env.step(action)
                rewards[name].append(reward)
    print({k: float(np.mean(v)) for k, v in rewards.items()})
    assert np.mean(rewards["gt"]) > np.mean(rewards["zero"])


def test_recordings_of_different_sizes_need_a_crop():
    with pytest.raises(ValueError, match=r"different sensor sizes.*128x128.*256x256"):
        EventFlowEnv("synthetic-test")
    env = EventFlowEnv("synthetic-test", crop=(64, 64))  # asked for: that crop of each
    _, info = env.reset(options={"sequence": "synthetic-test-256-00"})
    assert tuple(info["crop"]) == (96, 96, 64, 64)


def test_explicit_window_list(recording):
    env = EventFlowEnv(recording)
    _, info = env.reset(options={"sequence": 0, "windows": [[30_000, 60_000], [60_000, 120_000]]})
    assert (info["window"].t_start, info["window"].t_end) == (30_000, 60_000)
    np.testing.assert_allclose(info["flow_gt"][0], 200 * 0.03, rtol=1e-5)
    _, _, _, truncated, info = env.step(np.zeros(env.action_space.shape, np.float32))
    assert (info["window"].t_start, info["window"].t_end) == (60_000, 120_000) and not truncated
    valid = info["flow_gt_valid"]  # chained from two stored maps: valid where the path stays on the sensor
    assert 0.7 < valid.mean() < 1.0 and not valid[:, -1].any()  # x moves +6 px per map: the right border leaves
    np.testing.assert_allclose(info["flow_gt"][0][valid], 200 * 0.06, rtol=1e-5)
    *_, truncated, _ = env.step(np.zeros(env.action_space.shape, np.float32))
    assert truncated


def test_async_vector_env_after_torch_use_in_parent(recording):
    """Forked workers must not deadlock in torch after the parent ran torch ops (reward on)."""
    import subprocess
    import sys

    script = f"""
import numpy as np, gymnasium, torch, envs
from envs.env import EventFlowEnv
env = EventFlowEnv({str(recording)!r}); env.reset(seed=0)
env.step(np.zeros(env.action_space.shape, np.float32))
vec = gymnasium.make_vec("EventFlow-v0", num_envs=2, vectorization_mode="async", data={str(recording)!r})
vec.reset(seed=0)
_, reward, *_ = vec.step(np.zeros((2,) + env.action_space.shape, np.float32))
assert np.all(reward < 0)
vec.close()
print("ok")
"""
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0 and "ok" in done.stdout, done.stderr[-2000:]
