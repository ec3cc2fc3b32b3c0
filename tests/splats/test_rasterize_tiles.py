"""The tile rasterisers, numba's on the CPU and Triton's (on a GPU where there is one, else in Triton's interpreter;
skipped without Triton), against the dense reference, in values and gradients, on random scenes, an empty view,
footprints across tile and image borders, pixels that stop early, crowded tiles, antialiasing, masks and patches; the
numba rasteriser's gradients the same bit for bit on a second run."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
import torch

from nerf_lightning.splats.projection import Projection, project
from nerf_lightning.splats.rasterize_pairs import rasterize_pairs
from nerf_lightning.splats.rasterize_reference import rasterize_reference
from nerf_lightning.splats.rasterize_tiles import TILE, depth_keys, fade, nearest_first, rasterize_tiles
from tests.splats.test_rasterize_pairs import camera, gaussians

BACKGROUND = torch.tensor([0.2, 0.4, 0.9])
# where Triton's kernels run in the tests: the GPU, else its interpreter on the CPU (tests/conftest.py asks for it)
TRITON_DEVICE = "cuda" if torch.cuda.is_available() else "cpu"


def rasterize_triton_here(projection: Projection, colours: torch.Tensor, height: int, width: int,
                          background: torch.Tensor, absgrad: bool = False) -> dict[str, torch.Tensor]:
    """rasterize_triton on :data:`TRITON_DEVICE`, its outputs brought back to the CPU (differentiably: the gradients
    reach the CPU's leaves)."""
    from nerf_lightning.splats.rasterize_triton import rasterize_triton

    moved = Projection(*(value.to(TRITON_DEVICE) for value in projection))
    out = rasterize_triton(moved, colours.to(TRITON_DEVICE), height, width, background.to(TRITON_DEVICE), absgrad)
    if moved.means2d is not projection.means2d and hasattr(moved.means2d, "absgrad"):
        projection.means2d.absgrad = moved.means2d.absgrad  # on the GPU, where the backward pass fills it
    return {key: value.cpu() for key, value in out.items()}


# the tile rasterisers the equality tests hold to the dense reference
TILE_RASTERISERS = [
    pytest.param(rasterize_tiles, id="numba"),
    pytest.param(rasterize_triton_here, id="triton",
                 marks=pytest.mark.skipif(importlib.util.find_spec("triton") is None, reason="Triton is not installed")),
]


def drawn(g: dict[str, torch.Tensor], rasteriser, height: int, width: int, antialiased: bool = False,
          K: torch.Tensor | None = None, **options) -> dict[str, torch.Tensor]:
    """The view ``rasteriser`` draws, with its footprints' ``means2d`` (whose ``absgrad`` the backward pass fills)."""
    K0, c2w = camera(height, width)
    projection = project(g["means"], g["quats"], g["log_scales"], torch.sigmoid(g["opacity_logits"]),
                         K0 if K is None else K, c2w, height, width, antialiased)
    return {**rasteriser(projection, g["colours"][projection.ids], height, width, BACKGROUND, **options),
            "means2d": projection.means2d}


def assert_equal_to_dense(g: dict[str, torch.Tensor], height: int, width: int, antialiased: bool = False,
                          mask: torch.Tensor | None = None, K: torch.Tensor | None = None,
                          rasteriser=rasterize_tiles) -> dict[str, torch.Tensor]:
    """Values and the gradients of one loss over rgb, accumulation and depth, and the footprints' absolute
    screen-space gradients (``means2d.absgrad``), ``rasteriser`` (the tiles) against dense, to 1e-5."""
    tiles = drawn(g, rasteriser, height, width, antialiased, K, absgrad=True)
    dense = drawn(g, rasterize_reference, height, width, antialiased, K, absgrad=True)
    for key in ("rgb", "accumulation"):
        torch.testing.assert_close(tiles[key], dense[key], atol=1e-5, rtol=1e-5)
    covered = dense["accumulation"] > 1e-3
    torch.testing.assert_close(tiles["depth"][covered], dense["depth"][covered], atol=1e-4, rtol=1e-5)
    weights = torch.rand(height, width, 3, generator=torch.Generator().manual_seed(7))
    target = torch.rand(height, width, 3, generator=torch.Generator().manual_seed(8))

    def gradients(out):
        rgb = out["rgb"] if mask is None else torch.where(mask[..., None], out["rgb"], target)  # data.masks=exclude's rule
        loss = (rgb * weights).sum() + out["accumulation"].sum() + (out["depth"] * covered).sum() * 0.1
        return torch.autograd.grad(loss, list(g.values()))

    for name, a, b in zip(g, gradients(tiles), gradients(dense)):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-4, msg=f"gradient with respect to {name}")
    torch.testing.assert_close(tiles["means2d"].absgrad.cpu(), dense["means2d"].absgrad, atol=1e-5, rtol=1e-4)
    assert dense["means2d"].absgrad.max() > 0
    return tiles


