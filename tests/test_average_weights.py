"""tools/average_weights.py: the averaged network is the (weighted) mean of its sources'
parameters, loads as a checkpoint, and networks that differ are refused by name."""

import pytest
import torch

from agents.checkpoint import load_checkpoint, save_checkpoint
from tests.conftest import load_script


@pytest.fixture(scope="module")
def tool():
    return load_script("tools/average_weights.py")


def _checkpoint(path, step, scale, name="ev-flownet", extra=None):
    model = {"conv.weight": torch.full((2, 3), float(scale)), "conv.bias": torch.arange(2.0) * scale,
             "counter": torch.tensor([7])}
    model.update(extra or {})
    return save_checkpoint(path, {"model_name": name, "model_config": {"width": 4}, "model": model, "step": step})


def test_the_average_is_the_weighted_mean_and_loads(tool, tmp_path):
    a, b = _checkpoint(tmp_path / "a.pt", 10, 1.0), _checkpoint(tmp_path / "b.pt", 30, 4.0)
    out = tmp_path / "avg.pt"
    assert tool.main([str(a), str(b), "--weights", "1", "3", "--out", str(out)]) == 0
    averaged = load_checkpoint(out)
    torch.testing.assert_close(averaged["model"]["conv.weight"], torch.full((2, 3), (1.0 + 3 * 4.0) / 4))
    torch.testing.assert_close(averaged["model"]["conv.bias"], torch.arange(2.0) * 3.25)
    assert averaged["model"]["counter"].tolist() == [7]  # integer buffers: the first's
    assert averaged["model_name"] == "ev-flownet" and averaged["step"] == 30
    assert [s["step"] for s in averaged["averaged_from"]] == [10, 30]
    equal = tool.average_checkpoints([a, b])
    torch.testing.assert_close(equal["model"]["conv.weight"], torch.full((2, 3), 2.5))


def test_other_networks_and_bad_weights_are_refused(tool, tmp_path, capsys):
    a = _checkpoint(tmp_path / "a.pt", 1, 1.0)
    other = _checkpoint(tmp_path / "other.pt", 1, 1.0, name="ev-mgrflownet")
    more = _checkpoint(tmp_path / "more.pt", 1, 1.0, extra={"head.weight": torch.zeros(1)})
    with pytest.raises(ValueError, match="other.pt: model_name 'ev-mgrflownet'"):
        tool.average_checkpoints([a, other])
    with pytest.raises(ValueError, match="more.pt: other network parameters"):
        tool.average_checkpoints([a, more])
    with pytest.raises(SystemExit):
        tool.main([str(a), str(a), "--weights", "1", "--out", str(tmp_path / "x.pt")])
    assert "one non-negative number per checkpoint (2)" in capsys.readouterr().err
    assert not (tmp_path / "x.pt").exists()
