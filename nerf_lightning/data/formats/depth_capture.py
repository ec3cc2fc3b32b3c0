"""A scene with true depth (the procedural one) written as a phone would have captured it: a ``transforms.json``
whose frames carry ``depth_file_path``, each depth map the views' camera z in a 16-bit PNG of millimetres or a
``.npy`` of metres (the scene's units taken as metres), at the photo's size or smaller and with noise, as a LiDAR's
are. What the depth tests read back and what the depth loss is measured on (``scripts/phone_depth_capture.py``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from nerf_lightning.data.formats.depth_maps import write_depth_png
from nerf_lightning.data.formats.transforms import transforms_meta
from nerf_lightning.data.image_stack import as_float_rgb
from nerf_lightning.data.images import downscale_depth
from nerf_lightning.data.scene import Scene, Views
from nerf_lightning.geometry.cameras import pixel_ray_lengths
from nerf_lightning.io import write_json, write_png


def camera_z(views: Views) -> torch.Tensor:
    """(N, H, W) float64 the views' true depth as camera z (what a phone's depth map holds), inf where nothing is hit."""
    lengths = torch.stack([pixel_ray_lengths(K.double(), views.height, views.width) for K in views.K])
    return views.depth.double() / lengths


def phone_depth(z: torch.Tensor, shrink: int = 1, noise: float = 0.0, generator: torch.Generator | None = None) -> torch.Tensor:
    """(H, W) camera z -> (H // shrink, W // shrink) as a phone's sensor gives it: each block's mean (a block that sees
    the background: none, 0), times (1 + ``noise`` x a standard normal) a pixel; 0 where there is no reading."""
    small = downscale_depth(z, shrink)
    small = small * (1.0 + noise * torch.randn(small.shape, generator=generator, dtype=small.dtype))
    return torch.where(torch.isfinite(small) & (small > 0), small, torch.zeros_like(small))


def write_depth_capture(scene: Scene, root: str | Path, suffix: str = ".png", shrink: int = 1, noise: float = 0.0,
                        seed: int = 0, splits: tuple[str, ...] | None = None) -> Path:
    """``scene``'s ``splits`` (views with images and depth; None: each of train, val and test it has) as a
    ``transforms.json`` capture in ``root``: images ``images/<split>_<i>.png``, depth maps ``depth/<split>_<i><suffix>``
    (``.png``: millimetres, ``.npy``: metres) made by :func:`phone_depth` (``shrink``, ``noise``, seeded by ``seed``),
    the splits named (``<split>_filenames``). Returns the json's path."""
    if suffix not in (".png", ".npy"):
        raise ValueError(f"depth maps are written as .png (millimetres) or .npy (metres), got '{suffix}'")
    root = Path(root)
    generator = torch.Generator().manual_seed(seed)
    frames, names = [], {}
    for split in splits or [name for name in ("train", "val", "test") if name in scene.splits]:
        views = scene.splits[split]
        file_paths = [f"images/{split}_{index:03d}.png" for index in range(len(views))]
        meta = transforms_meta(views, file_paths)
        for index, (frame, z) in enumerate(zip(meta["frames"], camera_z(views))):
            write_png(root / frame["file_path"], as_float_rgb(views.images[index]))
            frame["depth_file_path"] = f"depth/{split}_{index:03d}{suffix}"
            depth = phone_depth(z, shrink, noise, generator)
            if suffix == ".png":
                write_depth_png(root / frame["depth_file_path"], depth.numpy())
            else:
                (root / "depth").mkdir(parents=True, exist_ok=True)
                np.save(root / frame["depth_file_path"], depth.numpy())
            frames.append(frame)
        names[f"{split}_filenames"] = file_paths
    path = root / "transforms.json"
    write_json(path, {"w": scene.train.width, "h": scene.train.height, "frames": frames, **names})
    return path

