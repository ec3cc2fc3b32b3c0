"""OPENCV_FISHEYE captures: a procedural scene photographed through a fisheye (Kannala-Brandt) lens, written as a
transforms.json, loaded back as the pinhole views its twin camera renders; the lens's pinhole view, bad lenses
refused by key, and a short training run on the capture."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch
from hydra.utils import instantiate
from kornia.metrics import psnr
from kornia.geometry.camera import distort_points_kannala_brandt, undistort_points_kannala_brandt

from nerf_lightning.data.formats import load_transforms
from nerf_lightning.data.formats.lenses import FisheyeLens
from nerf_lightning.data.formats.procedural import camera_positions, shade, trace
from nerf_lightning.data.image_stack import as_float_rgb
from nerf_lightning.data.images import downscale, load_image, load_mask
from nerf_lightning.geometry.cameras import look_at, opengl_to_opencv
from nerf_lightning.geometry.rays import image_pixels, image_rays
from nerf_lightning.io import write_json, write_png
from nerf_lightning.training import train

STEPS, MARGIN_DB = 120, 1.0  # the short run's steps, and how far above black its held-out view must score (16.3 dB, black 13.9)

# a GoPro-like lens on a small sensor: 126 degrees across, 163 corner to corner (its pinhole view of the same focal: 98, 112)
WIDTH, HEIGHT, FOCAL, CX, CY = 96, 80, 42.0, 48.6, 39.7
COEFFICIENTS = (0.05, -0.02, 0.004, -0.0005)  # k1..k4
PHOTO_K = torch.tensor([[FOCAL, 0.0, CX], [0.0, FOCAL, CY], [0.0, 0.0, 1.0]], dtype=torch.float64)
SUPERSAMPLE = 3  # rays a pixel side, area-averaged, so that both renders are antialiased and resampling one costs little


def fisheye_rays(K: torch.Tensor, c2w: torch.Tensor, height: int, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Rays (H * W, 3) each of a fisheye photo of K (3, 3), :data:`COEFFICIENTS` and OpenCV c2w (4, 4): each pixel
    centre undistorted to the z = 1 plane (kornia's inverse; the lens sees less than 90 degrees off axis)."""
    parameters = torch.tensor([K[0, 0], K[1, 1], K[0, 2], K[1, 2], *COEFFICIENTS], dtype=torch.float64)
    on_plane = undistort_points_kannala_brandt(image_pixels(height, width).double(), parameters)
    # the inverse closes: each ray lands back on its pixel
    torch.testing.assert_close(distort_points_kannala_brandt(on_plane, parameters), image_pixels(height, width).double(), atol=1e-6, rtol=0)
    directions = torch.nn.functional.normalize(torch.cat([on_plane, torch.ones_like(on_plane[:, :1])], dim=-1), dim=-1)
    return c2w[:3, 3].expand_as(directions), directions @ c2w[:3, :3].T


