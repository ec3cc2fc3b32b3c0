"""The fused numba projection and colour (the no-gradient CPU fast path) against the PyTorch reference, project then
spherical_harmonics: the same footprints in the same order, the same colours, at every SH degree, with and without
antialiasing, from a rotated camera, with Gaussians behind the camera and outside the view."""

from __future__ import annotations

import math

import pytest
import torch

from nerf_lightning.splats.projection import project
from nerf_lightning.splats.projection_fast import project_and_shade
from nerf_lightning.splats.sh import spherical_harmonics
from tests.splats.test_rasterize_pairs import camera

HEIGHT, WIDTH = 37, 53


def scene(n: int = 400, seed: int = 0) -> dict[str, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=generator) * torch.tensor([1.2, 1.0, 1.0])
    means[:5, 2] = -6.0  # behind the camera
    means[5:9, 0] = 30.0  # far outside the view
    return {
        "means": means,
        "quats": torch.randn(n, 4, generator=generator),
        "log_scales": torch.rand(n, 3, generator=generator) * 3.0 - 4.0,
        "opacities": torch.sigmoid(torch.randn(n, generator=generator) * 2.0),
        "sh0": torch.randn(n, 1, 3, generator=generator),
        "shN": torch.randn(n, 15, 3, generator=generator) * 0.3,
    }


def turned_camera() -> tuple[torch.Tensor, torch.Tensor]:
    """The test camera turned 20 degrees about y and moved, so that no axis of the world is one of the camera's."""
    K, c2w = camera(HEIGHT, WIDTH)
    angle = math.radians(20.0)
    turn = torch.tensor([[math.cos(angle), 0.0, math.sin(angle)], [0.0, 1.0, 0.0], [-math.sin(angle), 0.0, math.cos(angle)]])
    c2w = c2w.clone()
    c2w[:3, :3] = turn
    c2w[:3, 3] = torch.tensor([1.3, -0.4, -3.8])
    return K, c2w


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("antialiased", [False, True])
@pytest.mark.parametrize("turned", [False, True])
def test_equal_to_the_reference(degree: int, antialiased: bool, turned: bool) -> None:
    g = scene(seed=degree)
    K, c2w = turned_camera() if turned else camera(HEIGHT, WIDTH)
    reference = project(g["means"], g["quats"], g["log_scales"], g["opacities"], K, c2w, HEIGHT, WIDTH, antialiased)
    directions = g["means"][reference.ids] - c2w[:3, 3]
    coefficients = torch.cat([g["sh0"], g["shN"]], dim=1)[reference.ids]
    reference_colours = spherical_harmonics(degree, coefficients, directions)
    fast, colours = project_and_shade(g["means"], g["quats"], g["log_scales"], g["opacities"], g["sh0"], g["shN"],
                                      degree, K, c2w, HEIGHT, WIDTH, antialiased)
    assert 50 < len(reference.ids) < len(g["means"]) - 9  # some culled, most drawn: the test sees both
    assert torch.equal(fast.ids, reference.ids)
    for name in ("means2d", "conics", "opacities", "depths", "extents"):
        torch.testing.assert_close(getattr(fast, name), getattr(reference, name), atol=1e-5, rtol=1e-5, msg=name)
        assert getattr(fast, name).dtype == torch.float32
    torch.testing.assert_close(colours, reference_colours, atol=1e-5, rtol=1e-5)


def test_an_empty_view_and_shN_without_higher_bands() -> None:
    g = scene(n=20)
    g["means"][:, 2] = -10.0  # all behind the camera
    K, c2w = camera(HEIGHT, WIDTH)
    fast, colours = project_and_shade(g["means"], g["quats"], g["log_scales"], g["opacities"], g["sh0"],
                                      g["shN"][:, :0], 0, K, c2w, HEIGHT, WIDTH)
    assert len(fast.ids) == 0 and colours.shape == (0, 3) and fast.means2d.shape == (0, 2)


