"""LLFF forward-facing captures (NeRF's ``nerf_llff_data`` layout).

``poses_bounds.npy`` is (N, 17): per view a 3x5 matrix, flattened row by row, whose first three columns are the
camera-to-world rotation with the axes [down, right, back], the fourth the camera centre and the fifth
[H, W, focal] of the full-size images, then the near and far depth bounds of the view's scene points. Images are
in ``images/`` (full size) or ``images_<k>/`` (downscaled k times), sorted by name, one per row.

As in the NeRF code (``load_llff.py``): the axes become [right, up, back] (OpenGL), the scene is scaled so that the
nearest bound is 1 / ``bd_factor``, and recentred on the average camera (its position the mean centre, its back
axis the mean back axis), so the cameras look down -z of the world; that similarity is kept as
``scene.world_from_capture``. Views are then converted to this project's
OpenCV cameras. The ``spiral`` split (what ``render.path=spiral`` renders) is NeRF's spiral: ``n_frames`` cameras on two turns of an ellipse around the
average camera, looking at the focus depth, with radii the 90th percentile of the camera offsets.

A capture that walks all around its subject (``layout="360"``; COLMAP's ``imgs2poses`` writes the same file for it)
is not forward-facing: NDC cannot hold it. It is normalised as a ``transforms.json`` capture is
(:func:`~nerf_lightning.data.formats.shared.normalising_transform`: centred on the cameras' focus, mean up +z,
the farthest camera coordinate 1), for the contraction (``data.contract=true``, ``experiment=nerfacto_360_cpu``),
and its render path is the orbit other 360 captures get.

Masks: a ``masks/`` folder beside ``images/`` (or ``masks_<k>/`` beside ``images_<k>/``), one mask an image with its
image's stem (any image format), the object where it is white (:func:`~nerf_lightning.data.images.load_mask`), at the
full size and downscaled as the images are, into ``views.masks``.

A COLMAP sparse model beside the images (``sparse/0/points3D.bin`` or ``.txt``, where ``imgs2poses`` leaves it) gives
``scene.points``, mapped into the scene's world by ``world_from_capture`` as the cameras are.
"""

from __future__ import annotations

import logging
import math
import shutil
from pathlib import Path

import numpy as np
import torch

from nerf_lightning.data.image_stack import stack_images
from nerf_lightning.data.images import downscale as area_downscale
from nerf_lightning.data.images import downscale_mask, load_image, load_mask
from nerf_lightning.io import write_png
from nerf_lightning.data.scene import Scene, Views, evenly_spaced, stacking_order
from nerf_lightning.data.formats.shared import apply_similarity, normalising_transform
from nerf_lightning.data.points import read_colmap_points
from nerf_lightning.geometry.cameras import opengl_to_opencv, validate_c2w

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
LAYOUTS = ("forward", "360")


