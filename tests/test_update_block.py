"""The learned finish (agents/update_block.py): its inputs against independent references, its
shapes and state, batched against one window at a time, that training it lowers the loss it is
trained on, and its file (loaded without running code, refused by name when it is not one)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from agents.checkpoint import CheckpointError, save_checkpoint
from agents.update_block import FEATURES, UpdateBlock, block_features, learned_finish, load_block
from agents.wrappers.refine import BLOCK, Finish, FinishedPolicy
from envs.windows import Window
from losses import LossSpec, window_loss, zero_flow_loss
from losses.events import EventBatch
from tests.recordings import translating_dots


def _window(rng, size=(20, 28), velocity=(90.0, -45.0), dots=10):
    events, (t0, t1) = translating_dots(rng, sensor_size=size, velocity=velocity, duration_us=66_666,
                                        num_dots=dots, events_per_s=6_000)
    return Window.of(events, t0, t1)


class _Fixed:
    """A policy that proposes one fixed flow."""

    input_key, voxel_bins, device = "count_image", 5, "cpu"

    def __init__(self, proposal) -> None:
        self.proposal = proposal

    def reset(self, mask=None):
        pass

    def act(self, obs, window=None):
        return self.proposal.copy()


def test_the_inputs_are_the_flow_per_frame_the_normalised_gradient_and_the_event_histogram(rng):
    window = _window(rng)
    batch = window.batch()
    H, W = 20, 28
    flow = torch.zeros(1, 2, H, W)
    flow[:, 0] = 1.5
    plain = dict(spec=LossSpec(), flow_scaling=None)  # the env's reward, flow scaling max(H, W)
    features = block_features(flow, batch, torch.tensor([2.0]), scale=4, **plain)
    assert features.shape == (1, len(FEATURES), 5, 7)
    assert torch.allclose(features[:, 0], torch.full((1, 5, 7), 0.75))  # pixels per frame
    assert torch.allclose(features[:, 1], torch.zeros(1, 5, 7))
    assert torch.allclose(features[:, 6], torch.full((1, 5, 7), float(np.log(2.0))))
    # the gradient: autograd of the loss written out here, pooled over 4 x 4 cells, mean magnitude 1
    current = flow.clone().requires_grad_()
    zero = zero_flow_loss(flow, batch, flow_scaling=float(W)).per_sample
    window_loss(current, batch, flow_scaling=float(W), zero_flow=zero).per_sample.sum().backward()
    pooled = F.avg_pool2d(current.grad, 4)
    ref = pooled / pooled.abs().mean()
    zero_features = block_features(flow, batch, torch.tensor([2.0]), scale=4, zero=zero, **plain)
    assert torch.allclose(zero_features[:, 2:4], ref, atol=1e-5)
    assert float(zero_features[:, 2:4].abs().mean()) == pytest.approx(1.0, rel=1e-5)
    # under zero flow the events stay at their integer pixels: the warped image is their histogram
    still = block_features(torch.zeros(1, 2, H, W), batch, torch.tensor([1.0]), scale=4)
    hist = np.zeros((H, W))
    np.add.at(hist, (window.events.y.astype(int), window.events.x.astype(int)), 1.0)
    cells = hist.reshape(5, 4, 7, 4)
    mean, square = cells.mean(axis=(1, 3)), (cells ** 2).mean(axis=(1, 3))
    assert np.allclose(still[0, 4].numpy(), np.log1p(mean), atol=1e-5)
    assert np.allclose(still[0, 5].numpy(), np.log1p(square / (mean + 1e-6)), atol=1e-4)


def test_an_untrained_block_returns_the_proposal_and_its_state_has_the_coarse_grid_shape(rng):
    block = UpdateBlock(hidden=8)
    batch = _window(rng, size=(37, 50)).batch()
    proposal = torch.randn(1, 2, 37, 50)
    finished = learned_finish(block, proposal, batch, steps=3, frames=1.0)
    assert torch.equal(finished, proposal)  # the head starts at zero: the identity
    features = block_features(proposal, batch, torch.tensor([1.0]), scale=block.scale)
    state = block.initial_state(features)
    assert features.shape == (1, 7, 10, 13) and state.shape == (1, 8, 10, 13)
    correction, state = block(features, state)
    assert correction.shape == (1, 2, 10, 13) and state.shape == (1, 8, 10, 13)
    assert float(state.detach().abs().sum()) > 0  # the GRU's state moved: it carries over the iterations
    with pytest.raises(ValueError, match="frames"):
        learned_finish(block, proposal, batch, steps=1, frames=0.0)
    # the correction goes through a grid of ``cells`` along the longer side: one cell, one vector
    uniform = UpdateBlock(hidden=8, cells=1)
    torch.nn.init.normal_(uniform.head[-1].weight, std=0.05)
    moved = learned_finish(uniform, proposal, batch, steps=1, frames=1.0) - proposal
    assert float(moved.abs().max()) > 0
    assert torch.allclose(moved, moved[:, :, :1, :1].expand_as(moved), atol=1e-6)


def test_a_batch_of_windows_is_finished_as_each_window_alone(rng):
    torch.manual_seed(0)
    block = UpdateBlock(hidden=8)
    torch.nn.init.normal_(block.head[-1].weight, std=0.05)  # a block that moves the flow
    windows = [_window(rng, dots=6), _window(rng, velocity=(-30.0, 60.0), dots=12)]
    proposals = torch.randn(2, 2, 20, 28) * 0.5
    frames = torch.tensor([2.0, 1.0])
    together = learned_finish(block, proposals, EventBatch.from_windows(windows), steps=3, frames=frames)
    for b, window in enumerate(windows):
        alone = learned_finish(block, proposals[b:b + 1], window.batch(), steps=3, frames=frames[b])
        assert torch.allclose(together[b:b + 1], alone, atol=1e-5)
    assert not torch.allclose(together, proposals)


def test_training_the_block_lowers_the_loss_after_its_finish_toward_the_true_motion(rng):
    """40 Adam updates on one window of dots moving 3 px right and 1.5 px up over it, from zero
    flow: the loss after the finish falls, and the flow it learned is the dots' motion."""
    torch.manual_seed(0)
    H, W = 32, 40
    events, (t0, t1) = translating_dots(rng, sensor_size=(H, W), velocity=(45.0, -22.5), duration_us=66_666,
                                        num_dots=12, events_per_s=8_000)
    batch = Window.of(events, t0, t1).batch()
    proposal = torch.zeros(1, 2, H, W)
    zero = zero_flow_loss(proposal, batch, flow_scaling=float(W)).per_sample

    def loss_of(flow):
        return window_loss(flow, batch, flow_scaling=float(W), zero_flow=zero).per_sample.sum()

    truth = torch.stack([torch.full((H, W), 3.0), torch.full((H, W), -1.5)])[None]
    assert float(loss_of(truth)) < float(loss_of(proposal))  # the case: the true motion has the lower loss
    block = UpdateBlock(hidden=8)
    optimizer = torch.optim.Adam(block.parameters(), lr=3e-3)
    with torch.no_grad():
        before = float(loss_of(learned_finish(block, proposal, batch, steps=2, frames=2.0)))
    for _ in range(40):
        optimizer.zero_grad()
        loss_of(learned_finish(block, proposal, batch, steps=2, frames=2.0)).backward()
        optimizer.step()
    with torch.no_grad():
        flow = learned_finish(block, proposal, batch, steps=2, frames=2.0)
    assert float(loss_of(flow)) < 0.9 * before
    assert abs(float(flow[0, 0].mean()) - 3.0) < 0.6 and abs(float(flow[0, 1].mean()) + 1.5) < 0.6