@pytest.mark.parametrize("rasteriser", TILE_RASTERISERS)
@pytest.mark.parametrize("antialiased", [False, True])
@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_the_tile_rasteriser_equals_the_dense_reference_in_values_and_gradients(seed, antialiased, rasteriser):
    out = assert_equal_to_dense(gaussians(seed=seed), 20, 24, antialiased, rasteriser=rasteriser)
    assert (out["accumulation"] > 1e-3).float().mean() > 0.3, "the scene should cover a good part of the image"


@pytest.mark.parametrize("rasteriser", TILE_RASTERISERS)
def test_footprints_across_tile_and_image_borders(rasteriser):
    # an image of 2 x 3 tiles and a bit (not a multiple of the tile), large Gaussians reaching over every border
    height, width = 2 * TILE + 5, 3 * TILE + 7
    g = gaussians(n=80, seed=4)
    with torch.no_grad():
        g["log_scales"] += 1.0
        g["means"][:, :2] *= 1.5
    out = assert_equal_to_dense(g, height, width, rasteriser=rasteriser)
    assert (out["accumulation"][-1] > 1e-3).any() and (out["accumulation"][:, -1] > 1e-3).any()


@pytest.mark.parametrize("rasteriser", TILE_RASTERISERS)
def test_an_empty_view_shows_the_background_and_passes_no_gradient(rasteriser):
    g = gaussians(n=10, seed=5)
    with torch.no_grad():
        g["means"][:, 2] = -10.0  # all behind the camera
    out = drawn(g, rasteriser, 20, 24)
    torch.testing.assert_close(out["rgb"], BACKGROUND.expand(20, 24, 3))
    assert out["accumulation"].abs().max() == 0
    out["rgb"].sum().backward()
    assert all(value.grad is None or value.grad.abs().max() == 0 for value in g.values())


def stack(n: int, opacity: float, spread: float = 0.0, seed: int = 0) -> Projection:
    """n round footprints of ``opacity`` about the middle of a 20 x 24 view, nearest first by index."""
    generator = torch.Generator().manual_seed(seed)
    means2d = (torch.tensor([12.0, 10.0]) + spread * torch.randn(n, 2, generator=generator)).requires_grad_()
    conics = torch.tensor([0.02, 0.0, 0.02]).repeat(n, 1).requires_grad_()
    opacities = torch.full((n,), opacity).requires_grad_()
    depths = torch.linspace(1.0, 2.0, n).requires_grad_()
    extents = torch.full((n, 2), 20.0)
    return Projection(torch.arange(n), means2d, conics, opacities, depths, extents)


def assert_projection_gradients_equal(projection: Projection, colours: torch.Tensor, height: int = 20, width: int = 24,
                                      rasteriser=rasterize_tiles) -> dict:
    out = {}
    for name, rasteriser in (("tiles", rasteriser), ("dense", rasterize_reference)):
        drawn_out = rasteriser(projection, colours, height, width, BACKGROUND, absgrad=True)
        loss = drawn_out["rgb"].sum() + 0.5 * drawn_out["accumulation"].sum() + 0.1 * drawn_out["depth"].sum()
        inputs = [projection.means2d, projection.conics, projection.opacities, projection.depths, colours]
        out[name] = (drawn_out, (*torch.autograd.grad(loss, inputs), projection.means2d.absgrad.cpu()))
    for key in ("rgb", "accumulation", "depth"):
        torch.testing.assert_close(out["tiles"][0][key], out["dense"][0][key], atol=1e-5, rtol=1e-5)
    for a, b in zip(out["tiles"][1], out["dense"][1]):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-4)
    return out["tiles"][0]


@pytest.mark.parametrize("rasteriser", TILE_RASTERISERS)
def test_a_pixel_stops_at_the_transmittance_floor_and_the_rest_is_not_drawn(rasteriser):
    # 40 footprints of opacity 0.5: 2^-13 < 1e-4, so the middle pixels stop after 13 and the later ones do nothing
    colours = torch.rand(40, 3, generator=torch.Generator().manual_seed(1)).requires_grad_()
    out = assert_projection_gradients_equal(stack(40, 0.5), colours, rasteriser=rasteriser)
    assert out["accumulation"][10, 12] > 1 - 2e-4
    # alphas at the clamp (0.999) too: an opacity above it passes no gradient through the clamp
    assert_projection_gradients_equal(stack(5, 0.9995, spread=3.0), torch.rand(5, 3).requires_grad_(), rasteriser=rasteriser)


@pytest.mark.parametrize("rasteriser", TILE_RASTERISERS)
def test_a_tile_with_more_footprints_than_a_block_holds(rasteriser):
    # 700 faint footprints over one tile (a GPU block holds 256): every one is composited, none is lost
    colours = torch.rand(700, 3, generator=torch.Generator().manual_seed(2)).requires_grad_()
    assert_projection_gradients_equal(stack(700, 0.01, spread=2.0, seed=3), colours, rasteriser=rasteriser)


