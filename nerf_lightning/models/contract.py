"""What every trained model is to the commands: typed protocols, not base classes or kind strings.

Every model of a scene renders a camera (:class:`RendersCamera`): ``nerf-render``, ``nerf-eval``, ``nerf-view`` and the
live viewer call :meth:`~RendersCamera.render_view` and nothing else of it. What only some models can do is asked for
by protocol (``implements(model, HasDensity)``), never by the model's class or a kind string:

- :class:`HasDensity`: a density and a colour at any point, which ``nerf-export`` meshes;
- :class:`ShowsOverlays`: things the viewer can draw over the render (the scene's box, occupied cells, ...);
- :class:`RendersImage`: an image field, rendered at any scale (no camera).

A new kind of model implements :class:`RendersCamera` (and whichever capability it has) and needs nothing in
``cli/``, :mod:`nerf_lightning.outputs` or :mod:`nerf_lightning.viz`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np
import torch

from nerf_lightning.geometry.space import SceneSpace


@runtime_checkable
class RendersCamera(Protocol):
    """A trained model of a scene: renders any pinhole camera.

    ``space``: the :class:`~nerf_lightning.geometry.space.SceneSpace` it was trained in (its near/far, how depth is
    pictured, how to map back to the capture's coordinates). ``device``: where it renders.

    ``render_view(K, c2w, height, width, abort=None)``: K (3, 3) intrinsics in pixels and an OpenCV camera-to-world
    c2w (4, 4) in the scene's world -> ``rgb`` (H, W, 3) in [0, 1], ``depth`` (H, W) (the expected distance along each
    pixel's unit ray, given that it ends) and ``accumulation`` (H, W) (opacity in [0, 1]), on the model's device,
    without gradients; rendered in as many pieces as the model needs to bound memory. ``abort`` is called between
    pieces: when it returns true the render stops and None is returned (the viewer, when its camera moves on).
    """

    space: SceneSpace
    device: torch.device

    def render_view(self, K: torch.Tensor, c2w: torch.Tensor, height: int, width: int,
                    abort: Callable[[], bool] | None = None) -> dict[str, torch.Tensor] | None: ...


@runtime_checkable
class HasDensity(Protocol):
    """A model with a volume density, which can be meshed (marching cubes, :mod:`nerf_lightning.outputs.mesh`).

    ``density_at(points)``: (N, 3) points in the sampling space (the scene's world, or NDC) -> (N,) densities >= 0,
    differentiable in the points. ``colour_at(points, viewdirs)``: (N, 3) points and unit directions -> (N, 3) colours.
    ``mesh_box()``: low, high (3,) the part of the sampling space worth meshing, in the sampling space.
    """

    space: SceneSpace

    def density_at(self, points: torch.Tensor) -> torch.Tensor: ...

    def colour_at(self, points: torch.Tensor, viewdirs: torch.Tensor) -> torch.Tensor: ...

    def mesh_box(self) -> tuple[torch.Tensor, torch.Tensor]: ...


@dataclass
class Overlay:
    """Something the viewer draws in the world over the render.

    Attributes:
        label: the checkbox's text.
        kind: ``lines`` (``points`` is (L, 2, 3), segments) or ``points`` (``points`` is (P, 3)).
        points: world coordinates (float32 numpy).
        colour: RGB 0..255.
        size: line width in screen pixels (lines) or point size in world units (points).
    """

    label: str
    kind: str
    points: np.ndarray
    colour: tuple[int, int, int]
    size: float


@runtime_checkable
class ShowsOverlays(Protocol):
    """A model with things to draw over its render in the viewer.

    ``overlay_names()``: name -> label of what it can draw (fixed for the model: the page makes a checkbox of each).
    ``overlay(name)``: that overlay as it is now (the live viewer asks again as the model trains), or None when it
    has nothing to draw (an empty grid).
    """

    def overlay_names(self) -> dict[str, str]: ...

    def overlay(self, name: str) -> Overlay | None: ...


@runtime_checkable
class HasGaussians(Protocol):
    """A model made of 3D Gaussians, written as a splat PLY or SPZ (:mod:`nerf_lightning.splats.ply`, :mod:`~nerf_lightning.splats.spz`).

    ``gaussian_parameters()`` -> means (N, 3) in the scene's world, quats (N, 4) w x y z, log_scales (N, 3),
    opacity_logits (N,), sh0 (N, 1, 3), shN (N, K - 1, 3) spherical-harmonic colours (3DGS's constants).
    """

    space: SceneSpace

    def gaussian_parameters(self) -> dict[str, torch.Tensor]: ...


@runtime_checkable
class RendersImage(Protocol):
    """An image field: ``render_image(scale)`` -> (round(s H), round(s W), 3) colours in [0, 1] of the fitted image."""

    def render_image(self, scale: float = 1.0) -> torch.Tensor: ...


def protocol_members(capability: type) -> set[str]:
    """The attributes and methods a protocol class names (its own and its protocol bases')."""
    members: set[str] = set()
    for base in capability.__mro__:
        if base in (Protocol, object) or not getattr(base, "_is_protocol", False):
            continue
        members |= set(base.__dict__.get("__annotations__", {}))
        members |= {name for name, value in base.__dict__.items() if callable(value) and not name.startswith("_")}
    return members


def implements(model: Any, capability: type) -> bool:
    """Whether ``model`` has every member of the protocol ``capability``, looked up as attributes are (``hasattr``).

    Not ``isinstance``: from Python 3.12 it looks a runtime-checkable protocol's members up statically
    (``inspect.getattr_static``), which does not see what an ``nn.Module`` keeps in its ``_modules`` and
    ``_buffers`` (a model's ``space``), so every model failed the check there."""
    return all(hasattr(model, name) for name in protocol_members(capability))


def require(model: Any, capability: type, command: str, what: str) -> None:
    """ValueError in one line when ``model`` lacks ``capability``: ``command`` needs ``what``, this model is X."""
    if not implements(model, capability):
        raise ValueError(f"{command} needs {what}; this checkpoint's model, {type(model).__name__}, has none")