def test_the_block_file_round_trips_and_anything_else_is_refused_by_name(tmp_path, rng):
    torch.manual_seed(1)
    block = UpdateBlock(hidden=8)
    torch.nn.init.normal_(block.head[-1].weight, std=0.05)
    path = tmp_path / "block.pt"
    save_checkpoint(path, {"kind": "evflow-update-block", "block": block.state_dict(), "block_config": block.config()})
    loaded, _ = load_block(path)
    batch = _window(rng).batch()
    proposal = torch.zeros(1, 2, 20, 28)
    with torch.no_grad():
        assert torch.equal(learned_finish(loaded, proposal, batch, steps=2, frames=1.0),
                           learned_finish(block.eval(), proposal, batch, steps=2, frames=1.0))
    other = tmp_path / "network.pt"
    save_checkpoint(other, {"kind": "something-else", "model": {}})
    with pytest.raises(ValueError, match="network.pt.*not an update block"):
        load_block(other)
    broken = tmp_path / "broken.pt"
    save_checkpoint(broken, {"kind": "evflow-update-block", "block": {"nope": torch.zeros(1)}, "block_config": {}})
    with pytest.raises(ValueError, match="broken.pt.*do not load"):
        load_block(broken)
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="junk.pt"):
        load_block(tmp_path / "junk.pt")


