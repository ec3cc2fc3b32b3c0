"""A PNG of the cameras, random rays and their samples, and one camera alone with rays from it."""

from __future__ import annotations

import io as _io
from pathlib import Path

import torch
# a bare Figure, not pyplot: drawing a PNG chooses no backend, so importing this leaves a notebook's inline figures be
from matplotlib.figure import Figure

from nerf_lightning.data.scene import Scene
from nerf_lightning.io import write_atomic
from nerf_lightning.viz.rays_sample import RaySample, frustum_corners


def _draw_frusta(axes, scene: Scene, indices: list[int], depth: float, colour: str) -> None:
    train = scene.train
    corners = frustum_corners(train.K[indices], train.c2w[indices], train.height, train.width, depth)
    for index, quad in zip(indices, corners):
        centre = train.c2w[index, :3, 3]
        for corner in quad:
            axes.plot(*torch.stack([centre, corner]).T.numpy(), color=colour, linewidth=0.6)
        loop = torch.cat([quad, quad[:1]])
        axes.plot(*loop.T.numpy(), color=colour, linewidth=0.8)
        # the image's top edge thicker, to show which way is up
        axes.plot(*quad[:2].T.numpy(), color="black", linewidth=1.4)


def _draw_rays(axes, scene: Scene, sample: RaySample, colour: str) -> None:
    near = sample.rays_o + scene.near * sample.rays_d
    far = sample.rays_o + scene.far * sample.rays_d
    for start, end in zip(near, far):
        axes.plot(*torch.stack([start, end]).T.numpy(), color=colour, linewidth=0.9, alpha=0.8)
    points = sample.points.reshape(-1, 3)
    axes.scatter(*points.T.numpy(), s=1.5, color="black", depthshade=False)


def _equal_axes(axes, points: torch.Tensor) -> None:
    low, high = points.amin(0), points.amax(0)
    centre, half = (low + high) / 2, float((high - low).max()) / 2
    for setter, c in zip((axes.set_xlim, axes.set_ylim, axes.set_zlim), centre.tolist()):
        setter(c - half, c + half)
    axes.set_box_aspect((1, 1, 1))
    axes.set_xlabel("x")
    axes.set_ylabel("y")
    axes.set_zlabel("z")


def plot_cameras_and_rays(scene: Scene, all_rays: RaySample, one_camera: RaySample, camera: int, path: str | Path) -> Path:
    """Left: every training camera's frustum, rays drawn from random views between near and far, their
    samples. Right: camera ``camera`` alone with rays through its own pixels, which must stay inside its frustum."""
    train = scene.train
    radius = float(train.c2w[:, :3, 3].norm(dim=-1).mean())
    depth = 0.12 * radius
    figure = Figure(figsize=(13, 6.5), dpi=100)

    left = figure.add_subplot(1, 2, 1, projection="3d")
    _draw_frusta(left, scene, list(range(len(train))), depth, "tab:blue")
    _draw_rays(left, scene, all_rays, "tab:red")
    _equal_axes(left, torch.cat([train.c2w[:, :3, 3], all_rays.points.reshape(-1, 3)]))
    left.set_title(f"{len(train)} training cameras, {all_rays.rays_o.shape[0]} random rays, {all_rays.points.shape[1]} samples each")

    right = figure.add_subplot(1, 2, 2, projection="3d")
    far_depth = scene.far
    _draw_frusta(right, scene, [camera], far_depth, "tab:blue")
    _draw_rays(right, scene, one_camera, "tab:green")
    corners = frustum_corners(train.K[[camera]], train.c2w[[camera]], train.height, train.width, far_depth)[0]
    _equal_axes(right, torch.cat([train.c2w[[camera], :3, 3], corners, one_camera.points.reshape(-1, 3)]))
    right.set_title(f"camera {camera} ({train.names[camera]}) and rays through its pixels")

    figure.suptitle(f"{scene.source}: near {scene.near:g}, far {scene.far:g}")
    figure.tight_layout(rect=(0, 0, 1, 0.95))
    buffer = _io.BytesIO()
    figure.savefig(buffer, format="png")
    return write_atomic(path, buffer.getvalue())
