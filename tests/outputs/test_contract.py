"""The model contract: the output layer works with any model that renders a camera, and asks the rest by capability."""

from __future__ import annotations

import json

import imageio.v3 as iio
import pytest
import torch
from torch import nn

from nerf_lightning.data.scene import Views
from nerf_lightning.geometry.rays import image_rays
from nerf_lightning.geometry.space import SceneSpace
from nerf_lightning.models import ImageFieldModule, RadianceFieldModule
from nerf_lightning.models.contract import HasDensity, RendersCamera, RendersImage, ShowsOverlays, implements
from nerf_lightning.outputs.evaluation import evaluate_views
from nerf_lightning.outputs.export import export_model, formats_of
from nerf_lightning.outputs.frames import write_path_renders


class Sphere(nn.Module):
    """A kind of model the output layer has never heard of: a red ball of radius 1 at the origin, ray-traced.

    It implements only :class:`RendersCamera` (no field, sampler, density or rays from a data module)."""

    def __init__(self) -> None:
        super().__init__()
        self.space = SceneSpace(near=2.0, far=6.0, background=(1.0, 1.0, 1.0))
        self.register_buffer("colour", torch.tensor([0.9, 0.1, 0.1]))

    @property
    def device(self) -> torch.device:
        return self.colour.device

    @torch.no_grad()
    def render_view(self, K, c2w, height, width, abort=None):
        origins, directions = image_rays(K[None].float(), c2w[None].float(), height, width)
        origins, directions = origins[0], directions[0]
        b = (origins * directions).sum(-1)
        disc = b.square() - (origins.square().sum(-1) - 1.0)
        hit = disc > 0
        depth = torch.where(hit, -b - disc.clamp(min=0).sqrt(), torch.zeros_like(b))
        accumulation = hit.float()
        rgb = accumulation[:, None] * self.colour + (1 - accumulation[:, None]) * self.space.background
        return {"rgb": rgb.reshape(height, width, 3), "depth": depth.reshape(height, width), "accumulation": accumulation.reshape(height, width)}


def orbit_views(n: int = 3, size: int = 24, with_images: bool = False, model=None) -> Views:
    K = torch.tensor([[30.0, 0.0, size / 2], [0.0, 30.0, size / 2], [0.0, 0.0, 1.0]]).expand(n, 3, 3).clone()
    c2w = torch.eye(4).expand(n, 4, 4).clone()
    for i in range(n):  # cameras on a circle of radius 4 looking at the origin (OpenCV: +z forward, +y down)
        angle = 2 * torch.pi * i / n
        position = torch.tensor([4 * torch.cos(torch.tensor(angle)), 4 * torch.sin(torch.tensor(angle)), 0.0])
        forward = -position / position.norm()
        down = torch.tensor([0.0, 0.0, -1.0])
        right = torch.linalg.cross(down, forward)
        c2w[i, :3, :3] = torch.stack([right, down, forward], dim=1)
        c2w[i, :3, 3] = position
    views = Views(K=K, c2w=c2w, height=size, width=size)
    if with_images:
        views.images = torch.stack([model.render_view(K[i], c2w[i], size, size)["rgb"] for i in range(n)])
    return views


def test_a_new_kind_of_model_evaluates_and_renders_paths_through_the_contract(tmp_path):
    model = Sphere()
    assert implements(model, RendersCamera) and not implements(model, HasDensity) and not implements(model, ShowsOverlays)
    views = orbit_views(with_images=True, model=model)
    views.images[0, :4] = 0.0  # one view differs from its render: a finite PSNR there, infinite (perfect) on the others
    rows = evaluate_views(model, views, tmp_path / "eval")
    assert len(rows) == 3 and rows[0]["psnr"] < 40 and rows[1]["psnr"] > 60
    # beside each raw score the colour-corrected one: the four changed pixels are no global colour change
    assert rows[0]["cc_psnr"] < 40 and rows[0]["cc_ssim"] <= 1.0 and "cc_psnr_masked" not in rows[0]
    assert (tmp_path / "eval" / "images" / "view_000_depth.png").is_file()

    written = write_path_renders(model, orbit_views(), tmp_path / "path")
    names = {path.name for path in written}
    assert {"rgb.gif", "depth.gif", "transforms.json", "rgb_0000.png"} <= names
    frame = iio.imread(tmp_path / "path" / "frames" / "rgb_0000.png")
    assert tuple(frame[12, 12]) == (230, 26, 26) and tuple(frame[0, 0]) == (255, 255, 255)  # the ball in the middle, background around
    assert len(json.loads((tmp_path / "path" / "transforms.json").read_text())["frames"]) == 3


