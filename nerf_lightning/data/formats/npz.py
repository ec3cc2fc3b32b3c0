"""The course's ``.npz``: images_train, c2ws_train, images_val, c2ws_val, c2ws_test (cameras only) and focal.

Its camera-to-world matrices are in the OpenCV convention: the course unprojects pixels with
x_c = s K^-1 [u, v, 1], s > 0, and samples between near and far in front of the camera, which only sees the
scene when the camera looks down its +z axis. The loader checks this instead of trusting it: the point
nearest to every camera's optical axis (where an orbit's cameras look) must lie in front of the cameras.
``convention=auto`` accepts either convention by that test and converts OpenGL; ``opencv`` or ``opengl``
forces one (the check then only confirms it).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from nerf_lightning.data.scene import Scene, Views
from nerf_lightning.geometry.cameras import opengl_to_opencv, validate_c2w
from nerf_lightning.geometry.paths import look_at_point
from nerf_lightning.io import to_uint8

REQUIRED_KEYS = ("images_train", "c2ws_train", "images_val", "c2ws_val", "c2ws_test", "focal")


def looks_forward(c2w: torch.Tensor) -> float:
    """How much (N, 4, 4) OpenCV cameras look at a common point: the mean cosine between each camera's +z axis
    and the direction to the point nearest all optical axes; near +1 for OpenCV orbits, near -1 for OpenGL ones."""
    origins = c2w[:, :3, 3].double()
    axes = torch.nn.functional.normalize(c2w[:, :3, 2].double(), dim=-1)
    # the optical axes are the same lines in either convention; only which way they point differs
    towards = torch.nn.functional.normalize(look_at_point(c2w.double()) - origins, dim=-1)
    return float((towards * axes).sum(-1).mean())


def _images(array: np.ndarray, key: str, path: Path) -> torch.Tensor:
    if array.ndim != 4 or array.shape[-1] != 3:
        raise ValueError(f"{path}: '{key}' has shape {array.shape}; expected (N, H, W, 3)")
    if array.dtype == np.uint8:
        return torch.from_numpy(array)  # kept as uint8, as the scene's other loaders keep theirs
    images = torch.from_numpy(array.astype(np.float32))
    if images.min() < 0 or images.max() > 1:
        raise ValueError(f"{path}: float '{key}' must be in [0, 1] (got {float(images.min()):.3g}..{float(images.max()):.3g}); store uint8 for 0..255")
    return images


def load_npz(
    path: str | Path,
    near: float = 2.0,
    far: float = 6.0,
    convention: str = "auto",
    background: tuple[float, float, float] = (1.0, 1.0, 1.0),
) -> Scene:
    """The course's npz as a Scene with splits train, val (also used as test) and render (c2ws_test)."""
    path = Path(path).expanduser()
    if not path.is_file():
        raise FileNotFoundError(f"npz file not found: {path}")
    try:
        data = dict(np.load(path))
    except Exception as error:
        raise ValueError(f"could not read {path} as an npz archive: {error}") from error
    missing = [key for key in REQUIRED_KEYS if key not in data]
    if missing:
        raise ValueError(f"{path}: missing key(s) {missing}; the course npz has {list(REQUIRED_KEYS)}")
    if convention not in ("auto", "opencv", "opengl"):
        raise ValueError(f"npz convention must be auto, opencv or opengl, got '{convention}'")

    images = {split: _images(data[f"images_{split}"], f"images_{split}", path) for split in ("train", "val")}
    c2ws = {}
    for split in ("train", "val", "test"):
        key = f"c2ws_{split}"
        c2ws[split] = validate_c2w(torch.from_numpy(np.asarray(data[key], dtype=np.float64)).float(), f"{path} '{key}'")
    for split in ("train", "val"):
        if images[split].shape[0] != c2ws[split].shape[0]:
            raise ValueError(f"{path}: 'images_{split}' has {images[split].shape[0]} images but 'c2ws_{split}' {c2ws[split].shape[0]} cameras")
    height, width = images["train"].shape[1:3]
    if images["val"].shape[1:3] != (height, width):
        raise ValueError(f"{path}: 'images_val' are {tuple(images['val'].shape[1:3])} but 'images_train' {(height, width)}: one size expected")
    focal = np.asarray(data["focal"], dtype=np.float64).reshape(-1)
    if focal.size != 1 or not np.isfinite(focal[0]) or focal[0] <= 0:
        raise ValueError(f"{path}: 'focal' must be one positive number, got {data['focal']!r}")

    alignment = looks_forward(c2ws["train"])
    if convention == "auto":
        convention = "opencv" if alignment > 0 else "opengl"
    expected = 1.0 if convention == "opencv" else -1.0
    if alignment * expected < 0.5:
        raise ValueError(
            f"{path}: the cameras of 'c2ws_train' do not look at a common point in the {convention} convention "
            f"(mean cosine {alignment * expected:.2f}); set data.scene.convention to the other one"
        )
    if convention == "opengl":
        c2ws = {split: opengl_to_opencv(matrix) for split, matrix in c2ws.items()}

    f = float(focal[0])
    K = torch.tensor([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])

    def views(split: str, with_images: bool) -> Views:
        count = c2ws[split].shape[0]
        return Views(K=K.expand(count, 3, 3).clone(), c2w=c2ws[split], height=height, width=width,
                     images=images[split] if with_images else None, names=[f"{split}_{i:03d}" for i in range(count)])

    val = views("val", True)
    splits = {"train": views("train", True), "val": val, "test": val, "render": views("test", False)}
    return Scene(splits=splits, near=near, far=far, background=torch.tensor(background, dtype=torch.float32), source=str(path))


def save_npz(scene: Scene, path: str | Path, convention: str = "opencv") -> Path:
    """Write a scene in the course's layout (uint8 images; cameras in ``convention``); for tests and sharing."""
    path = Path(path)
    convert = opengl_to_opencv if convention == "opengl" else (lambda matrix: matrix)
    render = scene.splits.get("render", scene.splits.get("test", scene.train))
    held_out = scene.held_out()

    np.savez(
        path,
        images_train=to_uint8(scene.train.images),
        c2ws_train=convert(scene.train.c2w).numpy(),
        images_val=to_uint8(held_out.images),
        c2ws_val=convert(held_out.c2w).numpy(),
        c2ws_test=convert(render.c2w).numpy(),
        focal=np.float64(scene.train.K[0, 0, 0]),
    )
    return path
