"""Which rasteriser draws a view: the one choice that training, ``nerf-render``, ``nerf-eval`` and the viewer share.

``model.rasterizer`` is one of:

- ``tiles``: the tile rasteriser of the view's device, forward and backward: numba loops on a CPU
  (:mod:`~nerf_lightning.splats.rasterize_tiles`), Triton kernels on CUDA
  (:mod:`~nerf_lightning.splats.rasterize_triton`);
- ``pairs`` (:mod:`~nerf_lightning.splats.rasterize`): plain PyTorch over (footprint, pixel) pairs; every device;
- ``auto`` (the default): ``tiles`` where the device has one that runs (Apple GPUs have none), else ``pairs``.

Apple GPUs have no tile rasteriser, and the pair one there is the slowest path there is (on an H100 it needed 37 GB
and made 1.4 steps a second at 800x800), so where a device is chosen for the user (``trainer.accelerator=auto``,
``device=auto``) splats train and draw on the CPU's tiles instead (:func:`device_for_splats`), said once in the log;
asking for the Apple GPU by name (``trainer.accelerator=mps``, ``device=mps``) still gets it.

Each tile rasteriser is tried once a process on a tiny view, forward and backward; where numba or Triton is missing
or fails to compile, one warning says so and ``pairs`` draws instead: the same values, slower.
"""

from __future__ import annotations

import logging
import warnings

import torch

from nerf_lightning.splats.projection import Projection
from nerf_lightning.splats.rasterize import MAX_PAIRS, rasterize

log = logging.getLogger(__name__)

AUTO, TILES, PAIRS = "auto", "tiles", "pairs"
RASTERIZERS = (AUTO, TILES, PAIRS)
# what :func:`choose_rasterizer` answers for ``tiles`` on CUDA
TRITON = "triton"

_tiles_ready: bool | None = None  # None: not tried yet in this process
_tiles = None  # the module nerf_lightning.splats.rasterize_tiles, once it is ready
_triton_ready: bool | None = None
_triton = None  # the module nerf_lightning.splats.rasterize_triton, once it is ready


def _probe(rasterize, device: str) -> None:
    """Draw a tiny view of two footprints on ``device`` and pass a gradient back: raises where the rasteriser cannot."""
    # with gradients even where the first view is drawn under no_grad or inference_mode (render_view, nerf-render)
    with torch.inference_mode(False), torch.enable_grad():
        means2d = torch.tensor([[2.0, 2.0], [3.0, 1.5]], device=device, requires_grad=True)
        conics = torch.tensor([[0.5, 0.1, 0.5], [1.0, 0.0, 1.0]], device=device)
        probe = Projection(torch.arange(2, device=device), means2d, conics, torch.tensor([0.9, 0.5], device=device),
                           torch.tensor([1.0, 2.0], device=device), torch.full((2, 2), 3.0, device=device))
        out = rasterize(probe, torch.rand(2, 3, device=device), 4, 5, torch.zeros(3, device=device))
        out["rgb"].sum().backward()


def tiles_available() -> bool:
    """Whether the tile rasteriser runs here: numba imports and its loops compile (tried once a process, on a tiny
    view forward and backward, so that a failure shows before training rather than in a backward pass)."""
    global _tiles_ready, _tiles
    if _tiles_ready is None:
        try:
            import nerf_lightning.splats.rasterize_tiles as rasterize_tiles

            _probe(rasterize_tiles.rasterize_tiles, "cpu")
            _tiles, _tiles_ready = rasterize_tiles, True
        except Exception as error:  # ImportError without numba; numba's errors where it cannot compile
            warnings.warn(f"the CPU tile rasteriser is unavailable ({type(error).__name__}: {error}); splats are drawn by "
                          "the plain PyTorch rasteriser, which gives the same images more slowly (pip install numba)",
                          stacklevel=2)
            _tiles_ready = False
    return _tiles_ready


def triton_available() -> bool:
    """Whether the GPU tile rasteriser runs here: Triton imports and its kernels compile and run on the current CUDA
    device (tried once a process, forward and backward)."""
    global _triton_ready, _triton
    if _triton_ready is None:
        try:
            import nerf_lightning.splats.rasterize_triton as rasterize_triton

            _probe(rasterize_triton.rasterize_triton, "cuda")
            _triton, _triton_ready = rasterize_triton, True
        except Exception as error:  # ImportError without triton; Triton's compile errors; no CUDA device
            warnings.warn(f"the GPU tile rasteriser is unavailable ({type(error).__name__}: {str(error)[:300]}); splats are "
                          "drawn by the plain PyTorch rasteriser, which gives the same images more slowly and with far "
                          "more memory (Triton comes with PyTorch's CUDA wheels on Linux)", stacklevel=2)
            _triton_ready = False
    return _triton_ready


def check_rasterizer(rasterizer: str) -> None:
    """ValueError in one line for a name that is not one of :data:`RASTERIZERS`."""
    if rasterizer not in RASTERIZERS:
        raise ValueError(f"model.rasterizer must be one of {', '.join(RASTERIZERS)}, got {rasterizer!r}")


def choose_rasterizer(device_type: str, rasterizer: str = AUTO) -> str:
    """What draws a view on a device of type ``device_type`` ("cpu", "cuda", "mps") for ``model.rasterizer``:
    ``tiles`` (numba, CPU), ``triton`` (CUDA) or ``pairs``."""
    check_rasterizer(rasterizer)
    if rasterizer == PAIRS:
        return PAIRS
    if device_type == "cpu":
        return TILES if tiles_available() else PAIRS
    if device_type == "cuda":
        return TRITON if triton_available() else PAIRS
    return PAIRS


def device_for_splats(device: torch.device | str, asked: bool) -> torch.device:
    """Where Gaussians train and draw when ``device`` was chosen (``asked``: named by the user, not ``auto``): the CPU,
    whose tiles draw, in place of an Apple GPU that was not asked for by name (one line in the log says so); else
    ``device`` itself."""
    device = torch.device(device)
    if device.type == "mps" and not asked:
        log.warning("splats train and draw on the CPU's tile rasteriser, not this Apple GPU: there they would have only "
                    "the plain PyTorch rasteriser, far slower and larger (no Metal tile kernel yet); ask for the Apple GPU "
                    "by name (trainer.accelerator=mps, or device=mps) to use it anyway")
        return torch.device("cpu")
    return device


def rasterize_view(projection: Projection, colours: torch.Tensor, height: int, width: int, background: torch.Tensor,
                   rasterizer: str = AUTO, max_pairs: int = MAX_PAIRS, absgrad: bool = False) -> dict[str, torch.Tensor]:
    """Footprints (M of them) with (M, 3) colours -> rgb (H, W, 3), depth (H, W), accumulation (H, W), drawn by the
    rasteriser :func:`choose_rasterizer` picks; ``max_pairs`` bounds the ``pairs`` rasteriser's memory; with
    ``absgrad``, the backward pass fills ``projection.means2d.absgrad``
    (:func:`~nerf_lightning.splats.rasterize.keep_absgrad`)."""
    chosen = choose_rasterizer(colours.device.type, rasterizer)
    if chosen == TILES:
        return _tiles.rasterize_tiles(projection, colours, height, width, background, absgrad)
    if chosen == TRITON:
        return _triton.rasterize_triton(projection, colours, height, width, background, absgrad)
    return rasterize(projection, colours, height, width, background, max_pairs, absgrad)
