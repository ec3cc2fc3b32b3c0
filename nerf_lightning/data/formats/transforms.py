"""COLMAP-posed captures in instant-ngp's / nerfstudio's ``transforms.json``.

Intrinsics are global keys, overridable per frame: ``fl_x``, ``fl_y``, ``cx``, ``cy``, ``w``, ``h`` (or
``camera_angle_x`` / ``camera_angle_y`` for the focal lengths, and the image's size for the rest), and the lens:
``camera_model`` with OpenCV's distortion ``k1``, ``k2``, ``p1``, ``p2`` (``k3`` too), or ``OPENCV_FISHEYE`` with
``k1`` to ``k4``. Each frame has ``file_path`` (relative to the json's folder) and ``transform_matrix`` (OpenGL
camera-to-world, as in the Blender scenes). Frames whose image is missing are skipped with one warning naming them.
Images with distortion are undistorted onto a pinhole camera of their size (:mod:`~nerf_lightning.data.formats.lenses`:
the same K, or for a fisheye the K that keeps every pixel inside the photo).

The world is normalised as nerfstudio's ``auto_orient_and_center_poses`` (orientation ``up``) and scale do:
centred on the cameras' focus (``centre="focus"``: the point nearest every optical axis, where an inward-facing
capture's subject is) or on the mean camera centre (``"poses"``), rotated so that the mean camera up is +z, scaled
so that the farthest camera centre coordinate is 1. That 4x4 similarity is kept as ``scene.world_from_capture``,
so renders and meshes can be mapped back to the capture's coordinates, and another file of the same capture can
be loaded into the same world (``world_from_capture=``). ``aabb_scale`` (instant-ngp: the scene reaches that many
times beyond the cameras' unit box) is kept as ``scene.aabb_scale`` and sets the default far bound.

Splits: nerfstudio's ``train_filenames`` / ``val_filenames`` / ``test_filenames`` lists where the json has them,
else every ``holdout_every``-th frame held out as val and test.

Masks: nerfstudio's per-frame ``mask_path`` (relative to the json's folder; ``nerf-process-data masks=`` writes
``masks/<photo>.png``), one mask a frame of its image's full size, the object where it is white (or non-zero in a mask
of 0s and 1s; :func:`~nerf_lightning.data.images.load_mask`), downscaled and undistorted as the image is, into
``views.masks``. Either every frame with an image has one, or none does.

Depth: nerfstudio's per-frame ``depth_file_path`` (a 16-bit PNG in millimetres or a ``.npy`` in metres, the json's
``depth_unit_scale_factor`` where it gives one), a phone's camera-z map of any size of its photo's shape, read into
``views.depth`` as the distance along each pixel's unit ray in the normalised world
(:mod:`~nerf_lightning.data.formats.depth_maps`). Either every frame with an image has one, or none does.

Sparse points: nerfstudio's ``ply_file_path`` (relative to the json's folder; ``nerf-process-data`` writes
``sparse_pc.ply``), a PLY of the capture's points in the json's coordinates, is read into ``scene.points``, mapped by
``world_from_capture`` as the cameras are.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np
import torch

from nerf_lightning.data.formats.depth_maps import capture_depths
from nerf_lightning.data.image_stack import stack_images
from nerf_lightning.data.images import downscale as downscale_image
from nerf_lightning.data.images import image_size, load_image, load_mask
from nerf_lightning.data.formats.lenses import Lens, read_lens
from nerf_lightning.data.formats.shared import apply_similarity, every_frame_or_none, normalising_transform
from nerf_lightning.data.points import SparsePoints, read_ply_points
from nerf_lightning.data.scene import Scene, Views, evenly_spaced, stacking_order
from nerf_lightning.geometry.cameras import opengl_to_opencv, validate_c2w

log = logging.getLogger(__name__)


def _number(frame: dict, meta: dict, key: str, path: Path, where: str) -> float | None:
    value = frame.get(key, meta.get(key))
    if value is None:
        return None
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{path}: {where}'{key}' must be a number, got {value!r}") from None
    if not math.isfinite(value):
        raise ValueError(f"{path}: {where}'{key}' is not finite ({value})")
    return value


def frame_intrinsics(frame: dict, meta: dict, width: int, height: int, path: Path, where: str) -> tuple[torch.Tensor, Lens]:
    """K (3, 3) and lens (:func:`~nerf_lightning.data.formats.lenses.read_lens`) of one frame of a ``width`` x
    ``height`` image, per-frame keys first."""
    def get(key: str) -> float | None:
        return _number(frame, meta, key, path, where)

    for key, actual in (("w", width), ("h", height)):
        declared = get(key)
        if declared is not None and round(declared) != actual:
            raise ValueError(f"{path}: {where}'{key}' is {declared:g} but the image is {width}x{height}")
    fl_x, fl_y = get("fl_x"), get("fl_y")
    angle_x, angle_y = get("camera_angle_x"), get("camera_angle_y")
    if fl_x is None and angle_x is not None:
        fl_x = 0.5 * width / math.tan(0.5 * angle_x)
    if fl_y is None and angle_y is not None:
        fl_y = 0.5 * height / math.tan(0.5 * angle_y)
    if fl_x is None and fl_y is None:
        raise ValueError(f"{path}: {where}no focal length: expected 'fl_x'/'fl_y' or 'camera_angle_x'/'camera_angle_y'")
    fl_x, fl_y = fl_x or fl_y, fl_y or fl_x
    cx, cy = get("cx"), get("cy")
    K = torch.tensor([[fl_x, 0.0, width / 2.0 if cx is None else cx], [0.0, fl_y, height / 2.0 if cy is None else cy], [0.0, 0.0, 1.0]])
    return K, read_lens(frame.get("camera_model", meta.get("camera_model", "OPENCV")), get, f"{path}: {where}")


def undistort(image: torch.Tensor, K: torch.Tensor, lens: Lens) -> torch.Tensor:
    """(H, W, C) image taken through ``lens`` -> the pinhole image of K (3, 3) (the K :func:`frame_lenses` gives)."""
    if not lens.distorts():
        return image
    return lens.undistort(image, K)


def load_transforms(root: str | Path, downscale: int = 1, holdout_every: int = 8, normalise: bool = True, near: float = 0.05,
                    far: float | None = None, background: tuple[float, float, float] = (0.0, 0.0, 0.0), max_views: int | None = None,
                    centre: str = "focus", world_from_capture: torch.Tensor | list | None = None, image_cache: str | None = None) -> Scene:
    """A ``transforms.json`` capture (instant-ngp or nerfstudio).

    Args:
        root: the json file, or the folder that holds ``transforms.json``.
        downscale: integer factor the images are area-averaged by (intrinsics scaled).
        holdout_every: every k-th frame with an image (0, k, 2k, ...) is held out as val and test; 0 for none.
            Ignored where the json names its splits (``train_filenames``, ``val_filenames``, ``test_filenames``).
        normalise: centre, orient and scale the world (see the module's docstring).
        near, far: the sampling range along unit rays, in the normalised world; far by default the diagonal
            of the box of half-size ``aabb_scale`` (2 sqrt(3) aabb_scale), 4 without one.
        background: RGB that transparent pixels (RGBA images) are composited onto.
        max_views: keep at most this many training views, evenly spaced.
        centre: where the normalised world's origin goes: ``focus``, ``poses`` or ``none`` (see the module's docstring).
        world_from_capture: a (4, 4) similarity to use instead of normalising: another scene's
            ``world_from_capture``, to load a second file of the same capture into that scene's world.
        image_cache: a folder to memory-map the decoded images from (written on first use; see
            :mod:`~nerf_lightning.data.image_stack`); None keeps them in memory.
    """
    path, meta = read_transforms_json(root)
    present = frames_with_images(path, meta["frames"])
    lenses, sizes = frame_lenses(path, meta, present, downscale)
    c2w, world_from_capture = capture_world(path, present, normalise, centre, world_from_capture)
    order, rows = stacking_order(frame_splits(path, meta, present, holdout_every, max_views))

    def decode(image_path: Path) -> torch.Tensor:
        return undistort(downscale_image(load_image(image_path, background=background), downscale), *lenses[image_path])

    image_paths = [present[index][2] for index in order]
    images = stack_images(image_paths, decode, cache=image_cache, label=path.parent.name,
                          recipe={"loader": "transforms", "downscale": downscale, "background": list(background)}, depends_on=[path])
    masks = _masks(path, [present[index] for index in order], sizes, lenses, downscale, image_cache)
    depth = capture_depths(path, meta, [present[index] for index in order], sizes, lenses, images.shape[1], images.shape[2],
                           world_from_capture, undistort)
    K = torch.stack([lenses[image_path][0] for image_path in image_paths])
    views = Views(K=K, c2w=c2w[order], height=images.shape[1], width=images.shape[2], images=images, masks=masks, depth=depth,
                  names=[image_path.name for image_path in image_paths])
    aabb_scale = float(meta["aabb_scale"]) if "aabb_scale" in meta else None
    if far is None:
        far = 2.0 * math.sqrt(3.0) * aabb_scale if aabb_scale else 4.0
    return Scene(
        splits={name: views.subset(split_rows) for name, split_rows in rows.items()}, near=near, far=far,
        background=torch.tensor(background, dtype=torch.float32), source=str(path),
        world_from_capture=world_from_capture.float(), aabb_scale=aabb_scale,
        points=sparse_points(path, meta, world_from_capture),
    )


# a frame with an image: (its index among the json's frames, the frame's dict, its image's path)
PresentFrame = tuple[int, dict, Path]


def read_transforms_json(root: str | Path) -> tuple[Path, dict]:
    """The path of the json ``root`` names (the file, or ``transforms.json`` in the folder) and what it holds, checked
    to have a non-empty ``frames`` list. FileNotFoundError or ValueError naming the file."""
    path = Path(root).expanduser()
    if path.is_dir():
        path = path / "transforms.json"
    if not path.is_file():
        raise FileNotFoundError(f"transforms.json not found: {path}")
    try:
        meta = json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise ValueError(f"{path} is not valid JSON: {error}") from error
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        raise ValueError(f"{path}: missing or empty 'frames' (expected a list of frames with file_path and transform_matrix)")
    return path, meta


def frames_with_images(path: Path, frames: list[dict]) -> list[PresentFrame]:
    """The ``frames`` of the json at ``path`` whose image file is there, as (index, frame, image path); a
    ``file_path`` without a suffix finds its ``.png``, ``.jpg`` or ``.jpeg``. The others are skipped with one warning
    naming them; FileNotFoundError where none has its image, ValueError naming a frame without ``file_path`` or
    ``transform_matrix``."""
    present, missing = [], []
    for index, frame in enumerate(frames):
        for key in ("file_path", "transform_matrix"):
            if key not in frame:
                raise ValueError(f"{path}: frame {index}: missing key '{key}'")
        image_path = path.parent / str(frame["file_path"])
        if not image_path.is_file() and image_path.suffix == "":
            image_path = next((image_path.with_suffix(s) for s in (".png", ".jpg", ".jpeg") if image_path.with_suffix(s).is_file()), image_path)
        (present if image_path.is_file() else missing).append((index, frame, image_path))
    if missing:
        names = ", ".join(str(frame["file_path"]) for _, frame, _ in missing)
        log.warning("%s: %d of %d frames have no image file and are skipped: %s", path, len(missing), len(frames), names)
    if not present:
        raise FileNotFoundError(f"{path}: none of its {len(frames)} frames has an image file (first: {frames[0]['file_path']})")
    return present


def frame_lenses(path: Path, meta: dict, present: list[PresentFrame], downscale: int
                 ) -> tuple[dict[Path, tuple[torch.Tensor, Lens]], dict[Path, tuple[int, int]]]:
    """Of each image path of ``present``: the (3, 3) K of its undistorted view, scaled down by ``downscale``, and its
    lens (:func:`frame_intrinsics`); and its full (height, width). From the images' headers, before anything is decoded."""
    lenses, sizes = {}, {}
    for number, frame, image_path in present:
        height, width = sizes[image_path] = image_size(image_path)
        K, lens = frame_intrinsics(frame, meta, width, height, path, f"frame {number} ({frame['file_path']}): ")
        K[:2] /= downscale  # downscale first, then undistort the smaller image: the distortion is in normalised coordinates
        lenses[image_path] = lens.pinhole(K, height // downscale, width // downscale)
    return lenses, sizes


def capture_world(path: Path, present: list[PresentFrame], normalise: bool, centre: str,
                  world_from_capture: torch.Tensor | list | None) -> tuple[torch.Tensor, torch.Tensor]:
    """The frames' cameras in the scene's world: (N, 4, 4) float32 OpenCV camera-to-world, and the (4, 4) float64
    similarity ``world_from_capture`` that maps the json's coordinates there (the one given; else the normalising
    one, :func:`~nerf_lightning.data.formats.shared.normalising_transform`, or the identity without ``normalise``)."""
    try:
        c2w = torch.tensor(np.asarray([frame["transform_matrix"] for _, frame, _ in present], dtype=np.float64))
    except ValueError as error:
        raise ValueError(f"{path}: every 'transform_matrix' must be a 4x4 list of numbers ({error})") from error
    c2w = validate_c2w(c2w, f"{path} 'transform_matrix'")
    if world_from_capture is not None:
        world_from_capture = torch.as_tensor(world_from_capture, dtype=torch.float64)
        if world_from_capture.shape != (4, 4):
            raise ValueError(f"load_transforms: world_from_capture must be 4x4, got {tuple(world_from_capture.shape)}")
    elif normalise:
        world_from_capture = normalising_transform(c2w, centre)
    else:
        world_from_capture = torch.eye(4, dtype=torch.float64)
    return opengl_to_opencv(apply_similarity(world_from_capture, c2w)).float(), world_from_capture


def frame_splits(path: Path, meta: dict, present: list[PresentFrame], holdout_every: int, max_views: int | None) -> dict[str, list[int]]:
    """Indices into ``present`` of each split: the json's named splits (:func:`_named_splits`), else every
    ``holdout_every``-th frame held out as val and test; the training split thinned to ``max_views``, evenly spaced."""
    splits = _named_splits(meta, path, [str(frame["file_path"]) for _, frame, _ in present])
    if splits is None:
        held = list(range(0, len(present), holdout_every)) if holdout_every else []
        splits = {"train": [i for i in range(len(present)) if i not in held]}
        if held:
            splits["val"] = splits["test"] = held
    if max_views:
        splits["train"] = [splits["train"][i] for i in evenly_spaced(len(splits["train"]), max_views)]
    return splits


def sparse_points(path: Path, meta: dict, world_from_capture: torch.Tensor) -> SparsePoints | None:
    """The capture's sparse points from the PLY its ``ply_file_path`` names, mapped by ``world_from_capture`` as the
    cameras are (:func:`~nerf_lightning.data.points.read_ply_points`); None without one, or (with a warning) where the
    file it names is not there."""
    if meta.get("ply_file_path") is None:
        return None
    if not isinstance(meta["ply_file_path"], str):
        raise ValueError(f"{path}: 'ply_file_path' must be a file name, got {meta['ply_file_path']!r}")
    ply = path.parent / meta["ply_file_path"]
    if not ply.is_file():  # the views load without their sparse points: only a model that starts from them needs them
        log.warning("%s: 'ply_file_path' names %s, which is not there: the scene has no sparse points", path, ply)
        return None
    try:
        return read_ply_points(ply, world_from_capture)
    except ValueError as error:
        raise ValueError(f"{path}: 'ply_file_path': {error}") from None


def _masks(path: Path, frames: list[PresentFrame], sizes: dict[Path, tuple[int, int]],
           lenses: dict[Path, tuple[torch.Tensor, Lens]], downscale: int, image_cache: str | None) -> torch.Tensor | None:
    """(N, H, W) bool masks of ``frames`` ((number, frame, image path), in the views' order) from their ``mask_path``,
    downscaled and undistorted as their images; None where no frame has one. ValueError naming the frames without one
    where only some have one, and naming a mask that is missing or of another size than its image."""
    if not every_frame_or_none(path, frames, "mask_path", "its mask"):
        return None
    mask_paths, image_of = [], {}
    for number, frame, image_path in frames:
        if not isinstance(frame["mask_path"], str):
            raise ValueError(f"{path}: frame {number}: 'mask_path' must be a file name, got {frame['mask_path']!r}")
        mask_paths.append(path.parent / frame["mask_path"])
        shared = image_of.setdefault(mask_paths[-1], image_path)
        if shared != image_path and (sizes[shared] != sizes[image_path] or not torch.equal(lenses[shared][0], lenses[image_path][0])
                                     or lenses[shared][1] != lenses[image_path][1]):
            raise ValueError(f"{path}: frame {number}: 'mask_path' {frame['mask_path']} is also the mask of {shared.name}, whose "
                             "size or lens differs: frames of different cameras need masks of their own")

    def decode(mask_path: Path) -> torch.Tensor:
        image_path = image_of[mask_path]
        mask = load_mask(mask_path, size=sizes[image_path], downscale_by=downscale)
        K, lens = lenses[image_path]
        if not lens.distorts():
            return mask
        return undistort(mask[..., None].float().expand(-1, -1, 3), K, lens)[..., 0] >= 0.5

    return stack_images(mask_paths, decode, cache=image_cache, label=f"{path.parent.name}-masks",
                        recipe={"loader": "transforms-masks", "downscale": downscale}, depends_on=[path])


def _named_splits(meta: dict, path: Path, file_paths: list[str]) -> dict[str, list[int]] | None:
    """nerfstudio's ``<split>_filenames`` lists -> view indices of each split; None where the json names none."""
    named = {split: meta[f"{split}_filenames"] for split in ("train", "val", "test") if f"{split}_filenames" in meta}
    if not named:
        return None
    index_of = {}
    for index, file_path in enumerate(file_paths):
        index_of[file_path] = index_of[Path(file_path).as_posix().removeprefix("./")] = index
    splits = {}
    for split, filenames in named.items():
        known = [index_of.get(str(name), index_of.get(Path(str(name)).as_posix().removeprefix("./"))) for name in filenames]
        splits[split] = [index for index in known if index is not None]
        if len(splits[split]) < len(filenames):
            log.warning("%s: %d of the %d '%s_filenames' have no frame with an image", path, len(filenames) - len(splits[split]), len(filenames), split)
    if not splits.get("train"):
        raise ValueError(f"{path}: 'train_filenames' names no frame with an image (expected file_path values of its frames)")
    return splits


def transforms_meta(views: Views, file_paths: list[str], world_from_capture: torch.Tensor | None = None) -> dict:
    """The inverse of :func:`load_transforms`: views as a ``transforms.json`` dict (per-frame intrinsics, OpenGL
    ``transform_matrix``), mapped back to the capture's coordinates by the inverse of ``world_from_capture``."""
    c2w = opengl_to_opencv(views.c2w.double())
    if world_from_capture is not None:
        c2w = apply_similarity(torch.linalg.inv(world_from_capture.double()), c2w)
    frames = [
        {"file_path": file_path, "fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]),
         "transform_matrix": matrix.tolist()}
        for file_path, K, matrix in zip(file_paths, views.K, c2w)
    ]
    return {"w": views.width, "h": views.height, "frames": frames}
