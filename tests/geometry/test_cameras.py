"""Cameras and rays: identities that hold only if the conventions are right."""

import json
import math

import pytest
import torch

from nerf_lightning.geometry import (
    camera_to_world,
    image_rays,
    look_at,
    opengl_to_opencv,
    pinhole_camera,
    pixel_to_camera,
    pixel_to_ray,
    sample_along_rays,
    validate_c2w,
)
from tests.conftest import SHARED_DATA

LEGO = SHARED_DATA / "nerf_synthetic" / "lego"


def random_cameras(count: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    eye = torch.nn.functional.normalize(torch.randn(count, 3, generator=generator), dim=-1) * 4.0
    c2w = look_at(eye, target=torch.randn(3, generator=generator) * 0.3)
    K = torch.tensor([[120.0, 0.0, 50.0], [0.0, 110.0, 40.0], [0.0, 0.0, 1.0]]).expand(count, 3, 3)
    return K, c2w


def test_project_of_unproject_is_identity():
    K, c2w = random_cameras(5)
    generator = torch.Generator().manual_seed(1)
    uv = torch.rand(5, 200, 2, generator=generator) * torch.tensor([100.0, 80.0])
    depth = 2.0 + 4.0 * torch.rand(5, 200, 1, generator=generator)
    world = camera_to_world(c2w, pixel_to_camera(K, uv, depth))
    camera = pinhole_camera(K, c2w, 80, 100)
    torch.testing.assert_close(camera.project(world), uv, atol=1e-3, rtol=0)
    # and the points are at that depth in front of the camera
    in_camera = camera_to_world(torch.linalg.inv(c2w), world)
    torch.testing.assert_close(in_camera[..., 2:], depth, atol=1e-4, rtol=0)


def test_pixel_to_ray_unit_directions_through_the_pixel():
    K, c2w = random_cameras(3)
    uv = torch.tensor([[[50.0, 40.0], [0.5, 0.5], [99.5, 79.5]]]).expand(3, 3, 2)
    rays_o, rays_d = pixel_to_ray(K, c2w, uv)
    torch.testing.assert_close(rays_d.norm(dim=-1), torch.ones(3, 3))
    torch.testing.assert_close(rays_o, c2w[:, None, :3, 3].expand(3, 3, 3))
    # a point along the ray projects back onto its pixel
    camera = pinhole_camera(K, c2w, 80, 100)
    torch.testing.assert_close(camera.project(rays_o + 3.0 * rays_d), uv, atol=1e-3, rtol=0)
    # the principal point's ray is the optical axis, +z of the OpenCV camera
    torch.testing.assert_close(rays_d[:, 0], c2w[:, :3, 2])


def test_the_courses_unbatched_shapes_give_the_batched_results():
    K, c2w = random_cameras(4)
    generator = torch.Generator().manual_seed(2)
    uv = torch.rand(4, 30, 2, generator=generator) * torch.tensor([100.0, 80.0])
    depth = 1.0 + torch.rand(4, 30, 1, generator=generator)
    batched_points = camera_to_world(c2w, pixel_to_camera(K, uv, depth))
    batched_o, batched_d = pixel_to_ray(K, c2w, uv)
    # one camera: K (3, 3), c2w (4, 4), uv (N, 2), s (N,) or (N, 1)
    x_c = pixel_to_camera(K[0], uv[0], depth[0, :, 0])
    assert x_c.shape == (30, 3)
    torch.testing.assert_close(x_c, pixel_to_camera(K[0], uv[0], depth[0]))
    torch.testing.assert_close(camera_to_world(c2w[0], x_c), batched_points[0])
    rays_o, rays_d = pixel_to_ray(K[0], c2w[0], uv[0])
    torch.testing.assert_close(rays_o, batched_o[0]) and torch.testing.assert_close(rays_d, batched_d[0])
    # a camera per pixel (random rays across images): c2w (N, 4, 4), uv (N, 2)
    camera_of = torch.tensor([0, 3, 1, 1, 2, 0])
    pixel_of = torch.tensor([5, 7, 0, 29, 13, 2])
    rays_o, rays_d = pixel_to_ray(K[0], c2w[camera_of], uv[camera_of, pixel_of])
    torch.testing.assert_close(rays_o, batched_o[camera_of, pixel_of])
    torch.testing.assert_close(rays_d, batched_d[camera_of, pixel_of])
    x_c = pixel_to_camera(K[0], uv[camera_of, pixel_of], depth[camera_of, pixel_of])
    torch.testing.assert_close(camera_to_world(c2w[camera_of], x_c), batched_points[camera_of, pixel_of])
    with pytest.raises(ValueError, match=r"c2w of shape \(4, 4, 4\) with 6 points"):
        camera_to_world(c2w, x_c)


def test_image_rays_are_row_major_pixel_centres():
    K, c2w = random_cameras(1)
    rays_o, rays_d = image_rays(K, c2w, 80, 100)
    assert rays_o.shape == rays_d.shape == (1, 8000, 3)
    _, expected = pixel_to_ray(K, c2w, torch.tensor([[[3.5, 2.5]]]))  # row 2, column 3
    torch.testing.assert_close(rays_d[0, 2 * 100 + 3], expected[0, 0])


def test_opengl_to_opencv_flips_y_and_z_and_is_its_own_inverse():
    _, c2w = random_cameras(4)
    flipped = opengl_to_opencv(c2w)
    torch.testing.assert_close(flipped[:, :, 0], c2w[:, :, 0])
    torch.testing.assert_close(flipped[:, :, 1:3], -c2w[:, :, 1:3])
    torch.testing.assert_close(opengl_to_opencv(flipped), c2w)


def test_bad_camera_matrices_are_named():
    _, c2w = random_cameras(3)
    bad = c2w.clone()
    bad[1, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="cams.json 'transform_matrix': camera 1 has non-finite"):
        validate_c2w(bad, "cams.json 'transform_matrix'")
    scaled = c2w.clone()
    scaled[2, :3, :3] *= 2.0
    with pytest.raises(ValueError, match="camera 2 is not rigid"):
        validate_c2w(scaled, "x")
    with pytest.raises(ValueError, match=r"expected camera-to-world matrices of shape \(N, 4, 4\)"):
        validate_c2w(c2w[:, :3], "x")


def test_stratified_samples():
    rays_o, rays_d = torch.zeros(1000, 3), torch.nn.functional.normalize(torch.randn(1000, 3), dim=-1)
    points, t = sample_along_rays(rays_o, rays_d, 2.0, 6.0, 64, perturb=False)
    assert points.shape == (1000, 64, 3) and t.shape == (1000, 64)
    torch.testing.assert_close(t[0], torch.linspace(2.0, 6.0, 64))
    torch.testing.assert_close(points, rays_o[:, None] + t[..., None] * rays_d[:, None])

    generator = torch.Generator().manual_seed(0)
    jittered_points, jittered = sample_along_rays(rays_o, rays_d, 2.0, 6.0, 64, perturb=True, generator=generator)
    assert (jittered >= 2.0).all() and (jittered <= 6.0).all()
    assert (jittered[:, 1:] >= jittered[:, :-1]).all()  # sorted along each ray
    mids = torch.cat([torch.tensor([2.0]), (t[0, 1:] + t[0, :-1]) / 2, torch.tensor([6.0])])
    assert ((jittered >= mids[:-1]) & (jittered <= mids[1:])).all()  # each in its own stratum
    assert not torch.allclose(jittered, t)
    # the jitter covers each stratum: the samples of the second stratum spread over most of it
    spread = (jittered[:, 1].max() - jittered[:, 1].min()) / (mids[2] - mids[1])
    assert spread > 0.9
    torch.testing.assert_close(jittered_points, rays_o[:, None] + jittered[..., None] * rays_d[:, None])


@pytest.mark.skipif(not LEGO.is_dir(), reason="lego is not in ../shared/data")
def test_every_lego_camera_looks_at_the_origin():
    for split in ("train", "val"):
        meta = json.loads((LEGO / f"transforms_{split}.json").read_text())
        c2w = opengl_to_opencv(torch.tensor([frame["transform_matrix"] for frame in meta["frames"]], dtype=torch.float64))
        focal = 0.5 * 800 / math.tan(0.5 * meta["camera_angle_x"])
        K = torch.tensor([[focal, 0.0, 400.0], [0.0, focal, 400.0], [0.0, 0.0, 1.0]], dtype=torch.float64).expand(len(c2w), 3, 3)
        centre = torch.tensor([400.0, 400.0], dtype=torch.float64).expand(len(c2w), 1, 2)
        rays_o, rays_d = pixel_to_ray(K, c2w, centre)
        # distance from the origin to each centre ray, and the origin in front of the camera
        distance = torch.linalg.cross(-rays_o[:, 0], rays_d[:, 0]).norm(dim=-1)
        assert distance.max() < 0.01, f"{split}: a centre ray misses the origin by {float(distance.max()):.4f}"
        assert ((-rays_o[:, 0] * rays_d[:, 0]).sum(-1) > 3.5).all()
