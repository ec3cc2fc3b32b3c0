"""What draws a view: the rasteriser chosen in config (``model/rasterizer``), with the projection, colours and loss
that go with it. The one choice that training, ``nerf-render``, ``nerf-eval`` and the viewer share.

``model/rasterizer`` is one of:

- ``tiles`` (:class:`TileRasterizer`): the tile rasteriser of the view's device, forward and backward: numba loops on
  a CPU (:mod:`~nerf_lightning.splats.rasterize_tiles`, with the projection, colours and loss in numba too:
  :mod:`~nerf_lightning.splats.projection_fast`, :mod:`~nerf_lightning.splats.loss_fast`), Triton kernels on CUDA
  (:mod:`~nerf_lightning.splats.rasterize_triton`); where the device has none (Apple GPUs), ``pairs``;
- ``auto`` (the default): the same;
- ``pairs`` (:class:`PairsRasterizer`, :mod:`~nerf_lightning.splats.rasterize_pairs`): plain PyTorch over
  (footprint, pixel) pairs, every device: the same images, slower, and on a GPU far more memory.

Apple GPUs have no tile rasteriser, and the pair one there is the slowest path there is (on an H100 it needed 37 GB
and made 1.4 steps a second at 800x800), so where a device is chosen for the user (``trainer.accelerator=auto``,
``device=auto``) splats train and draw on the CPU's tiles instead (:func:`device_for_splats`), said once in the log;
asking for the Apple GPU by name (``trainer.accelerator=mps``, ``device=mps``) still gets it.

Each tile rasteriser is tried once by its chooser (:class:`FastKernels`) on a tiny view, forward and backward; where
numba or Triton is missing or fails to compile, one warning says so and ``pairs`` draws instead: the same values.
"""

from __future__ import annotations

import logging
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Any

import torch
from torch.profiler import record_function

from nerf_lightning.splats.projection import Projection, project
from nerf_lightning.splats.rasterize_pairs import MAX_PAIRS, rasterize_pairs
from nerf_lightning.splats.sh import coefficients_for, spherical_harmonics

log = logging.getLogger(__name__)

# what draws a view, as :meth:`Rasterizer.choose` names it
NUMBA, TRITON, PAIRS = "tiles", "triton", "pairs"


def _probe(rasterize: Callable[..., dict[str, torch.Tensor]], device: str) -> None:
    """Draw a tiny view of two footprints on ``device`` and pass a gradient back: raises where the rasteriser cannot."""
    # with gradients even where the first view is drawn under no_grad or inference_mode (render_view, nerf-render)
    with torch.inference_mode(False), torch.enable_grad():
        means2d = torch.tensor([[2.0, 2.0], [3.0, 1.5]], device=device, requires_grad=True)
        conics = torch.tensor([[0.5, 0.1, 0.5], [1.0, 0.0, 1.0]], device=device)
        probe = Projection(torch.arange(2, device=device), means2d, conics, torch.tensor([0.9, 0.5], device=device),
                           torch.tensor([1.0, 2.0], device=device), torch.full((2, 2), 3.0, device=device))
        out = rasterize(probe, torch.rand(2, 3, device=device), 4, 5, torch.zeros(3, device=device))
        out["rgb"].sum().backward()


class FastKernels:
    """Which tile rasterisers run here, each tried the first time it is asked for (a tiny view forward and backward,
    so that a failure shows before training rather than in a backward pass) and remembered: its function, or None
    where it failed (one warning)."""

    def __init__(self) -> None:
        self.tried: dict[str, Callable[..., dict[str, torch.Tensor]] | None] = {}

    def numba(self) -> Callable[..., dict[str, torch.Tensor]] | None:
        """numba's tile rasteriser (CPU tensors), where numba imports and its loops compile."""
        if NUMBA not in self.tried:
            try:
                from nerf_lightning.splats.rasterize_tiles import rasterize_tiles

                _probe(rasterize_tiles, "cpu")
                self.tried[NUMBA] = rasterize_tiles
            except Exception as error:  # ImportError without numba; numba's errors where it cannot compile
                warnings.warn(f"the CPU tile rasteriser is unavailable ({type(error).__name__}: {error}); splats are drawn "
                              "by the plain PyTorch rasteriser, which gives the same images more slowly (pip install numba)",
                              stacklevel=3)
                self.tried[NUMBA] = None
        return self.tried[NUMBA]

    def triton(self) -> Callable[..., dict[str, torch.Tensor]] | None:
        """Triton's tile rasteriser, where Triton imports and its kernels compile and run on the current CUDA device."""
        if TRITON not in self.tried:
            try:
                from nerf_lightning.splats.rasterize_triton import rasterize_triton

                _probe(rasterize_triton, "cuda")
                self.tried[TRITON] = rasterize_triton
            except Exception as error:  # ImportError without triton; Triton's compile errors; no CUDA device
                warnings.warn(f"the GPU tile rasteriser is unavailable ({type(error).__name__}: {str(error)[:300]}); splats "
                              "are drawn by the plain PyTorch rasteriser, which gives the same images more slowly and with "
                              "far more memory (Triton comes with PyTorch's CUDA wheels on Linux)", stacklevel=3)
                self.tried[TRITON] = None
        return self.tried[TRITON]


