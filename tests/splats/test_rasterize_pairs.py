"""The splat rasteriser against its dense reference (values and gradients), its pairs against the reference's drawn
pixels, the projection's means against kornia, bands within a pair budget, and no float64 (Apple GPUs)."""

from __future__ import annotations

import math

import pytest
import torch
from kornia.geometry.camera.perspective import project_points

from nerf_lightning.splats.projection import MIN_ALPHA, project
from nerf_lightning.splats.rasterize_core import pixel_boxes
from nerf_lightning.splats.rasterize_pairs import drawn_pairs, footprint_table, rasterize_pairs, row_bands
from nerf_lightning.splats.rasterize_reference import rasterize_reference
from nerf_lightning.splats.sh import SH_C0, rgb_to_sh, spherical_harmonics
from tests.test_devices_and_precision import NoFloat64

HEIGHT, WIDTH = 20, 24


def camera(height: int = HEIGHT, width: int = WIDTH) -> tuple[torch.Tensor, torch.Tensor]:
    """A camera at (0, 0, -4) looking down +z at the origin (OpenCV), focal length about the image's width."""
    K = torch.tensor([[1.1 * width, 0.0, width / 2 + 0.3], [0.0, 1.1 * width, height / 2 - 0.2], [0.0, 0.0, 1.0]])
    c2w = torch.eye(4)
    c2w[2, 3] = -4.0
    return K, c2w


def gaussians(n: int = 60, seed: int = 0) -> dict[str, torch.Tensor]:
    """N Gaussians about the origin, some large, some tiny, a few behind the camera or outside its view."""
    generator = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=generator) * torch.tensor([1.2, 1.0, 1.0])
    means[:3, 2] = -6.0  # behind the camera
    means[3:5, 0] = 30.0  # far outside the view
    return {
        "means": means.requires_grad_(),
        "quats": torch.randn(n, 4, generator=generator).requires_grad_(),
        "log_scales": (torch.rand(n, 3, generator=generator) * 2.5 - 3.5).requires_grad_(),
        "opacity_logits": (torch.randn(n, generator=generator) * 2.0).requires_grad_(),
        "colours": torch.rand(n, 3, generator=generator).requires_grad_(),
    }


def draw(g: dict[str, torch.Tensor], rasteriser, antialiased: bool = False, **options) -> dict[str, torch.Tensor]:
    """The view ``rasteriser`` draws, with its footprints' ``means2d`` (whose ``absgrad`` the backward pass fills)."""
    K, c2w = camera()
    projection = project(g["means"], g["quats"], g["log_scales"], torch.sigmoid(g["opacity_logits"]), K, c2w, HEIGHT, WIDTH, antialiased)
    out = rasteriser(projection, g["colours"][projection.ids], HEIGHT, WIDTH, torch.tensor([0.2, 0.4, 0.9]), **options)
    return {**out, "means2d": projection.means2d}


@pytest.mark.parametrize("antialiased", [False, True])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_rasteriser_equals_the_dense_reference_in_values_and_gradients(seed, antialiased):
    g = gaussians(seed=seed)
    fast, dense = draw(g, rasterize_pairs, antialiased, absgrad=True), draw(g, rasterize_reference, antialiased, absgrad=True)
    for key in ("rgb", "accumulation"):
        torch.testing.assert_close(fast[key], dense[key], atol=1e-5, rtol=1e-5)
    drawn = dense["accumulation"] > 1e-3
    assert drawn.float().mean() > 0.3, "the scene should cover a good part of the image"
    torch.testing.assert_close(fast["depth"][drawn], dense["depth"][drawn], atol=1e-4, rtol=1e-5)
    # one loss over all three outputs, its gradients with respect to every parameter
    weights = torch.rand(HEIGHT, WIDTH, 3, generator=torch.Generator().manual_seed(7))

    def gradients(out):
        loss = (out["rgb"] * weights).sum() + out["accumulation"].sum() + (out["depth"] * drawn).sum() * 0.1
        return torch.autograd.grad(loss, list(g.values()))

    for name, a, b in zip(g, gradients(fast), gradients(dense)):
        assert a.abs().max() > 0 or name == "opacity_logits" and b.abs().max() == 0, name
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-4, msg=f"gradient with respect to {name}")
    # AbsGS's statistic: each pixel's pull on a footprint's centre, summed as absolute values
    torch.testing.assert_close(fast["means2d"].absgrad, dense["means2d"].absgrad, atol=1e-5, rtol=1e-4)
    assert dense["means2d"].absgrad.max() > 0


def test_the_pairs_are_the_pixels_the_reference_draws():
    g = gaussians(seed=3)
    K, c2w = camera()
    with torch.no_grad():
        projection = project(g["means"], g["quats"], g["log_scales"], torch.sigmoid(g["opacity_logits"]), K, c2w, HEIGHT, WIDTH)
        footprint, pixel, _ = drawn_pairs(footprint_table(projection), pixel_boxes(projection, HEIGHT, WIDTH), 0, HEIGHT, WIDTH)
        fast = set(zip(footprint.tolist(), pixel.tolist()))
        # the reference's rule, pair by pair
        v, u = torch.meshgrid(torch.arange(HEIGHT) + 0.5, torch.arange(WIDTH) + 0.5, indexing="ij")
        d = torch.stack([u.reshape(-1), v.reshape(-1)], -1)[None] - projection.means2d[:, None]  # (M, P, 2)
        a, b, c = projection.conics.unbind(-1)
        sigma = 0.5 * (a[:, None] * d[..., 0] ** 2 + c[:, None] * d[..., 1] ** 2) + b[:, None] * d[..., 0] * d[..., 1]
        alpha = projection.opacities[:, None] * torch.exp(-sigma)
        inside = (d.abs() <= projection.extents[:, None]).all(-1) & (alpha >= MIN_ALPHA) & (sigma >= 0)
        dense = set(map(tuple, torch.nonzero(inside).tolist()))
    assert fast == dense and len(fast) > 100


