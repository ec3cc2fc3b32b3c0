"""Camera refinement: zero corrections leave the rays alone; a correction turns a ray about its camera centre and
moves it; the penalties are the corrections' weighted squared sizes; a checkpoint's corrections load at their size;
corrected cameras make the corrected rays."""

import math

import pytest
import torch

from nerf_lightning.geometry.refinement import CameraRefinement


def test_zero_corrections_leave_the_rays_as_they_are():
    refinement = CameraRefinement()
    refinement.resize(4)
    origins, directions = torch.randn(10, 3), torch.nn.functional.normalize(torch.randn(10, 3), dim=-1)
    got_o, got_d = refinement(origins, directions, torch.arange(10) % 4)
    torch.testing.assert_close(got_o, origins)
    torch.testing.assert_close(got_d, directions)
    assert all(float(value.detach()) == 0.0 for value in refinement.penalties().values())


def test_a_correction_turns_the_rays_of_its_view_about_the_camera_and_moves_them():
    refinement = CameraRefinement(rotation_penalty=2.0, translation_penalty=3.0)
    refinement.resize(2)
    with torch.no_grad():
        refinement.rows[1] = torch.tensor([0.0, 0.0, math.pi / 2, 0.1, 0.0, -0.2])  # view 1: 90 degrees about z
    origins = torch.tensor([[1.0, 2.0, 3.0], [1.0, 2.0, 3.0]])
    directions = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    got_o, got_d = refinement(origins, directions, torch.tensor([0, 1]))
    torch.testing.assert_close(got_o, torch.tensor([[1.0, 2.0, 3.0], [1.1, 2.0, 2.8]]))
    torch.testing.assert_close(got_d, torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]), atol=1e-6, rtol=0)
    penalties = {name: value.detach() for name, value in refinement.penalties().items()}  # means over the 2 views
    assert float(penalties["camera_rotation"]) == pytest.approx(2.0 * (math.pi / 2) ** 2 / 2)
    assert float(penalties["camera_translation"]) == pytest.approx(3.0 * 0.05 / 2)
    # the corrections learn: a loss on the moved ray reaches them
    got_o[1].sum().backward()
    assert refinement.rows.grad[1, 3:].abs().sum() > 0 and refinement.rows.grad[0].abs().sum() == 0


def test_corrections_load_at_their_saved_size_and_an_unknown_view_is_refused():
    trained = CameraRefinement()
    trained.resize(5)
    with torch.no_grad():
        trained.rows.normal_()
    fresh = CameraRefinement()
    fresh.load_state_dict(trained.state_dict())
    torch.testing.assert_close(fresh.rows, trained.rows)
    fresh.eval()  # outside a training step (whose indices the datamodule draws; the check would make a GPU wait)
    with pytest.raises(IndexError, match="camera index 5 is beyond the 5 training views of this CameraRefinement"):
        fresh(torch.zeros(1, 3), torch.ones(1, 3), torch.tensor([5]))
    with pytest.raises(ValueError, match="lr > 0"):
        CameraRefinement(lr=0.0)


def test_corrected_cameras_make_the_rays_that_forward_corrects():
    from nerf_lightning.geometry.rays import image_rays

    refinement = CameraRefinement()
    refinement.resize(3)
    with torch.no_grad():
        refinement.rows.copy_(torch.randn(3, 6, generator=torch.Generator().manual_seed(0)) * 0.3)
    rotations = torch.linalg.qr(torch.randn(2, 3, 3, generator=torch.Generator().manual_seed(1)))[0]
    rotations = rotations * torch.linalg.det(rotations)[:, None, None]  # proper rotations
    c2w = torch.eye(4).repeat(2, 1, 1)
    c2w[:, :3, :3], c2w[:, :3, 3] = rotations, torch.tensor([[1.0, -2.0, 3.0], [0.5, 0.0, -1.0]])
    K = torch.tensor([[20.0, 0.0, 8.0], [0.0, 22.0, 6.0], [0.0, 0.0, 1.0]]).expand(2, 3, 3)
    views = torch.tensor([2, 0])
    corrected = refinement.corrected_c2w(c2w, views)
    assert corrected.shape == (2, 4, 4) and torch.equal(corrected[:, 3], c2w[:, 3])
    torch.testing.assert_close(corrected[:, :3, :3] @ corrected[:, :3, :3].transpose(1, 2), torch.eye(3).expand(2, 3, 3))
    rays_o, rays_d = image_rays(K, c2w, 12, 16)  # (2, 192, 3)
    want_o, want_d = refinement(rays_o.reshape(-1, 3), rays_d.reshape(-1, 3), views.repeat_interleave(192))
    got_o, got_d = image_rays(K, corrected, 12, 16)
    torch.testing.assert_close(got_o.reshape(-1, 3), want_o)
    torch.testing.assert_close(got_d.reshape(-1, 3), want_d)
    # nerfstudio's form: the same correction written in the camera's frame and multiplied on the right
    from kornia.geometry.conversions import axis_angle_to_rotation_matrix

    w, t = refinement.rows[views, :3].detach(), refinement.rows[views, 3:].detach()
    R = c2w[:, :3, :3]
    right = torch.eye(4).repeat(2, 1, 1)
    right[:, :3, :3] = axis_angle_to_rotation_matrix((R.transpose(1, 2) @ w[..., None])[..., 0])
    right[:, :3, 3] = (R.transpose(1, 2) @ t[..., None])[..., 0]
    torch.testing.assert_close(corrected.detach(), c2w @ right)
    corrected[0, 0, 3].backward()  # the corrections learn through the cameras too
    assert refinement.rows.grad[2, 3] == 1.0 and refinement.rows.grad[1].abs().sum() == 0
    with pytest.raises(ValueError, match=r"c2w \(V, 4, 4\) and camera_indices \(V,\)"):
        refinement.corrected_c2w(c2w[0], views)