@dataclass(frozen=True)
class ViewDrawer:
    """What draws a view on one device: ``name`` (``tiles``: numba's, ``triton``, ``pairs``), its ``rasterize``
    (projection, colours, height, width, background, absgrad=...), and whether the projection, colours and loss take
    numba's fused paths (``numba``)."""

    name: str
    rasterize_fn: Callable[..., dict[str, torch.Tensor]]
    antialiased: bool = False
    numba: bool = False

    def project(self, gaussians: Any, degree: int, K: torch.Tensor, c2w: torch.Tensor, height: int,
                width: int) -> tuple[Projection, torch.Tensor]:
        """The :class:`~nerf_lightning.splats.gaussians.Gaussians` seen by a camera (K (3, 3), OpenCV c2w (4, 4)) ->
        the :class:`Projection` of those drawn and their (M, 3) colours of SH ``degree``."""
        g = gaussians
        learned_camera = torch.is_grad_enabled() and c2w.requires_grad  # camera refinement: the reference's autograd
        if self.numba and not learned_camera:
            # projection and colour in one numba loop, forward and backward, held equal to the two PyTorch steps below
            from nerf_lightning.splats.projection_fast import project_and_shade

            with record_function("splats.project_and_shade"):
                return project_and_shade(g.means, g.quats, g.log_scales, g.opacities, g.sh0, g.shN, degree, K, c2w,
                                         height, width, self.antialiased)
        # the labels name the step's stages in a profile (scripts/profile_splat_step.py)
        with record_function("splats.project"):
            projection = project(g.means, g.quats, g.log_scales, g.opacities, K, c2w, height, width, self.antialiased)
        with record_function("splats.sh"):
            directions = g.means.index_select(0, projection.ids) - c2w[:3, 3]
            # only the seen Gaussians' coefficients of the bands in use, gathered (not every Gaussian's concatenated first)
            higher = g.shN[:, : coefficients_for(degree) - 1]
            coefficients = torch.cat([g.sh0.index_select(0, projection.ids), higher.index_select(0, projection.ids)], dim=1)
            return projection, spherical_harmonics(degree, coefficients, directions)

    def rasterize(self, projection: Projection, colours: torch.Tensor, height: int, width: int,
                  background: torch.Tensor, absgrad: bool = False) -> dict[str, torch.Tensor]:
        """Footprints (M of them) with (M, 3) colours -> rgb (H, W, 3), depth (H, W) (camera z), accumulation (H, W)
        over ``background`` (3,); with ``absgrad``, the backward pass fills ``projection.means2d.absgrad``
        (:func:`~nerf_lightning.splats.rasterize_core.keep_absgrad`)."""
        return self.rasterize_fn(projection, colours, height, width, background, absgrad=absgrad)


class Rasterizer:
    """``model.rasterizer``: what draws a view on each device (:meth:`for_device`). ``max_pairs`` bounds the pairs
    rasteriser's memory (about 100 bytes a pair with gradients; a view with more is drawn in bands of rows);
    ``antialiased``: Mip-Splatting's opacity compensation of the projection's low-pass filter."""

    def __init__(self, max_pairs: int = MAX_PAIRS, antialiased: bool = False) -> None:
        if max_pairs < 1:
            raise ValueError(f"model.rasterizer.max_pairs must be >= 1, got {max_pairs}")
        self.max_pairs, self.antialiased = max_pairs, antialiased
        self.kernels = FastKernels()

    def choose(self, device_type: str) -> str:
        """What draws a view on a device of type ``device_type`` ("cpu", "cuda", "mps"): ``tiles`` (numba, CPU),
        ``triton`` (CUDA) or ``pairs``."""
        return PAIRS

    def for_device(self, device_type: str) -> ViewDrawer:
        """The :class:`ViewDrawer` of a device of type ``device_type``."""
        chosen = self.choose(device_type)
        if chosen == NUMBA:
            return ViewDrawer(NUMBA, self.kernels.numba(), self.antialiased, numba=True)
        if chosen == TRITON:
            return ViewDrawer(TRITON, self.kernels.triton(), self.antialiased)
        return ViewDrawer(PAIRS, partial(rasterize_pairs, max_pairs=self.max_pairs), self.antialiased)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(max_pairs={self.max_pairs}, antialiased={self.antialiased})"


class PairsRasterizer(Rasterizer):
    """``model/rasterizer=pairs``: the plain PyTorch pairs rasteriser and projection on every device."""


class TileRasterizer(Rasterizer):
    """``model/rasterizer=tiles`` (and ``auto``): the tile rasteriser of the view's device, numba's on a CPU, Triton's
    on CUDA; the pairs rasteriser where there is none (Apple GPUs) or it does not run here (one warning)."""

    def choose(self, device_type: str) -> str:
        if device_type == "cpu":
            return NUMBA if self.kernels.numba() is not None else PAIRS
        if device_type == "cuda":
            return TRITON if self.kernels.triton() is not None else PAIRS
        return PAIRS


# the choices of model/rasterizer, by name (scripts that switch between them)
RASTERIZERS: dict[str, type[Rasterizer]] = {"auto": TileRasterizer, "tiles": TileRasterizer, "pairs": PairsRasterizer}


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