def test_bands_within_a_pair_budget_draw_the_same_image():
    g = gaussians(seed=4)
    whole, banded = draw(g, rasterize_pairs, absgrad=True), draw(g, rasterize_pairs, max_pairs=300, absgrad=True)
    for key in ("rgb", "depth", "accumulation"):
        torch.testing.assert_close(whole[key], banded[key], atol=1e-6, rtol=1e-6)
    for out in (whole, banded):
        out["rgb"].square().sum().backward()
    torch.testing.assert_close(whole["means2d"].absgrad, banded["means2d"].absgrad, atol=1e-6, rtol=1e-5)
    K, c2w = camera()
    with torch.no_grad():
        projection = project(g["means"], g["quats"], g["log_scales"], torch.sigmoid(g["opacity_logits"]), K, c2w, HEIGHT, WIDTH)
    bands = row_bands(pixel_boxes(projection, HEIGHT, WIDTH), HEIGHT, 300)
    assert len(bands) > 2 and bands[0][0] == 0 and bands[-1][1] == HEIGHT
    assert all(stop == next_start for (_, stop), (next_start, _) in zip(bands, bands[1:]))


def test_the_projected_means_are_kornias_projections_and_culling_is_by_the_near_plane_and_the_view():
    g = gaussians(seed=5)
    K, c2w = camera()
    with torch.no_grad():
        projection = project(g["means"], g["quats"], g["log_scales"], torch.sigmoid(g["opacity_logits"]), K, c2w, HEIGHT, WIDTH)
        in_camera = g["means"] @ torch.linalg.inv(c2w)[:3, :3].T + torch.linalg.inv(c2w)[:3, 3]
        expected = project_points(in_camera[projection.ids], K[None].expand(len(projection.ids), 3, 3))
    torch.testing.assert_close(projection.means2d, expected, atol=1e-4, rtol=1e-5)
    ids = set(projection.ids.tolist())
    assert not ids & {0, 1, 2, 3, 4}, "behind the camera or far outside the view"
    assert len(ids) > 40


def test_an_opaque_stack_stops_a_pixel_and_the_background_shows_through_what_is_left():
    """Ten wide Gaussians of opacity 0.95 one behind the other, centred on a pixel's centre: three are drawn there
    (the fourth would take the transmittance to 6e-6 <= 1e-4), and the background shows through the 1.25e-4 left."""
    n = 10
    means = torch.zeros(n, 3)
    means[:, 2] = torch.linspace(0.0, 1.0, n)
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1)
    log_scales = torch.full((n, 3), math.log(2.0))
    opacities = torch.full((n,), 0.95)
    colours = torch.zeros(n, 3)
    colours[0, 0] = 1.0  # the nearest one red, the rest black
    K, c2w = camera()
    K[0, 2], K[1, 2] = 12.5, 10.5  # the means project onto the centre of pixel (10, 12)
    projection = project(means, quats, log_scales, opacities, K, c2w, HEIGHT, WIDTH)
    out = rasterize_pairs(projection, colours[projection.ids], HEIGHT, WIDTH, torch.ones(3))
    left = 0.05**3
    torch.testing.assert_close(out["rgb"][10, 12], torch.tensor([0.95 + left, left, left]), atol=1e-6, rtol=0)
    torch.testing.assert_close(out["accumulation"][10, 12], torch.tensor(1.0 - left), atol=1e-6, rtol=0)
    assert out["depth"][10, 12] < 4.0 + 3 / 9  # the weights' mean depth lies among the first three


def test_no_float64_anywhere_in_a_forward_and_backward():
    g = gaussians(seed=6)
    with NoFloat64():
        out = draw(g, rasterize_pairs)
        (out["rgb"].sum() + out["depth"].sum()).backward()


def test_spherical_harmonics_degree_zero_is_the_colour_and_higher_bands_vary_with_direction():
    rgb = torch.rand(5, 3)
    coefficients = torch.zeros(5, 16, 3)
    coefficients[:, 0] = rgb_to_sh(rgb)
    directions = torch.randn(5, 3)
    torch.testing.assert_close(spherical_harmonics(3, coefficients, directions), rgb)
    coefficients[:, 1:] = torch.randn(5, 15, 3) * 0.3
    seen = [spherical_harmonics(degree, coefficients, directions) for degree in range(4)]
    assert all((a - b).abs().max() > 1e-3 for a, b in zip(seen, seen[1:]))
    assert (spherical_harmonics(3, coefficients, -directions) - seen[3]).abs().max() > 1e-3
    assert SH_C0 == pytest.approx(0.5 / math.sqrt(math.pi))
    with pytest.raises(ValueError, match="degree 3 needs"):
        spherical_harmonics(3, coefficients[:, :9], directions)
