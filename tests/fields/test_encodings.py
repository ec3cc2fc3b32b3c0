import math

import pytest
import torch

from nerf_lightning.fields import ImageField, SinusoidalEncoding


@pytest.mark.parametrize("levels", [0, 1, 10, 40])
def test_width_is_two_plus_four_l_for_image_coordinates(levels):
    encoding = SinusoidalEncoding(in_dim=2, num_frequencies=levels)
    out = encoding(torch.rand(7, 5, 2))
    assert encoding.out_dim == 2 + 4 * levels
    assert out.shape == (7, 5, 2 + 4 * levels)


def test_values_at_known_inputs():
    encoding = SinusoidalEncoding(in_dim=2, num_frequencies=2)
    out = encoding(torch.tensor([[0.5, 0.25]]))[0]
    # [x, y, sin(pi x), sin(pi y), cos(pi x), cos(pi y), sin(2 pi x), sin(2 pi y), cos(2 pi x), cos(2 pi y)]
    s = math.sqrt(0.5)
    expected = torch.tensor([0.5, 0.25, 1.0, s, 0.0, s, 0.0, 1.0, -1.0, 0.0])
    torch.testing.assert_close(out, expected, atol=1e-6, rtol=0)


def test_matches_the_formula_level_by_level():
    x = torch.rand(100, 3)
    levels = 6
    out = SinusoidalEncoding(in_dim=3, num_frequencies=levels)(x)
    torch.testing.assert_close(out[:, :3], x)  # the raw input is kept
    for k in range(levels):
        block = out[:, 3 + 6 * k : 3 + 6 * (k + 1)]
        torch.testing.assert_close(block[:, :3], torch.sin(2**k * math.pi * x))
        torch.testing.assert_close(block[:, 3:], torch.cos(2**k * math.pi * x))


def test_without_input():
    out = SinusoidalEncoding(in_dim=2, num_frequencies=3, include_input=False)(torch.zeros(4, 2))
    assert out.shape == (4, 12)
    torch.testing.assert_close(out, torch.tensor([0.0, 0.0, 1.0, 1.0] * 3).expand(4, 12))


def test_wrong_coordinate_count_is_named():
    with pytest.raises(ValueError, match=r"expected \(\.\.\., 2\) coordinates, got \(4, 3\)"):
        SinusoidalEncoding(in_dim=2, num_frequencies=3)(torch.zeros(4, 3))


def test_image_field_outputs_colours_in_unit_range():
    torch.manual_seed(0)
    field = ImageField(num_frequencies=4, hidden_width=32, hidden_layers=2)
    with torch.no_grad():
        for parameter in field.parameters():
            parameter.mul_(50.0)  # saturate: outputs must still stay in [0, 1]
    rgb = field(torch.rand(1000, 2) * 4 - 2)
    assert rgb.shape == (1000, 3)
    assert rgb.min() >= 0.0 and rgb.max() <= 1.0
    assert rgb.min() < 0.01 and rgb.max() > 0.99  # the sigmoid really saturates, on both sides


def test_image_field_layers():
    field = ImageField(num_frequencies=10, hidden_width=256, hidden_layers=3)
    linears = [m for m in field.modules() if isinstance(m, torch.nn.Linear)]
    assert [(m.in_features, m.out_features) for m in linears] == [(42, 256), (256, 256), (256, 256), (256, 3)]