def test_a_degree_the_coefficients_do_not_hold_is_refused() -> None:
    g = scene(n=4)
    K, c2w = camera(HEIGHT, WIDTH)
    with pytest.raises(ValueError, match="degree 3"):
        project_and_shade(g["means"], g["quats"], g["log_scales"], g["opacities"], g["sh0"], g["shN"][:, :3], 3, K, c2w,
                          HEIGHT, WIDTH)


def reference_and_fast(g: dict[str, torch.Tensor], degree: int, antialiased: bool, K: torch.Tensor,
                       c2w: torch.Tensor) -> tuple[tuple[torch.Tensor, ...], tuple[torch.Tensor, ...]]:
    """The gradients of the six Gaussian tensors through the reference (in float64: in float32 its own rounding
    reaches 2e-5 of the largest quaternion gradient, the fast path's float64 arithmetic 1e-7) and through the fast
    path (float32), of one loss that weighs every differentiable output (means2d, conics, opacities, depths,
    colours) by fixed random numbers."""

    def gradients(dtype: torch.dtype, draw) -> tuple[torch.Tensor, ...]:
        leaves = {name: value.to(dtype).clone().requires_grad_() for name, value in g.items()}
        projection, colours = draw(leaves, K.to(dtype), c2w.to(dtype))
        generator = torch.Generator().manual_seed(1)
        outputs = (*projection[1:5], colours)
        loss = sum((value * torch.randn(value.shape, generator=generator).to(dtype)).sum() for value in outputs)
        return torch.autograd.grad(loss, list(leaves.values()))

    def reference(leaves, K, c2w):
        projection = project(leaves["means"], leaves["quats"], leaves["log_scales"], leaves["opacities"], K, c2w,
                             HEIGHT, WIDTH, antialiased)
        directions = leaves["means"].index_select(0, projection.ids) - c2w[:3, 3]
        coefficients = torch.cat([leaves["sh0"], leaves["shN"]], dim=1).index_select(0, projection.ids)
        return projection, spherical_harmonics(degree, coefficients, directions)

    def fast(leaves, K, c2w):
        return project_and_shade(*leaves.values(), degree, K, c2w, HEIGHT, WIDTH, antialiased)

    return gradients(torch.float64, reference), gradients(torch.float32, fast)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("antialiased", [False, True])
@pytest.mark.parametrize("turned", [False, True])
def test_gradients_equal_to_the_references(degree: int, antialiased: bool, turned: bool) -> None:
    """Through the conic, the EWA Jacobian (clamped for the Gaussians beside the view), the quaternion and scales,
    the antialiasing compensation and the SH colour's direction, to every Gaussian tensor (Gaussians not drawn: 0)."""
    K, c2w = turned_camera() if turned else camera(HEIGHT, WIDTH)
    expected, fast = reference_and_fast(scene(seed=degree), degree, antialiased, K, c2w)
    for name, want, got in zip(("means", "quats", "log_scales", "opacities", "sh0", "shN"), expected, fast):
        assert got.shape == want.shape and got.dtype == torch.float32, name
        scale = want.abs().max().clamp(min=1e-6)  # gradients span orders of magnitude; compare to the largest
        torch.testing.assert_close(got.double() / scale, want / scale, atol=1e-5, rtol=0.0, msg=name)
    assert expected[0][:5].abs().sum() == 0 and fast[0][:5].abs().sum() == 0  # behind the camera: not drawn


def test_gradients_are_the_same_bit_for_bit_each_time_and_keep_shN_without_higher_bands() -> None:
    g = scene(n=3000, seed=4)
    K, c2w = turned_camera()
    _, first = reference_and_fast(g, 2, True, K, c2w)
    _, second = reference_and_fast(g, 2, True, K, c2w)
    assert all(torch.equal(a, b) for a, b in zip(first, second))
    g["shN"] = g["shN"][:, :0]
    _, fast = reference_and_fast(g, 0, False, K, c2w)
    assert fast[5].shape == (3000, 0, 3)
