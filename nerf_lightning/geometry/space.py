"""The scene's space: where rays are sampled and what a field sees, built once from a Scene.

The data flows: a file format -> :class:`~nerf_lightning.data.scene.Scene` -> :class:`SceneSpace` -> rays -> a
sampler -> a field -> the renderer. The scene space is the one object after the Scene that knows how the scene was
parametrised, so that the samplers, the fields, rendering and export call it instead of reading flags:

- *Sampling space*: rays are world rays (unit directions), or, for a forward-facing capture, rays in normalised
  device coordinates (:class:`NDC`), where t in [0, 1] runs from the near plane to infinity. ``near`` and ``far``
  are the range of t along the sampling rays.
- *Field space*: the points a field and an occupancy grid see. The sampling space itself, or, for an unbounded
  scene, the sampling space passed through a :class:`~nerf_lightning.geometry.contraction.Contraction` (all of
  space inside [-2, 2]^3). A field's and a grid's ``aabb`` are boxes of the field space.
- *Capture space*: the coordinates of the capture's files, from which the loader's similarity
  ``world_from_capture`` took the scene (renders and meshes are mapped back to it).

Checkpoints keep the space as one entry (:meth:`SceneSpace.state`), so every command rebuilds it from ``ckpt_path``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, NamedTuple

import kornia
import torch
from torch import nn

from nerf_lightning.geometry.contraction import Contraction
from nerf_lightning.geometry.rays import indexed_pixel_rays, ndc_rays, ndc_to_world, ray_aabb_intersect


class Rays(NamedTuple):
    """N rays in the sampling space: ``origins`` and ``directions`` (N, 3) (unit in the world, not in NDC),
    ``viewdirs`` (N, 3), the unit world directions a field sees, and ``camera_indices`` (N,), the training image
    of each ray (for a field's appearance embedding), or None for rays of other views."""

    origins: torch.Tensor
    directions: torch.Tensor
    viewdirs: torch.Tensor
    camera_indices: torch.Tensor | None = None

    def points(self, ray_indices: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """(M,) ray of each sample and (M,) distances -> (M, 3) points in the sampling space."""
        return self.origins[ray_indices] + self.directions[ray_indices] * t[:, None]


class NDC:
    """Normalised device coordinates of a forward-facing capture whose cameras look down -z (NeRF's LLFF setting).

    Args:
        focal, width, height: the training cameras' focal length and image size in pixels.
        near_plane: the plane z = -near_plane maps to NDC z = -1 (infinity maps to +1).
        reach: the largest |x| and |y| the training rays reach in NDC (:func:`ndc_reach`), or None where unknown
            (checkpoints written before it was kept). x and y are -1 to 1 across the average camera's picture
            only: the other cameras see past it.
    """

    # a mesh of an NDC field stops short of z = 1, which is infinitely far
    mesh_far_z = 0.95

    def __init__(self, focal: float, width: int, height: int, near_plane: float = 1.0, reach: Sequence[float] | None = None) -> None:
        self.focal, self.width, self.height, self.near_plane = float(focal), int(width), int(height), float(near_plane)
        self.reach = None if reach is None else (float(reach[0]), float(reach[1]))

    def rays(self, origins: torch.Tensor, directions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(N, 3) world rays -> (N, 3) NDC origins and directions (see :func:`~nerf_lightning.geometry.rays.ndc_rays`)."""
        return ndc_rays(origins, directions, self.focal, self.width, self.height, self.near_plane)

    def to_world(self, points: torch.Tensor) -> torch.Tensor:
        """(..., 3) NDC points (z < 1) -> (..., 3) world points."""
        return ndc_to_world(points, self.focal, self.width, self.height, self.near_plane)

    def state(self) -> dict[str, Any]:
        state: dict[str, Any] = {"focal": self.focal, "width": self.width, "height": self.height, "near_plane": self.near_plane}
        if self.reach is not None:
            state["reach"] = list(self.reach)
        return state

    def __repr__(self) -> str:
        return f"NDC(focal={self.focal:g}, width={self.width}, height={self.height}, near_plane={self.near_plane:g})"


def ndc_reach(views: Any, ndc: NDC) -> tuple[float, float]:
    """The largest |x| and |y| in NDC that a ray of ``views`` (a :class:`~nerf_lightning.data.scene.Views`) reaches
    between the near plane (t = 0) and infinity (t = 1). NDC rays are straight, and at either end a picture's rays
    make a quadrilateral whose corners are the corner pixels' rays, so those four rays of each view bound them all."""
    height, width = views.height, views.width
    corners = torch.tensor([0, width - 1, (height - 1) * width, height * width - 1])
    index = (torch.arange(len(views))[:, None] * height * width + corners).reshape(-1)
    origins, directions = ndc.rays(*indexed_pixel_rays(views.K, views.c2w, height, width, index))
    ends = torch.cat([origins, origins + directions])  # (8V, 3): t = 0 and t = 1
    return float(ends[:, 0].abs().max()), float(ends[:, 1].abs().max())


class SceneSpace(nn.Module):
    """Near/far, background, the capture's similarity and the optional NDC and contraction of a scene.

    Args:
        near, far: the range of t along sampling rays (world units along unit rays; 0 and 1 in NDC).
        background: (3,) RGB blended in where rays are not opaque.
        world_from_capture: (4, 4) similarity from the capture's coordinates to the scene's, or None.
        ndc: sample in normalised device coordinates (forward-facing captures), or None.
        contraction: fields see the scene contracted into [-2, 2]^3 (unbounded captures), or None.
        bounds: (6,) the box (xmin, ymin, zmin, xmax, ymax, zmax) the scene lies in, where it is known (an object's
            box fitted to its masks, ``data.object_box``): every ray's range is cut to it, or None.

    An ``nn.Module`` so that it moves with its model between devices; its tensors are not in ``state_dict``:
    checkpoints keep :meth:`state` instead.
    """

    def __init__(
        self,
        near: float = 2.0,
        far: float = 6.0,
        background: torch.Tensor | tuple[float, float, float] = (1.0, 1.0, 1.0),
        world_from_capture: torch.Tensor | None = None,
        ndc: NDC | None = None,
        contraction: Contraction | None = None,
        bounds: Sequence[float] | torch.Tensor | None = None,
    ) -> None:
        super().__init__()
        if ndc is not None and contraction is not None:
            raise ValueError("a scene is sampled in NDC (data.ndc=true) or contracted (data.contract=true), not both")
        if bounds is not None and (ndc is not None or contraction is not None):
            raise ValueError("an object's box (data.object_box) bounds a scene in its world: it goes with neither data.ndc=true "
                             "nor data.contract=true")
        if not 0.0 <= near < far:
            raise ValueError(f"the scene space needs 0 <= near < far, got near={near}, far={far}")
        self.near, self.far = float(near), float(far)
        self.ndc, self.contraction = ndc, contraction
        self.register_buffer("background", torch.as_tensor(background, dtype=torch.float32).clone(), persistent=False)
        wfc = None if world_from_capture is None else torch.as_tensor(world_from_capture, dtype=torch.float32).clone()
        self.register_buffer("world_from_capture", wfc, persistent=False)
        box = None if bounds is None else torch.as_tensor(bounds, dtype=torch.float32).detach().clone().reshape(6)
        self.register_buffer("bounds", box, persistent=False)

    @classmethod
    def from_scene(cls, scene: Any, ndc: bool = False, contract: bool = False,
                   bounds: torch.Tensor | None = None) -> SceneSpace:
        """The space of a loaded :class:`~nerf_lightning.data.scene.Scene`: NDC from its training cameras (which must
        look down -z) with ``ndc``; the contraction with ``contract``; the box (6,) the scene lies in, ``bounds``."""
        if ndc and contract:
            raise ValueError("data.ndc=true and data.contract=true do not go together: NDC is for forward-facing captures, "
                             "the contraction for captures all around a subject")
        ndc_space = None
        near, far = scene.near, scene.far
        if ndc:
            train = scene.train
            forward = torch.nn.functional.normalize(train.c2w[:, :3, 2].mean(0), dim=0)
            if float(forward[2]) > -0.9:
                raise ValueError(f"data.ndc=true needs forward-facing cameras looking down -z (an LLFF capture), but {scene.source}'s "
                                 f"mean viewing direction is {[round(v, 3) for v in forward.tolist()]}")
            ndc_space = NDC(float(train.K[0, 0, 0]), train.width, train.height, near_plane=1.0)
            ndc_space.reach = ndc_reach(train, ndc_space)
            near, far = 0.0, 1.0  # NDC rays run from the near plane (t = 0) to infinity (t = 1)
        return cls(near, far, scene.background, scene.world_from_capture, ndc_space, Contraction() if contract else None, bounds)

    # -- rays and points ----------------------------------------------------------------------------------------

    def rays(self, origins: torch.Tensor, directions: torch.Tensor) -> Rays:
        """(N, 3) world rays with unit directions -> :class:`Rays` in the sampling space."""
        if self.ndc is None:
            return Rays(origins, directions, directions)
        ndc_origins, ndc_directions = self.ndc.rays(origins, directions)
        return Rays(ndc_origins, ndc_directions, directions)

    def to_field(self, points: torch.Tensor) -> torch.Tensor:
        """(..., 3) sampling-space points -> (..., 3) the points a field sees (contracted, or as they are)."""
        return points if self.contraction is None else self.contraction(points)

    def ray_range(self, rays: Rays, aabb: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(N,) t_enter and t_exit of each ray: near..far, cut to the scene's :attr:`bounds` where it has them (a ray
        that misses them gets an empty range, t_exit = t_enter: nothing to sample, the background shows), then to a
        field-space box ``aabb`` (6,) where that box bounds the rays (not for a contracted scene, whose box holds all
        of space); t_exit < t_enter: a miss."""
        n_rays = rays.origins.shape[0]
        t_enter, t_exit = rays.origins.new_full((n_rays,), self.near), rays.origins.new_full((n_rays,), self.far)
        if self.bounds is not None:
            box_enter, box_exit = ray_aabb_intersect(rays.origins, rays.directions, self.bounds)
            t_enter = torch.maximum(t_enter, box_enter).clamp(max=self.far)
            t_exit = torch.maximum(torch.minimum(t_exit, box_exit), t_enter)
        if aabb is None or self.contraction is not None:
            return t_enter, t_exit
        box_enter, box_exit = ray_aabb_intersect(rays.origins, rays.directions, aabb)
        return torch.maximum(t_enter, box_enter), torch.minimum(t_exit, box_exit)

    def check_box(self, aabb: torch.Tensor, key: str) -> None:
        """A field's or grid's field-space box must hold a contracted scene's whole cube, in NDC all that the
        training rays reach (:attr:`NDC.reach`), and an object's :attr:`bounds`; ValueError naming ``key`` and the
        box to set otherwise."""
        box = aabb.detach().cpu().float()

        def holds(needed: torch.Tensor, tolerance: float) -> bool:
            return not bool((box[:3] > needed[:3] + tolerance).any() or (box[3:] < needed[3:] - tolerance).any())

        if self.ndc is not None and self.ndc.reach is not None:
            reach_x, reach_y = self.ndc.reach
            if not holds(torch.tensor([-reach_x, -reach_y, -1.0, reach_x, reach_y, 1.0]), 1e-3):
                x, y = (math.ceil(10 * value) / 10 for value in (reach_x, reach_y))
                raise ValueError(f"{key} is {box.tolist()}, but the training cameras' rays in NDC (data.ndc=true) reach "
                                 f"|x| = {reach_x:.2f} and |y| = {reach_y:.2f} from the near plane (z = -1) to infinity (z = 1): "
                                 f"what they see outside the box would be left out. Set {key}=[-{x}, -{y}, -1.0, {x}, {y}, 1.0] or wider")
        if self.bounds is not None and not holds(self.bounds.detach().cpu().float(), 1e-4):
            raise ValueError(f"{key} is {box.tolist()}, but the object's box (data.object_box) is "
                             f"{[round(value, 3) for value in self.bounds.tolist()]}: what lies outside would be left out. "
                             f"Set {key}=[-1.0, -1.0, -1.0, 1.0, 1.0, 1.0] (the fitted box lies inside it)")
        if self.contraction is not None and not holds(torch.tensor(self.contraction.bounds), 1e-6):
            raise ValueError(f"{key} is {box.tolist()}, but a contracted scene (data.contract=true) fills the cube "
                             f"{list(self.contraction.bounds)}: set {key}={list(self.contraction.bounds)}")

    # -- pictures and meshes ------------------------------------------------------------------------------------

    def depth_picture(self, depth: torch.Tensor, accumulation: torch.Tensor | None = None) -> torch.Tensor:
        """Depth (...,) as a picture (...,) in [0, 1], near bright: linear between near and far; for a contracted scene
        contracted like the scene, 1 - d/2 up to d = 1 (the inner box's half-size), 1/(2d) beyond. With
        ``accumulation`` (...,) it fades out where nothing is hit (the depth of a transparent pixel means nothing)."""
        if self.contraction is not None:
            picture = torch.where(depth <= 1.0, 1.0 - depth / 2.0, 0.5 / depth.clamp(min=1.0))
        else:
            picture = (1.0 - (depth - self.near) / (self.far - self.near)).clamp(0.0, 1.0)
        return picture if accumulation is None else picture * accumulation

    def bounded_box(self, aabb: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The part of a field-space box ``aabb`` (6,) that can be meshed, as low, high (3,) in the sampling space:
        a contracted scene's inner box (where the contraction is the identity), an NDC box short of infinity."""
        low, high = aabb[:3].detach().float().cpu().clone(), aabb[3:].detach().float().cpu().clone()
        if self.contraction is not None:
            inner = torch.tensor(self.contraction.identity_box)
            low, high = torch.maximum(low, inner[:3]), torch.minimum(high, inner[3:])
        if self.ndc is not None:
            high[2] = min(float(high[2]), self.ndc.mesh_far_z)
        return low, high

    def to_capture(self, points: torch.Tensor) -> torch.Tensor:
        """(V, 3) sampling-space points -> (V, 3) in the capture's coordinates: NDC undone, then the loader's
        similarity undone (float64)."""
        points = points.double()
        if self.ndc is not None:
            points = self.ndc.to_world(points)
        if self.world_from_capture is not None:
            capture_from_world = torch.linalg.inv(self.world_from_capture.cpu().double())  # Apple GPUs have no float64
            points = kornia.geometry.transform_points(capture_from_world[None], points.cpu()[None])[0]
        return points

    # -- checkpoints --------------------------------------------------------------------------------------------

    def state(self) -> dict[str, Any]:
        """Plain numbers and lists, what checkpoints keep."""
        return {
            "near": self.near, "far": self.far, "background": self.background.tolist(),
            "world_from_capture": None if self.world_from_capture is None else self.world_from_capture.tolist(),
            "ndc": None if self.ndc is None else self.ndc.state(),
            "contraction": None if self.contraction is None else "max-norm",
            "bounds": None if self.bounds is None else self.bounds.tolist(),
        }

    @classmethod
    def from_state(cls, state: dict[str, Any]) -> SceneSpace:
        ndc = NDC(**state["ndc"]) if state.get("ndc") else None
        return cls(state["near"], state["far"], tuple(state["background"]), state.get("world_from_capture"), ndc,
                   Contraction() if state.get("contraction") else None, state.get("bounds"))

    def extra_repr(self) -> str:
        bounds = "" if self.bounds is None else f", bounds={[round(value, 3) for value in self.bounds.tolist()]}"
        return f"near={self.near:g}, far={self.far:g}, ndc={self.ndc}, contraction={self.contraction}{bounds}"