def photograph(rays_o: torch.Tensor, rays_d: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """The procedural scene along (H s * W s, 3) rays of a supersampled image -> (H, W, 3) float, area-averaged."""
    hit = trace(rays_o, rays_d)
    rgb = shade(hit, rays_d) * torch.isfinite(hit["t"]).double()[:, None]
    return downscale(rgb.reshape(height * SUPERSAMPLE, width * SUPERSAMPLE, 3).float(), SUPERSAMPLE)


def pinhole_photo(K: torch.Tensor, c2w: torch.Tensor) -> torch.Tensor:
    """The twin: what a pinhole camera of K (3, 3) at OpenCV c2w (4, 4) sees, (H, W, 3)."""
    K = K.double().clone()
    K[:2] *= SUPERSAMPLE
    rays_o, rays_d = image_rays(K[None], c2w[None].double(), HEIGHT * SUPERSAMPLE, WIDTH * SUPERSAMPLE)
    return photograph(rays_o[0], rays_d[0], HEIGHT, WIDTH)


def write_fisheye_capture(root: Path, n_views: int, radius: float = 1.9) -> tuple[Path, torch.Tensor]:
    """``n_views`` fisheye photos of the procedural scene from a sphere of ``radius`` as a transforms.json with
    ``camera_model: OPENCV_FISHEYE`` and k1..k4 at its top level; returns its path and the OpenCV c2w (N, 4, 4)."""
    c2w = look_at(camera_positions(n_views, radius=radius))
    K = PHOTO_K.clone()
    K[:2] *= SUPERSAMPLE
    frames = []
    for index in range(n_views):
        photo = photograph(*fisheye_rays(K, c2w[index], HEIGHT * SUPERSAMPLE, WIDTH * SUPERSAMPLE), HEIGHT, WIDTH)
        write_png(root / "images" / f"{index:03d}.png", photo)
        frames.append({"file_path": f"images/{index:03d}.png", "transform_matrix": opengl_to_opencv(c2w[index]).tolist()})
    write_json(root / "transforms.json", {"camera_model": "OPENCV_FISHEYE", "fl_x": FOCAL, "fl_y": FOCAL, "cx": CX, "cy": CY,
                                          "w": WIDTH, "h": HEIGHT, **dict(zip(("k1", "k2", "k3", "k4"), COEFFICIENTS)), "frames": frames})
    return root, c2w


@pytest.fixture(scope="module")
def fisheye_capture(tmp_path_factory) -> tuple[Path, torch.Tensor]:
    return write_fisheye_capture(tmp_path_factory.mktemp("fisheye") / "capture", n_views=24)


def test_a_fisheye_capture_loads_as_its_pinhole_twin(fisheye_capture):
    root, c2w = fisheye_capture
    views = load_transforms(root, holdout_every=0, normalise=False).train.subset([0, 9, 17])
    torch.testing.assert_close(views.K, PHOTO_K.float().expand(3, 3, 3))  # a fisheye's pinhole view keeps its focal
    undistorted, misread = [], []
    for row, index in enumerate((0, 9, 17)):
        twin = pinhole_photo(views.K[row], c2w[index])
        undistorted.append(float(psnr(as_float_rgb(views.images[row]), twin, 1.0)))
        photo = load_image(root / "images" / f"{index:03d}.png")  # read as a pinhole photo, as it was before
        misread.append(float(psnr(photo, twin, 1.0)))
    # each view its twin but for a bilinear resampling (which cannot make up the detail the fisheye's rim squeezed out
    # of the view's rim) and 8-bit PNGs: 34.7, 35.1 and 36.1 dB here; the photo read as a pinhole 22.1, 17.1 and 19.6
    assert min(undistorted) > 33.0, undistorted
    assert min(u - m for u, m in zip(undistorted, misread)) > 10.0, (undistorted, misread)


def test_a_lens_that_does_not_squeeze_gets_a_longer_focal_so_every_pixel_lies_in_the_photo():
    fisheye = FisheyeLens(COEFFICIENTS)
    K, placed = fisheye.pinhole(PHOTO_K, HEIGHT, WIDTH)
    assert torch.equal(K, PHOTO_K) and placed.photo == (FOCAL, FOCAL, CX, CY)
    pincushion = FisheyeLens((0.6, 0.1, 0.0, 0.0))  # theta_d > tan(theta): the view's corners beyond the photo's
    K, placed = pincushion.pinhole(PHOTO_K, HEIGHT, WIDTH)
    assert float(K[0, 0]) > 1.1 * FOCAL and float(K[1, 1]) == float(K[0, 0]) and torch.equal(K[:2, 2], PHOTO_K[:2, 2])
    on_plane = (image_pixels(HEIGHT, WIDTH).double() - K[:2, 2]) / K.diagonal()[:2]
    landed = distort_points_kannala_brandt(on_plane, torch.tensor([*placed.photo, *placed.coefficients], dtype=torch.float64))
    assert float(landed[..., 0].min()) >= -1e-6 and float(landed[..., 0].max()) <= WIDTH + 1e-6
    assert float(landed[..., 1].min()) >= -1e-6 and float(landed[..., 1].max()) <= HEIGHT + 1e-6
    assert float(landed[..., 0].max()) > WIDTH - 1.0 or float(landed[..., 1].max()) > HEIGHT - 1.0  # no longer than needed


def test_per_frame_lenses_and_bad_lenses_name_the_file_and_key(fisheye_capture, tmp_path):
    root, _ = fisheye_capture
    meta = json.loads((root / "transforms.json").read_text())
    meta["frames"] = [{**frame, "file_path": str(root / frame["file_path"])} for frame in meta["frames"][:3]]
    lens_keys = ("camera_model", "k1", "k2", "k3", "k4")
    frame_meta = {key: meta.pop(key) for key in lens_keys}
    meta["frames"][1].update(frame_meta)  # one fisheye frame among pinhole ones: the lens read per frame
    path = tmp_path / "transforms.json"
    path.write_text(json.dumps(meta))
    views = load_transforms(path, holdout_every=0, normalise=False).train
    assert torch.equal(views.images[1], load_transforms(root, holdout_every=0, normalise=False).train.images[1])  # undistorted
    raw = load_image(root / "images" / "000.png")
    assert torch.equal(as_float_rgb(views.images[0]), raw)  # a frame without camera_model or k's: OPENCV, no distortion
    for change, message in [
        ({"camera_model": "EQUIRECTANGULAR"},
         r"transforms.json: frame 1 \(.*001.png\): 'camera_model' is 'EQUIRECTANGULAR': this loader reads .*OPENCV_FISHEYE"),
        ({"k3": None}, r"transforms.json: frame 1 .*'camera_model' OPENCV_FISHEYE needs k1, k2, k3, k4: 'k3' missing"),
        ({"k2": math.nan}, r"transforms.json: frame 1 .*'k2' is not finite"),
        ({"k4": "big"}, r"transforms.json: frame 1 .*'k4' must be a number, got 'big'"),
        ({"p1": 0.01}, r"'camera_model' OPENCV_FISHEYE has no tangential terms, but 'p1' is not 0"),
    ]:
        broken = json.loads(json.dumps(meta))
        broken["frames"][1].update(change)
        broken["frames"][1] = {key: value for key, value in broken["frames"][1].items() if value is not None}
        path.write_text(json.dumps(broken))
        with pytest.raises(ValueError, match=message):
            load_transforms(path, holdout_every=0, normalise=False)


def test_a_fisheye_captures_masks_are_undistorted_with_its_photos(fisheye_capture, tmp_path):
    root, _ = fisheye_capture
    meta = json.loads((root / "transforms.json").read_text())
    meta["frames"] = meta["frames"][:3]
    for frame in meta["frames"]:
        photo = load_image(root / frame["file_path"])
        frame["file_path"] = str(root / frame["file_path"])
        frame["mask_path"] = str(tmp_path / Path(frame["file_path"]).name)
        write_png(frame["mask_path"], (photo.amax(-1, keepdim=True) > 0).float().expand(-1, -1, 3))  # the scene, not the black
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    views = load_transforms(tmp_path, holdout_every=0, normalise=False).train
    on_scene = as_float_rgb(views.images).amax(-1) > 0.02

    def overlap(masks: torch.Tensor) -> torch.Tensor:  # (V,) intersection over union with where the views show the scene
        return (masks & on_scene).sum(dim=(1, 2)) / (masks | on_scene).sum(dim=(1, 2))

    raw = torch.stack([load_mask(frame["mask_path"]) for frame in meta["frames"]])
    # undistorted: 0.94 to 0.95 (the masks' edges cut at half, the images' at their faintest); as written: 0.77 to 0.81
    assert float(overlap(views.masks).min()) > 0.9 > 0.85 > float(overlap(raw).max())


def test_a_fisheye_capture_trains(fisheye_capture, make_config):
    root, _ = fisheye_capture
    cfg = make_config("experiment=fast", "data/scene=transforms", f"data.root={root}", "data.scene.downscale=1",
                      "trainer.accelerator=cpu", "model.field.encoding.n_levels=4", "model.field.encoding.log2_table_size=12",
                      "model.field.encoding.max_resolution=64", "model.sampler.grid.resolution=16", "data.batch_size=512",
                      "data.val_views=1", f"data.val_every={STEPS}", f"trainer.max_steps={STEPS}", "logger={}", "callbacks=none",
                      "trainer.enable_progress_bar=false", "trainer.enable_model_summary=false")
    metrics = train(cfg)
    datamodule = instantiate(cfg.data)
    datamodule.setup("fit")
    # what a field that learnt nothing renders: the background, black
    black = [float(psnr(torch.zeros_like(batch["image"]), batch["image"], 1.0)) for batch in datamodule.val_dataloader()]
    assert metrics["step"] == STEPS and metrics["val/psnr"] > sum(black) / len(black) + MARGIN_DB, (metrics, black)