def _normalize(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _view_matrix(back: np.ndarray, up: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """(3, 4) OpenGL camera-to-world with the given back axis, approximately the given up, at ``centre``."""
    z = _normalize(back)
    x = _normalize(np.cross(up, z))
    y = np.cross(z, x)
    return np.stack([x, y, z, centre], axis=1)


def average_pose(c2w: np.ndarray) -> np.ndarray:
    """(N, 3, 4) OpenGL cameras -> (3, 4) their average: mean centre, mean back axis, mean up."""
    return _view_matrix(c2w[:, :3, 2].sum(0), c2w[:, :3, 1].sum(0), c2w[:, :3, 3].mean(0))


def llff_spiral(c2w: np.ndarray, bounds: np.ndarray, n_frames: int = 120, turns: int = 2, z_rate: float = 0.5) -> np.ndarray:
    """NeRF's ``render_path_spiral`` for (N, 3, 4) recentred OpenGL cameras: (n_frames, 3, 4) OpenGL cameras."""
    average = average_pose(c2w)
    up = _normalize(c2w[:, :3, 1].sum(0))
    close_depth, infinity_depth = bounds.min() * 0.9, bounds.max() * 5.0
    weight = 0.75
    focus = 1.0 / ((1.0 - weight) / close_depth + weight / infinity_depth)
    radii = np.percentile(np.abs(c2w[:, :3, 3]), 90, axis=0)
    frames = []
    for theta in np.linspace(0.0, 2.0 * math.pi * turns, n_frames + 1)[:-1]:
        centre = average[:, :3] @ (np.array([math.cos(theta), -math.sin(theta), -math.sin(theta * z_rate)]) * radii) + average[:, 3]
        look_at = average[:, :3] @ np.array([0.0, 0.0, -focus]) + average[:, 3]
        frames.append(_view_matrix(centre - look_at, up, centre))
    return np.stack(frames)


def _homogeneous(c2w: np.ndarray) -> np.ndarray:
    bottom = np.broadcast_to(np.array([0.0, 0.0, 0.0, 1.0]), (*c2w.shape[:-2], 1, 4))
    return np.concatenate([c2w, bottom], axis=-2)


def read_poses_bounds(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``poses_bounds.npy`` -> (N, 3, 4) OpenGL camera-to-world, (N, 3) [H, W, focal], (N, 2) near/far bounds."""
    if not path.is_file():
        raise FileNotFoundError(f"LLFF poses not found: {path}")
    try:
        array = np.load(path)
    except Exception as error:
        raise ValueError(f"could not read {path}: {error}") from error
    if array.ndim != 2 or array.shape[1] != 17 or array.shape[0] == 0:
        raise ValueError(f"{path}: expected an (N, 17) array (a 3x5 pose and 2 bounds a view), got shape {array.shape}")
    if not np.isfinite(array).all():
        raise ValueError(f"{path}: view {int(np.nonzero(~np.isfinite(array).all(1))[0][0])} has non-finite values")
    poses = array[:, :15].reshape(-1, 3, 5).astype(np.float64)
    bounds = array[:, 15:].astype(np.float64)
    # [down, right, back] -> [right, up, back]
    c2w = np.concatenate([poses[:, :, 1:2], -poses[:, :, 0:1], poses[:, :, 2:4]], axis=2)
    return c2w, poses[:, :, 4], bounds


def write_poses_bounds(path: str | Path, c2w_opencv: torch.Tensor, height: int, width: int, focal: float, bounds: np.ndarray) -> Path:
    """Write (N, 4, 4) OpenCV cameras with their [H, W, focal] and (N, 2) bounds as ``poses_bounds.npy``."""
    c2w = c2w_opencv.double().numpy()
    # OpenCV [right, down, forward] -> LLFF [down, right, back]
    rotation = np.stack([c2w[:, :3, 1], c2w[:, :3, 0], -c2w[:, :3, 2]], axis=2)
    hwf = np.broadcast_to(np.array([height, width, focal], dtype=np.float64)[None, :, None], (len(c2w), 3, 1))
    poses = np.concatenate([rotation, c2w[:, :3, 3:4], hwf], axis=2)
    path = Path(path)
    np.save(path, np.concatenate([poses.reshape(-1, 15), np.asarray(bounds, dtype=np.float64)], axis=1))
    return path


log = logging.getLogger(__name__)


def downscaled_folder(root: Path, factor: int) -> Path:
    """``root/images_<factor>``, written once from the full-size ``root/images`` by area averaging when a capture has
    only those (what COLMAP's ``imgs2poses`` leaves; LLFF's own ``minify`` does the same). Written into a temporary
    folder and renamed, so an interrupted run leaves no half folder."""
    folder, full = root / f"images_{factor}", root / "images"
    if folder.is_dir() or factor == 1 or not full.is_dir():
        return folder
    files = sorted(p for p in full.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        return folder
    log.info("%s: writing images_%d/ from the %d full-size images (once; later runs read it)", root, factor, len(files))
    partial = root / f".images_{factor}.partial"
    shutil.rmtree(partial, ignore_errors=True)
    for path in files:
        write_png(partial / f"{path.stem}.png", area_downscale(load_image(path), factor))
    partial.rename(folder)
    return folder


def read_masks(root: Path, files: list[Path], downscale: int, size: tuple[int, int], image_cache: str | None) -> torch.Tensor | None:
    """(N, H, W) bool masks of the image ``files`` (of ``size`` (H, W)) from ``root/masks_<downscale>/`` or else
    ``root/masks/`` (downscaled to ``size``), matched by stem; None where the capture has neither folder."""
    folder = root / f"masks_{downscale}" if (root / f"masks_{downscale}").is_dir() and downscale != 1 else root / "masks"
    if not folder.is_dir():
        return None
    by_stem = {path.stem: path for path in sorted(folder.iterdir()) if path.is_file() and not path.name.startswith(".")}
    missing = [file.name for file in files if file.stem not in by_stem]
    if missing:
        raise ValueError(f"{folder} has no mask for {len(missing)} of the {len(files)} images ({', '.join(missing[:5])}"
                         f"{' ...' if len(missing) > 5 else ''}): give each image a mask of its stem, or remove the folder")

    def decode(path: Path) -> torch.Tensor:
        mask = load_mask(path)
        factor = mask.shape[1] // size[1]
        if factor < 1 or mask.shape[0] // factor != size[0] or mask.shape[1] // factor != size[1]:
            raise ValueError(f"mask {path} is {mask.shape[1]}x{mask.shape[0]}: neither its image's {size[1]}x{size[0]} nor a whole multiple of it")
        return downscale_mask(mask, factor)

    return stack_images([by_stem[file.stem] for file in files], decode, cache=image_cache, label=f"{root.name}-{folder.name}",
                        recipe={"loader": "llff-masks", "size": list(size)})


def load_llff(root: str | Path, downscale: int = 8, holdout_every: int = 8, bd_factor: float | None = 0.75, recentre: bool = True,
              near: float | None = None, far: float | None = None, render_frames: int = 120, max_views: int | None = None,
              image_cache: str | None = None, layout: str = "forward") -> Scene:
    """An LLFF capture.

    Args:
        root: the folder with ``poses_bounds.npy`` and ``images[_k]/``.
        downscale: k of the ``images_<k>`` folder to read (1 reads ``images/``); sizes and the focal length are
            scaled from the npy's full-size [H, W, focal] by the images' actual size. A capture with only the
            full-size ``images/`` gets its ``images_<k>/`` written once (:func:`downscaled_folder`).
        holdout_every: every k-th view (0, k, 2k, ...) is held out as val and test (NeRF's ``llffhold`` = 8).
        bd_factor: scale the scene so that the nearest bound is 1 / bd_factor (None: no scaling).
        recentre: move the world to the average camera.
        near, far: the sampling range; by default 0.9 x the smallest bound and the largest bound.
        render_frames: frames of the ``spiral`` split.
        max_views: keep at most this many training views, evenly spaced.
        image_cache: a folder to memory-map the decoded images from (written on first use; see
            :mod:`~nerf_lightning.data.image_stack`); None keeps them in memory.
        layout: ``forward`` (cameras looking one way, NeRF's LLFF scenes: ``bd_factor`` and ``recentre`` apply, for
            NDC) or ``360`` (cameras all around the subject: normalised as a transforms.json capture, see the
            module's docstring; near 0.05 and far 1.5 x the farthest bound by default).
    """
    layout = str(layout)  # data.scene.layout=360 on the command line: Hydra reads the name as the number 360
    if layout not in LAYOUTS:
        raise ValueError(f"data.scene.layout must be one of {LAYOUTS} (forward-facing, or all around the subject), got '{layout}'")
    root = Path(root).expanduser()
    if not root.is_dir():
        raise FileNotFoundError(f"LLFF scene folder not found: {root}")
    c2w, hwf, bounds = read_poses_bounds(root / "poses_bounds.npy")
    folder, files = image_files(root, downscale, len(c2w))
    held, order, rows = view_splits(len(files), holdout_every, max_views)
    images = stack_images([files[i] for i in order], load_image, cache=image_cache, label=f"{root.name}-{folder.name}", recipe={"loader": "llff"})
    height, width = images.shape[1:3]
    masks = read_masks(root, [files[i] for i in order], downscale, (height, width), image_cache)
    focal = scaled_focal(folder, hwf[0], width, height)
    c2w, bounds, world_from_capture = capture_world(c2w, bounds, layout, bd_factor, recentre)
    near = (0.05 if layout == "360" else float(bounds.min() * 0.9)) if near is None else near
    spiral = llff_spiral(c2w, bounds, render_frames) if layout == "forward" else None

    def to_opencv(matrices: np.ndarray, source: str) -> torch.Tensor:
        return opengl_to_opencv(validate_c2w(torch.from_numpy(_homogeneous(matrices)), source)).float()

    cameras = to_opencv(c2w, f"{root / 'poses_bounds.npy'}")[order]
    K = torch.tensor([[focal, 0.0, width / 2.0], [0.0, focal, height / 2.0], [0.0, 0.0, 1.0]], dtype=torch.float32)
    views = Views(K=K.expand(len(order), 3, 3).clone(), c2w=cameras, height=height, width=width, images=images, masks=masks,
                  names=[files[i].name for i in order])
    splits = {name: views.subset(split_rows) for name, split_rows in rows.items()}
    if held:
        splits["test"] = splits["val"]
    if spiral is not None:  # a 360 capture gets the orbit of the other 360 captures
        splits["spiral"] = Views(K=K.expand(len(spiral), 3, 3).clone(), c2w=to_opencv(spiral, "the LLFF spiral"), height=height, width=width)
    far = float(bounds.max()) * (1.0 if layout == "forward" else 1.5) if far is None else far
    points = read_colmap_points(root / "sparse" / "0", torch.from_numpy(world_from_capture))
    return Scene(splits=splits, near=near, far=far, background=torch.zeros(3), source=str(root),
                 world_from_capture=torch.from_numpy(world_from_capture).float(), points=points)


def image_files(root: Path, downscale: int, poses: int) -> tuple[Path, list[Path]]:
    """The folder of the images ``downscale`` reads (``images/`` for 1, else ``images_<k>/``, written where only
    ``images/`` is there: :func:`downscaled_folder`) and its images, sorted by name. FileNotFoundError naming the
    image folders the capture has where that one is missing; ValueError where its images are not one a pose of the
    ``poses``."""
    folder = root / "images" if downscale == 1 else downscaled_folder(root, downscale)
    if not folder.is_dir():
        available = sorted(p.name for p in root.iterdir() if p.is_dir() and p.name.startswith("images"))
        raise FileNotFoundError(f"{folder} not found: data.scene.downscale={downscale} reads it; {root} has {available or 'no image folders'}")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if len(files) != poses:
        raise ValueError(f"{folder} has {len(files)} images but {root / 'poses_bounds.npy'} has {poses} poses: expected one image a pose")
    return folder, files


def view_splits(count: int, holdout_every: int, max_views: int | None) -> tuple[list[int], list[int], dict[str, list[int]]]:
    """Of ``count`` views, the held-out ones (every ``holdout_every``-th, NeRF's ``llffhold``), and the order they
    are stacked in with each split's rows (:func:`~nerf_lightning.data.scene.stacking_order` of the training views,
    thinned to ``max_views``, and the held-out ones as ``val``)."""
    held = list(range(0, count, holdout_every)) if holdout_every else []
    train = [i for i in range(count) if i not in held]
    if max_views:
        train = [train[i] for i in evenly_spaced(len(train), max_views)]
    order, rows = stacking_order({"train": train, "val": held} if held else {"train": train})
    return held, order, rows


def scaled_focal(folder: Path, full_hwf: np.ndarray, width: int, height: int) -> float:
    """The focal length of ``folder``'s ``width`` x ``height`` images, from the poses' full-size [H, W, focal];
    ValueError where those images are not a uniform downscale of that size."""
    full_height, full_width, full_focal = full_hwf
    scale_x, scale_y = full_width / width, full_height / height
    if abs(scale_x - scale_y) > 0.02 * scale_x:
        raise ValueError(f"{folder}: images of {width}x{height} are not a uniform downscale of the poses' {full_width:.0f}x{full_height:.0f}")
    return full_focal / scale_x


def capture_world(c2w: np.ndarray, bounds: np.ndarray, layout: str, bd_factor: float | None, recentre: bool
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N, 3, 4) OpenGL cameras and (N, 2) bounds moved into the scene's world (see the module's docstring: a
    ``360`` capture normalised as a transforms.json one; a forward-facing one scaled by ``bd_factor`` and, with
    ``recentre``, moved to its average camera); and the (4, 4) similarity ``world_from_capture`` that does it."""
    world_from_capture = np.eye(4)  # the similarity below, kept with the scene to map results back
    if layout == "360":
        similarity = normalising_transform(torch.from_numpy(_homogeneous(c2w)), "focus")
        c2w = apply_similarity(similarity, torch.from_numpy(_homogeneous(c2w))).numpy()[:, :3]
        scale = float(similarity[:3, :3].det().abs() ** (1.0 / 3.0))
        bounds, world_from_capture = bounds * scale, similarity.numpy()
    elif bd_factor is not None:
        scale = 1.0 / (bounds.min() * bd_factor)
        c2w[:, :3, 3] *= scale
        bounds = bounds * scale
        world_from_capture = np.diag([scale, scale, scale, 1.0])
    if recentre and layout == "forward":
        recentring = np.linalg.inv(_homogeneous(average_pose(c2w)))
        c2w = (recentring @ _homogeneous(c2w))[:, :3]
        world_from_capture = recentring @ world_from_capture
    return c2w, bounds, world_from_capture