@pytest.mark.parametrize("rasteriser", TILE_RASTERISERS)
def test_a_masked_loss_and_a_patch_get_the_reference_gradients(rasteriser):
    height, width = 20, 24
    mask = torch.rand(height, width, generator=torch.Generator().manual_seed(3)) > 0.4
    assert_equal_to_dense(gaussians(seed=6), height, width, mask=mask, rasteriser=rasteriser)
    # a patch: the view's camera with its principal point moved to the patch's corner, drawn at the patch's size
    K, _ = camera(40, 48)
    patch = K.clone()
    patch[0, 2] -= 13
    patch[1, 2] -= 7
    assert_equal_to_dense(gaussians(seed=7), height, width, K=patch, rasteriser=rasteriser)


def test_the_same_input_gives_the_same_gradients_bit_for_bit():
    g = gaussians(n=300, seed=8)
    grads = []
    for _ in range(2):
        out = drawn(g, rasterize_tiles, 40, 48)
        grads.append(torch.autograd.grad(out["rgb"].square().sum() + out["depth"].sum(), list(g.values())))
    for a, b in zip(*grads):
        assert torch.equal(a, b)


def test_float64_inputs_are_drawn_in_float64():
    g = {key: value.detach().double().requires_grad_() for key, value in gaussians(seed=9).items()}
    K, c2w = camera()
    projection = project(g["means"], g["quats"], g["log_scales"], torch.sigmoid(g["opacity_logits"]), K.double(), c2w.double(), 20, 24)
    out = rasterize_tiles(projection, g["colours"][projection.ids], 20, 24, BACKGROUND.double())
    assert out["rgb"].dtype == torch.float64
    torch.testing.assert_close(out["rgb"], rasterize_pairs(projection, g["colours"][projection.ids], 20, 24, BACKGROUND.double())["rgb"])


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_the_radix_sort_orders_depths_as_a_stable_sort_does(dtype) -> None:
    """Ties kept in index order (as the reference's stable sort keeps them), negative and tiny depths in place."""
    rng = np.random.default_rng(0)
    depths = np.concatenate([rng.normal(size=3000), np.full(40, 1.5), -np.abs(rng.normal(size=40)),
                             [0.0, 1e-30, -1e-30, 1e30, -1e30]]).astype(dtype)
    rng.shuffle(depths)
    order = nearest_first(*depth_keys(depths))
    assert np.array_equal(order, np.argsort(depths, kind="stable"))


def test_the_fall_off_is_exp_where_the_loops_ask_it() -> None:
    """Every sigma a loop evaluates lies in [0, log(255) + 1e-6]; checked a little past it."""
    sigmas = np.linspace(0.0, 6.0, 100_001)
    fades = np.array([fade(sigma) for sigma in sigmas[::97]])
    np.testing.assert_allclose(fades, np.exp(-sigmas[::97]), rtol=1e-8, atol=0.0)
    # past the table (an opacity over 1 given to the tile kernels) it stays on it; a NaN sigma gives NaN, as exp does
    assert 0.0 <= fade(100.0) < 1e-3 and np.isnan(fade(float("nan")))


@pytest.mark.parametrize("rasteriser", [rasterize_tiles, rasterize_pairs], ids=["numba", "pairs"])
def test_absgrad_adds_up_over_backward_passes_as_gradients_do(rasteriser):
    g = gaussians(seed=11)
    out = drawn(g, rasteriser, 20, 24, absgrad=True)
    loss = out["rgb"].square().sum()
    loss.backward(retain_graph=True)
    once = out["means2d"].absgrad.clone()
    loss.backward()
    assert once.max() > 0
    torch.testing.assert_close(out["means2d"].absgrad, 2 * once)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_the_numba_pixel_boxes_are_the_references_to_the_pixel(dtype):
    from nerf_lightning.splats.rasterize_core import pixel_boxes
    from nerf_lightning.splats.rasterize_tiles import pixel_boxes as pixel_boxes_fast

    generator = torch.Generator().manual_seed(0)
    count = 20_000
    means2d = torch.rand(count, 2, generator=generator, dtype=dtype) * 160 - 30  # off every border too
    extents = torch.rand(count, 2, generator=generator, dtype=dtype) * 12
    # centres on pixel edges and whole extents: where ceil and floor decide a box's first and last pixel
    means2d[:2000] = torch.randint(-6, 40, (2000, 2), generator=generator).to(dtype) + 0.5
    extents[:1000] = torch.randint(0, 5, (1000, 2), generator=generator).to(dtype)
    projection = Projection(torch.arange(count), means2d, torch.zeros(count, 3, dtype=dtype), torch.zeros(count, dtype=dtype),
                            torch.zeros(count, dtype=dtype), extents)
    assert torch.equal(pixel_boxes_fast(projection, 90, 120), pixel_boxes(projection, 90, 120))
