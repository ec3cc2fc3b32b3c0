"""Blender synthetic scenes (NeRF's nerf_synthetic layout).

``transforms_{train,val,test}.json`` each hold ``camera_angle_x`` (horizontal field of view, radians) and
``frames``, each with ``file_path`` (an RGBA PNG, ``.png`` implied when missing) and ``transform_matrix``
(OpenGL camera-to-world). Alpha is composited onto the background. This project's procedural scene adds
``depth_<split>.npy`` (N, H, W) of true ray distances, read when present.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

from nerf_lightning.data.image_stack import stack_images
from nerf_lightning.data.images import downscale as downscale_image
from nerf_lightning.data.images import load_image
from nerf_lightning.data.scene import Scene, Views, evenly_spaced
from nerf_lightning.geometry.cameras import opengl_to_opencv, validate_c2w


def _read_json(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise ValueError(f"{path} is not valid JSON: {error}") from error


def _require(mapping: dict, key: str, path: Path, where: str = "") -> object:
    if key not in mapping:
        raise ValueError(f"{path}: {where}missing key '{key}'")
    return mapping[key]


def load_blender_split(
    root: Path, split: str, downscale: int = 1, background: torch.Tensor | None = None, max_views: int | None = None,
    image_cache: str | None = None,
) -> Views:
    """One ``transforms_<split>.json`` as :class:`Views` with OpenCV cameras; images area-averaged by ``downscale``,
    kept as uint8 (memory-mapped from ``image_cache`` where given, see :func:`stack_images`)."""
    path = root / f"transforms_{split}.json"
    meta = _read_json(path)
    angle = float(_require(meta, "camera_angle_x", path))
    frames = _require(meta, "frames", path)
    if not isinstance(frames, list) or not frames:
        raise ValueError(f"{path}: 'frames' must be a non-empty list")
    if max_views:
        frames = [frames[i] for i in evenly_spaced(len(frames), max_views)]
    background = torch.ones(3) if background is None else background

    matrices, image_paths = [], []
    for index, frame in enumerate(frames):
        file_path = str(_require(frame, "file_path", path, f"frame {index}: "))
        matrices.append(_require(frame, "transform_matrix", path, f"frame {index}: "))
        image_path = root / file_path
        image_paths.append(image_path.with_suffix(".png") if image_path.suffix == "" else image_path)
    try:
        c2w = torch.tensor(np.asarray(matrices, dtype=np.float64), dtype=torch.float32)
    except ValueError as error:
        raise ValueError(f"{path}: every 'transform_matrix' must be a 4x4 list of numbers ({error})") from error
    c2w = opengl_to_opencv(validate_c2w(c2w, f"{path} 'transform_matrix'"))
    colour = tuple(background.tolist())
    images = stack_images(image_paths, lambda image_path: downscale_image(load_image(image_path, background=colour), downscale),
                          cache=image_cache, label=f"{root.name}-{split}", recipe={"loader": "blender", "downscale": downscale, "background": colour})

    height, width = images.shape[1:3]
    focal = 0.5 * width / math.tan(0.5 * angle)  # of the (downscaled) image
    K = torch.tensor([[focal, 0.0, width / 2.0], [0.0, focal, height / 2.0], [0.0, 0.0, 1.0]]).expand(len(frames), 3, 3).clone()

    depth = None
    depth_path = root / f"depth_{split}.npy"
    if depth_path.is_file() and downscale == 1:
        depth = torch.from_numpy(np.load(depth_path)).float()
        if max_views:
            depth = depth[evenly_spaced(depth.shape[0], max_views)]
    return Views(K=K, c2w=c2w, height=height, width=width, images=images, depth=depth,
                 names=[image_path.name for image_path in image_paths])


def load_blender(
    root: str | Path,
    downscale: int = 1,
    background: tuple[float, float, float] = (1.0, 1.0, 1.0),
    near: float = 2.0,
    far: float = 6.0,
    holdout_every: int | None = None,
    max_views: int | None = None,
    image_cache: str | None = None,
) -> Scene:
    """A Blender synthetic scene: ``train`` from transforms_train.json, ``val`` from transforms_val.json and
    ``test`` from transforms_test.json, or from val when there is no test file.

    Args:
        root: the scene folder.
        downscale: integer factor (4 gives lego's 200x200 from 800x800); the focal length is scaled with it.
        background: RGB in [0, 1] that transparent pixels are composited onto (white by default).
        near, far: the range along unit rays (2 and 6 for the synthetic scenes).
        holdout_every: move every k-th training view (0, k, 2k, ...) to the val split (useful when a capture
            comes without one).
        max_views: keep at most this many views of each split, evenly spaced (quick runs).
        image_cache: a folder to memory-map the decoded images from (written on first use; see
            :mod:`~nerf_lightning.data.image_stack`); None keeps them in memory.
    """
    root = Path(root).expanduser()
    if not root.is_dir():
        raise FileNotFoundError(f"Blender scene folder not found: {root}")
    if not (root / "transforms_train.json").is_file():
        raise FileNotFoundError(f"{root} has no transforms_train.json: expected a Blender synthetic scene (transforms_{{train,val,test}}.json)")
    colour = torch.tensor(background, dtype=torch.float32)
    splits = {"train": load_blender_split(root, "train", downscale, colour, max_views, image_cache)}
    for split in ("val", "test"):
        if (root / f"transforms_{split}.json").is_file():
            splits[split] = load_blender_split(root, split, downscale, colour, max_views, image_cache)
    if holdout_every:
        count = len(splits["train"])
        held = list(range(0, count, holdout_every))
        splits["val"] = splits["train"].subset(held)
        splits["train"] = splits["train"].subset([i for i in range(count) if i % holdout_every])
    if "test" not in splits and "val" in splits:
        splits["test"] = splits["val"]
    return Scene(splits=splits, near=near, far=far, background=colour, source=str(root))