def test_a_block_finish_in_the_finished_policy_is_the_learned_finish(rng):
    torch.manual_seed(2)
    block = UpdateBlock(hidden=8).eval()
    torch.nn.init.normal_(block.head[-1].weight, std=0.05)
    window = _window(rng)
    proposal = np.full((2, 20, 28), 0.7, np.float32)

    with pytest.raises(ValueError, match="block"):
        FinishedPolicy(_Fixed(proposal), [Finish(BLOCK, 2)])
    policy = FinishedPolicy(_Fixed(proposal), [Finish(BLOCK, 2)], block=block)
    with torch.no_grad():
        ref = learned_finish(block, torch.as_tensor(proposal)[None], window.batch(), steps=2, frames=2.0)
    assert np.allclose(policy.act(None, window), ref[0].numpy(), atol=1e-6)


def test_train_block_trains_writes_a_loadable_block_resumes_and_refuses_devval(tmp_path, capsys):
    from evflow_cli.commands import train_block
    from tests.recordings import write_translating_recording

    recording = write_translating_recording(tmp_path / "dots.h5", np.random.default_rng(3), sensor_size=(32, 40),
                                            duration_us=200_000, velocity=(60.0, -30.0), events_per_s=20_000)
    out = tmp_path / "block"
    argv = ["--data", str(recording), "--dt", "1", "2", "--windows", "2", "--minutes", "0.002", "--batch", "1",
            "--hidden", "4", "--iterations", "2", "--out", str(out), "--no-progress"]
    assert train_block.main(argv) == 0
    block, payload = load_block(out / "block.pt")
    assert payload["updates"] >= 1 and payload["curve"] and block.hidden == 4
    assert (out / "curve.json").exists()
    with pytest.raises(FileExistsError, match="--resume"):
        train_block.main(argv)
    collected = train_block.collect(train_block.TrainBlockOptions(data=str(recording), dt=[1, 2], windows=2,
                                                                  out=str(out), no_progress=True))
    assert "from" in capsys.readouterr().out  # the proposals come back from OUT/proposals.npz
    fresh = train_block.collect(train_block.TrainBlockOptions(data=str(recording), dt=[1, 2], windows=2,
                                                              out=str(tmp_path / "fresh"), no_progress=True))
    assert len(collected) == len(fresh) == 4
    for (w1, p1), (w2, p2) in zip(collected, fresh):  # the cache round trip: the same windows and proposals
        assert (w1.t_start, w1.t_end) == (w2.t_start, w2.t_end) and np.array_equal(p1, p2)
        assert all(np.array_equal(getattr(w1.events, k), getattr(w2.events, k)) for k in "xytp")
    assert train_block.main(argv + ["--resume"]) == 0
    _, resumed = load_block(out / "block.pt")
    assert resumed["updates"] > payload["updates"]
    with pytest.raises(ValueError, match="devval"):
        train_block.main(["--data", "../shared/devval", "--out", str(tmp_path / "x")])
    # the teacher's target: the --cmax solve from zero flow of each window, kept beside the proposals
    taught = tmp_path / "taught"
    assert train_block.main([*argv[:-3], "--out", str(taught), "--target", "teacher", "--no-progress"]) == 0
    pairs = train_block.collect(train_block.TrainBlockOptions(data=str(recording), dt=[1, 2], windows=2,
                                                              out=str(taught), no_progress=True))
    flows = train_block.teacher_flows(pairs, train_block.TrainBlockOptions(data=str(recording), dt=[1, 2], windows=2,
                                                                           out=str(taught), no_progress=True))
    assert "teacher flows from" in capsys.readouterr().out
    from agents.cmax import CMaxSettings

    assert np.allclose(flows[-1], CMaxSettings().solve(pairs[-1][0], pairs[-1][1].shape[-2:]), atol=1e-5)


def test_block_steps_before_a_solve_are_the_block_then_that_solve(rng):
    from agents.wrappers.refine import finish_settings

    torch.manual_seed(3)
    block = UpdateBlock(hidden=8).eval()
    torch.nn.init.normal_(block.head[-1].weight, std=0.05)
    window = _window(rng)
    proposal = np.full((2, 20, 28), 0.4, np.float32)

    finish = Finish.from_dict({"solver": "fine", "steps": 3, "block_steps": 2})
    with pytest.raises(ValueError, match="block"):
        FinishedPolicy(_Fixed(proposal), [finish])
    with pytest.raises(ValueError, match="block_steps"):
        Finish("fine", 3, block_steps=-1)
    policy = FinishedPolicy(_Fixed(proposal), [finish], block=block)
    with torch.no_grad():
        moved = learned_finish(block, torch.as_tensor(proposal)[None], window.batch(), steps=2, frames=2.0)[0].numpy()
    expected = finish_settings("fine", 3).solve(window, (20, 28), base=moved)
    assert np.allclose(policy.act(None, window), expected, atol=1e-5)
