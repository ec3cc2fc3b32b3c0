import pytest
import torch

from nerf_lightning.fields import NeRFField


def test_paper_architecture():
    field = NeRFField()
    widths = [(layer.in_features, layer.out_features) for layer in field.trunk]
    # 63 encoded position features in, the encoded position concatenated again after the fifth layer
    assert widths == [(63, 256)] + [(256, 256)] * 4 + [(256 + 63, 256)] + [(256, 256)] * 2
    assert (field.view.in_features, field.view.out_features) == (256 + 27, 128)
    assert (field.rgb_head.in_features, field.density_head.in_features) == (128, 256)


def test_outputs_and_view_dependence():
    torch.manual_seed(0)
    field = NeRFField(hidden_width=64, hidden_layers=4, skip_layer=1, view_width=32, density_activation="softplus")
    points = torch.randn(10, 7, 3)
    directions = torch.nn.functional.normalize(torch.randn(10, 7, 3), dim=-1)
    out = field(points, directions)
    assert out["rgb"].shape == (10, 7, 3) and out["density"].shape == (10, 7)
    assert (out["rgb"] > 0).all() and (out["rgb"] < 1).all() and (out["density"] >= 0).all()
    # density depends on position only; colour on the direction too
    other = field(points, -directions)
    torch.testing.assert_close(other["density"], out["density"])
    assert not torch.allclose(other["rgb"], out["rgb"])
    torch.testing.assert_close(field.density(points), out["density"])


def test_bad_sizes_are_refused():
    with pytest.raises(ValueError, match="skip_layer"):
        NeRFField(hidden_layers=4, skip_layer=4)
    with pytest.raises(ValueError, match="density_activation"):
        NeRFField(density_activation="exp")
