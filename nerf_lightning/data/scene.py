"""The one type every data format loads into: posed views, split, bounds, background and sparse points."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from nerf_lightning.data.points import SparsePoints
from nerf_lightning.geometry.rays import image_rays


@dataclass
class Views:
    """Pinhole views of one image size, cameras in the OpenCV convention (see :mod:`nerf_lightning.geometry.cameras`).

    Attributes:
        K: (N, 3, 3) intrinsics in pixels.
        c2w: (N, 4, 4) camera-to-world.
        height, width: image size in pixels.
        images: (N, H, W, 3) RGB composited onto the scene's background: uint8 0..255 (what the loaders give; possibly
            memory-mapped, see :mod:`~nerf_lightning.data.image_stack`) or float in [0, 1] (views made in code);
            :func:`~nerf_lightning.data.image_stack.as_float_rgb` reads either. None for cameras only (a render path).
        depth: (N, H, W) distance along each pixel's unit ray to the first surface (the procedural scene's true one,
            or a capture's depth maps: :mod:`~nerf_lightning.data.formats.depth_maps`), inf where the ray hits
            nothing, NaN where a pixel's is unknown (a depth map without a reading there); None where unknown.
        masks: (N, H, W) bool, True where a pixel shows the object (a capture's masks: a turntable's object, or the
            part of a photo to learn from; possibly memory-mapped like the images); None where the capture has none.
            What training and evaluation do with them is the datamodule's ``masks`` mode
            (:mod:`~nerf_lightning.data.masks`).
        names: one name per view (its file), for messages and outputs.
    """

    K: torch.Tensor
    c2w: torch.Tensor
    height: int
    width: int
    images: torch.Tensor | None = None
    depth: torch.Tensor | None = None
    masks: torch.Tensor | None = None
    names: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        count = self.c2w.shape[0]
        if self.K.shape != (count, 3, 3) or self.c2w.shape != (count, 4, 4):
            raise ValueError(f"Views need K (N, 3, 3) and c2w (N, 4, 4) with one N, got {tuple(self.K.shape)} and {tuple(self.c2w.shape)}")
        if self.images is not None and self.images.shape != (count, self.height, self.width, 3):
            raise ValueError(f"Views: images {tuple(self.images.shape)} do not match {count} cameras of {self.height}x{self.width}")
        if self.depth is not None and self.depth.shape != (count, self.height, self.width):
            raise ValueError(f"Views: depth {tuple(self.depth.shape)} does not match {count} cameras of {self.height}x{self.width}")
        if self.masks is not None and (self.masks.shape != (count, self.height, self.width) or self.masks.dtype != torch.bool):
            raise ValueError(f"Views: masks {tuple(self.masks.shape)} of {self.masks.dtype} are not {count} bool masks of {self.height}x{self.width}")
        if not self.names:
            self.names = [f"view_{index:03d}" for index in range(count)]

    def __len__(self) -> int:
        return int(self.c2w.shape[0])

    def subset(self, index: torch.Tensor | list[int]) -> Views:
        """The views at ``index``, in that order. A run of consecutive indices slices the images instead of
        copying them, so a split of memory-mapped images stays mapped."""
        index = torch.as_tensor(index, dtype=torch.long)
        start = int(index[0]) if len(index) else 0
        consecutive = start >= 0 and torch.equal(index, torch.arange(start, start + len(index)))

        def take(values: torch.Tensor | None) -> torch.Tensor | None:
            if values is None:
                return None
            return values[start : start + len(index)] if consecutive else values[index]

        return Views(
            K=self.K[index],
            c2w=self.c2w[index],
            height=self.height,
            width=self.width,
            images=take(self.images),
            depth=take(self.depth),
            masks=take(self.masks),
            names=[self.names[int(i)] for i in index],
        )


    def scaled(self, scale: float) -> Views:
        """The same cameras rendering ``scale`` times as many pixels a side (no images)."""
        if scale == 1.0:
            return Views(K=self.K, c2w=self.c2w, height=self.height, width=self.width, names=self.names)
        K = self.K.clone()
        K[:, :2] *= scale
        return Views(K=K, c2w=self.c2w, height=round(self.height * scale), width=round(self.width * scale), names=self.names)

    def surface_points(self) -> torch.Tensor:
        """(P, 3) the true surface points the views see: each pixel's ray at its true depth (float64; needs ``depth``)."""
        if self.depth is None:
            raise ValueError("these views have no true depth: surface points need it")
        rays_o, rays_d = image_rays(self.K.double(), self.c2w.double(), self.height, self.width)
        depth = self.depth.reshape(len(self), -1).double()
        hit = torch.isfinite(depth)
        return (rays_o + rays_d * depth.nan_to_num(posinf=0.0)[..., None])[hit]


@dataclass
class Scene:
    """A multi-view scene.

    Attributes:
        splits: ``train`` (always), ``val`` and ``test`` (held-out images) and optionally ``render`` (cameras
            of a render path, no images).
        near, far: the range along unit rays where the scene lies.
        background: (3,) RGB the images were composited onto, and that rendering blends in.
        source: where it was loaded from, for messages.
        world_from_capture: (4, 4) similarity from the file's coordinates to the scene's (where a loader
            normalised them), to map renders and meshes back; None for the identity.
        aabb_scale: instant-ngp's ``aabb_scale`` of the capture (how far beyond the unit box the scene reaches), if given.
        points: the capture's sparse 3D points in the scene's world (``world_from_capture`` applied), where the
            capture has them (a transforms.json's ``ply_file_path``, a COLMAP model beside an LLFF capture); None otherwise.
    """

    splits: dict[str, Views]
    near: float
    far: float
    background: torch.Tensor = field(default_factory=lambda: torch.ones(3))
    source: str = ""
    world_from_capture: torch.Tensor | None = None
    aabb_scale: float | None = None
    points: SparsePoints | None = None

    def __post_init__(self) -> None:
        if "train" not in self.splits or len(self.splits["train"]) == 0:
            raise ValueError(f"{self.source}: a scene needs at least one training view")
        if not 0 <= self.near < self.far:
            raise ValueError(f"{self.source}: need 0 <= near < far, got near={self.near}, far={self.far}")

    @property
    def train(self) -> Views:
        return self.splits["train"]

    def held_out(self, prefer: str = "val") -> Views:
        """The held-out views: ``prefer`` if the scene has it, else the other of val and test."""
        other = "test" if prefer == "val" else "val"
        for name in (prefer, other):
            if name in self.splits and len(self.splits[name]) and self.splits[name].images is not None:
                return self.splits[name]
        raise ValueError(f"{self.source}: no held-out views with images (val or test); hold some out with data.scene.holdout_every")


def stacking_order(splits: dict[str, list[int]]) -> tuple[list[int], dict[str, list[int]]]:
    """Views of each split (indices into a capture's frames) -> the order to stack the frames' images in, each
    split's in a row and a view shared by splits once, and each split's rows in that stack: consecutive rows, so
    that :meth:`Views.subset` slices every split out of one stack instead of copying it."""
    order = list(dict.fromkeys(index for indices in splits.values() for index in indices))
    row = {index: position for position, index in enumerate(order)}
    return order, {name: [row[index] for index in indices] for name, indices in splits.items()}


def evenly_spaced(count: int, keep: int) -> list[int]:
    """``keep`` indices spread evenly over ``range(count)`` (all of them if keep >= count)."""
    if keep >= count:
        return list(range(count))
    return [round(i * (count - 1) / max(keep - 1, 1)) for i in range(keep)]
