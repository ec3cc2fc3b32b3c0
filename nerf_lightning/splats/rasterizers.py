"""Which rasteriser draws a view: the one choice that training, ``nerf-render``, ``nerf-eval`` and the viewer share.

- ``tiles`` (:mod:`~nerf_lightning.splats.rasterize_tiles`): numba loops over tiles, forward and backward; CPU tensors.
- ``pairs`` (:mod:`~nerf_lightning.splats.rasterize`): plain PyTorch over (footprint, pixel) pairs; every device.

``auto`` takes ``tiles`` on a CPU where numba imports and compiles, and ``pairs`` elsewhere (CUDA and Apple GPUs).
Where numba is missing or fails to compile, one warning says so and ``pairs`` draws instead: the same values, slower.
"""

from __future__ import annotations

import warnings

import torch

from nerf_lightning.splats.projection import Projection
from nerf_lightning.splats.rasterize import MAX_PAIRS, rasterize

AUTO, TILES, PAIRS = "auto", "tiles", "pairs"
RASTERIZERS = (AUTO, TILES, PAIRS)

_tiles_ready: bool | None = None  # None: not tried yet in this process
_tiles = None  # the module nerf_lightning.splats.rasterize_tiles, once it is ready


def tiles_available() -> bool:
    """Whether the tile rasteriser runs here: numba imports and its loops compile (tried once a process, on a tiny
    view forward and backward, so that a failure shows before training rather than in a backward pass)."""
    global _tiles_ready, _tiles
    if _tiles_ready is None:
        try:
            import nerf_lightning.splats.rasterize_tiles as rasterize_tiles

            # with gradients even where the first view is drawn under no_grad or inference_mode (render_view, nerf-render)
            with torch.inference_mode(False), torch.enable_grad():
                means2d = torch.tensor([[2.0, 2.0], [3.0, 1.5]], requires_grad=True)
                conics = torch.tensor([[0.5, 0.1, 0.5], [1.0, 0.0, 1.0]])
                probe = Projection(torch.arange(2), means2d, conics, torch.tensor([0.9, 0.5]), torch.tensor([1.0, 2.0]),
                                   torch.full((2, 2), 3.0))
                out = rasterize_tiles.rasterize_tiles(probe, torch.rand(2, 3), 4, 5, torch.zeros(3))
                out["rgb"].sum().backward()
            _tiles, _tiles_ready = rasterize_tiles, True
        except Exception as error:  # ImportError without numba; numba's errors where it cannot compile
            warnings.warn(f"the CPU tile rasteriser is unavailable ({type(error).__name__}: {error}); splats are drawn by "
                          "the plain PyTorch rasteriser, which gives the same images more slowly (pip install numba)",
                          stacklevel=2)
            _tiles_ready = False
    return _tiles_ready


def check_rasterizer(rasterizer: str) -> None:
    """ValueError in one line for a name that is not one of :data:`RASTERIZERS`."""
    if rasterizer not in RASTERIZERS:
        raise ValueError(f"model.rasterizer must be one of {', '.join(RASTERIZERS)}, got {rasterizer!r}")


def choose_rasterizer(device_type: str, rasterizer: str = AUTO) -> str:
    """``tiles`` or ``pairs`` for a view drawn on a device of type ``device_type`` ("cpu", "cuda", "mps")."""
    check_rasterizer(rasterizer)
    if rasterizer == PAIRS or device_type != "cpu":
        return PAIRS
    return TILES if tiles_available() else PAIRS


def rasterize_view(projection: Projection, colours: torch.Tensor, height: int, width: int, background: torch.Tensor,
                   rasterizer: str = AUTO, max_pairs: int = MAX_PAIRS) -> dict[str, torch.Tensor]:
    """Footprints (M of them) with (M, 3) colours -> rgb (H, W, 3), depth (H, W), accumulation (H, W), drawn by the
    rasteriser :func:`choose_rasterizer` picks; ``max_pairs`` bounds the ``pairs`` rasteriser's memory."""
    if choose_rasterizer(colours.device.type, rasterizer) == TILES:
        return _tiles.rasterize_tiles(projection, colours, height, width, background)
    return rasterize(projection, colours, height, width, background, max_pairs)