def test_export_names_what_a_model_without_a_density_can_export(tmp_path):
    assert formats_of(Sphere()) == []
    with pytest.raises(ValueError, match=r"format=ply needs Gaussians \(a splat PLY\) or a density to mesh .*model, Sphere, has none: it has nothing nerf-export writes"):
        export_model(Sphere(), "ply", tmp_path, {})
    with pytest.raises(ValueError, match=r"format must be one of ply, obj, glb, spz, got 'stl'"):
        export_model(Sphere(), "stl", tmp_path, {})


def test_the_shipped_models_declare_their_capabilities(make_config):
    from hydra.utils import instantiate

    radiance = instantiate(make_config("experiment=fast").model)
    assert isinstance(radiance, RadianceFieldModule)
    assert implements(radiance, RendersCamera) and implements(radiance, HasDensity) and implements(radiance, ShowsOverlays)
    assert formats_of(radiance) == ["ply", "obj", "glb"]
    assert set(radiance.overlay_names()) == {"box", "occupied_cells"}
    box = radiance.overlay("box")
    assert box.kind == "lines" and box.points.shape == (12, 2, 3)
    image = instantiate(make_config("experiment=image").model)
    assert isinstance(image, ImageFieldModule) and implements(image, RendersImage) and not implements(image, RendersCamera)


def test_render_view_of_a_radiance_field_is_its_rays_rendered(make_config):
    """render_view (the contract) gives what rendering the view's rays gives, shaped as an image."""
    from hydra.utils import instantiate

    model = instantiate(make_config("experiment=fast").model).eval()
    views = orbit_views(n=1, size=16)
    frame = model.render_view(views.K[0], views.c2w[0], 16, 16)
    rays_o, rays_d = image_rays(views.K, views.c2w, 16, 16)
    with torch.no_grad():
        out = model.render(rays_o[0], rays_d[0])
    assert frame["rgb"].shape == (16, 16, 3) and frame["depth"].shape == (16, 16) and frame["accumulation"].shape == (16, 16)
    torch.testing.assert_close(frame["rgb"].reshape(-1, 3), out["rgb"])
    assert model.render_view(views.K[0], views.c2w[0], 16, 16, abort=lambda: True) is None


def test_a_command_asks_the_model_for_what_it_needs_and_refuses_a_model_without_it_in_one_line(make_config, tmp_path):
    """An image field renders no camera and has no density: nerf-eval and nerf-export say so by capability."""
    from nerf_lightning.checkpoints import load_model
    from nerf_lightning.outputs.evaluation import evaluate_checkpoint
    from nerf_lightning.outputs.export import export_model
    from nerf_lightning.training import train

    train(make_config("experiment=image", "data.downscale=8", "data.batch_size=64", "trainer.max_steps=2", "data.val_steps=[]",
                      "trainer.enable_progress_bar=false", run_dir=tmp_path / "image"))
    ckpt = tmp_path / "image" / "checkpoints" / "last.ckpt"
    model, info = load_model(ckpt)
    assert info["global_step"] == 2
    with pytest.raises(ValueError, match="nerf-eval needs a model that renders a camera; this checkpoint's model, ImageFieldModule, has none"):
        evaluate_checkpoint(ckpt, tmp_path / "eval")
    with pytest.raises(ValueError, match="format=obj needs a density to mesh .*ImageFieldModule.*nothing nerf-export writes"):
        export_model(model, "obj", tmp_path / "export", {})


def test_a_model_whose_space_is_a_submodule_renders_a_camera_as_python_3_12_looks_it_up():
    """Python 3.12's isinstance on a runtime-checkable protocol finds members with inspect.getattr_static, which does
    not see an nn.Module's submodules: nerf-eval refused every checkpoint there (seen on a GPU machine's Python 3.12)."""
    import inspect

    from nerf_lightning.models.contract import protocol_members, require

    model = _SpaceHolder()
    with pytest.raises(AttributeError):
        inspect.getattr_static(model, "space")  # where 3.12's isinstance looks, the space is not found
    assert protocol_members(RendersCamera) == {"space", "device", "render_view"}
    assert implements(model, RendersCamera)
    require(model, RendersCamera, "nerf-eval", "a model that renders a camera")  # no error


class _SpaceHolder(nn.Module):
    """A model as the shipped ones hold their space: a submodule set after construction."""

    def __init__(self) -> None:
        super().__init__()
        self.space = SceneSpace(near=2.0, far=6.0)

    @property
    def device(self) -> torch.device:
        return torch.device("cpu")

    def render_view(self, K, c2w, height, width, abort=None):
        return None
