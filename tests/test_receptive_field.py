"""tools/receptive_field.py on networks whose receptive field is known by construction."""

import numpy as np
import pytest
import torch

from tests.conftest import load_script


@pytest.fixture(scope="module")
def rf():
    return load_script("tools/receptive_field.py")


def test_a_stack_of_3x3_convolutions_reaches_one_pixel_per_layer(rf):
    torch.manual_seed(0)
    layers = [torch.nn.Conv2d(5, 4, 3, padding=1), torch.nn.Conv2d(4, 4, 3, padding=1), torch.nn.Conv2d(4, 2, 3, padding=1)]
    for layer in layers:
        torch.nn.init.uniform_(layer.weight, 0.5, 1.0)  # positive: no cancellation inside the field
    model = torch.nn.Sequential(*layers)
    grad = rf.gradient_map(model, 5, 33, density=1.0)
    stats = rf.field_stats(grad)
    assert stats["half_width"] == 3  # three 3x3 layers: 7x7
    assert np.count_nonzero(grad) == 49
    assert 0 < stats["radii"][0.5] <= stats["radii"][0.9] <= stats["radii"][0.99] <= 3 * np.sqrt(2)


def test_the_mass_radii_of_a_known_map(rf):
    grad = np.zeros((21, 21))
    grad[10, 10] = 1.0  # half of the mass on the pixel itself
    grad[10, 15] = 1.0  # the other half 5 px away
    stats = rf.field_stats(grad, fractions=(0.5, 0.9))
    assert stats == {"half_width": 5, "radii": {0.5: 0.0, 0.9: 5.0}}


def test_a_tuple_output_reads_the_last_flow(rf):
    class Two(torch.nn.Module):
        def forward(self, x):
            wide = torch.nn.functional.avg_pool2d(x[:, :2], 5, stride=1, padding=2)
            return [x[:, :2] * 0, wide], {}

    grad = rf.gradient_map(Two(), 3, 17, density=1.0)
    assert rf.field_stats(grad)["half_width"] == 2


def test_bad_arguments_are_named(rf, capsys):
    for argv, name in ((["--density", "0"], "--density"), (["--inputs", "0"], "--inputs"), (["--size", "4"], "--size")):
        with pytest.raises(SystemExit):
            rf.main(argv)
        assert name in capsys.readouterr().err
