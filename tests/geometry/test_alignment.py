"""The alignment of two camera sets (nerf-process-data's check against published poses): a similarity fitted by
Umeyama's method, then each camera's position and rotation error."""

import math

import pytest
import torch

from nerf_lightning.geometry.alignment import camera_pose_errors, umeyama_similarity


def random_rotation(generator: torch.Generator) -> torch.Tensor:
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=generator, dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r))
    return q if torch.linalg.det(q) > 0 else -q


def test_umeyama_recovers_a_known_similarity():
    generator = torch.Generator().manual_seed(0)
    source = torch.randn(20, 3, generator=generator, dtype=torch.float64)
    rotation, scale, translation = random_rotation(generator), 2.7, torch.tensor([1.0, -4.0, 0.5], dtype=torch.float64)
    target = scale * source @ rotation.T + translation
    transform = umeyama_similarity(source, target)
    assert torch.allclose(transform[:3, :3], scale * rotation, atol=1e-10)
    assert torch.allclose(transform[:3, 3], translation, atol=1e-10)
    # a mirrored target is fitted by a rotation, never a reflection
    mirrored = umeyama_similarity(source, source * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64))
    assert torch.linalg.det(mirrored[:3, :3]) > 0
    with pytest.raises(ValueError, match="at least 3 points"):
        umeyama_similarity(source[:2], target[:2])


def test_camera_errors_after_alignment_are_those_put_in():
    generator = torch.Generator().manual_seed(1)
    count = 12
    reference = torch.eye(4, dtype=torch.float64).repeat(count, 1, 1)
    reference[:, :3, :3] = torch.stack([random_rotation(generator) for _ in range(count)])
    reference[:, :3, 3] = 3.0 * torch.randn(count, 3, generator=generator, dtype=torch.float64)
    # the same cameras in another similarity frame: scale 0.4, a rotation, a shift
    rotation = random_rotation(generator)
    recovered = reference.clone()
    recovered[:, :3, :3] = rotation @ reference[:, :3, :3]
    recovered[:, :3, 3] = 0.4 * reference[:, :3, 3] @ rotation.T + torch.tensor([5.0, 0.0, -2.0], dtype=torch.float64)
    errors = camera_pose_errors(recovered, reference)
    assert errors["position_error"].max() < 1e-9 and errors["rotation_error"].max() < 1e-5
    # one camera turned by 2 degrees about its own axis: only its rotation error moves, by 2 degrees
    angle = math.radians(2.0)
    turn = torch.tensor([[math.cos(angle), -math.sin(angle), 0.0], [math.sin(angle), math.cos(angle), 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    recovered[3, :3, :3] = recovered[3, :3, :3] @ turn
    errors = camera_pose_errors(recovered, reference)
    assert errors["rotation_error"][3] == pytest.approx(2.0, abs=1e-6)
    assert errors["rotation_error"][torch.arange(count) != 3].max() < 1e-5
    spread = (reference[:, :3, 3] - reference[:, :3, 3].mean(0)).norm(dim=-1).pow(2).mean().sqrt()
    assert float(errors["spread"]) == pytest.approx(float(spread))


def test_one_camera_far_off_does_not_pull_the_others():
    generator = torch.Generator().manual_seed(2)
    count = 30
    reference = torch.eye(4, dtype=torch.float64).repeat(count, 1, 1)
    reference[:, :3, :3] = torch.stack([random_rotation(generator) for _ in range(count)])
    reference[:, :3, 3] = torch.randn(count, 3, generator=generator, dtype=torch.float64)
    recovered = reference.clone()
    # every centre off by about 1 % of the spread, as structure from motion leaves them, and one camera 2 spreads away
    recovered[:, :3, 3] += 0.01 * torch.randn(count, 3, generator=generator, dtype=torch.float64)
    recovered[7, :3, 3] += torch.tensor([3.0, -2.0, 1.5], dtype=torch.float64)
    errors = camera_pose_errors(recovered, reference)
    others = torch.arange(count) != 7
    assert errors["aligned_on"][others].all() and not errors["aligned_on"][7]
    assert float(errors["position_error"][others].max()) < 0.05  # the noise, not the far camera's pull
    assert float(errors["position_error"][7]) > 3.0
    assert float(errors["rotation_error"][others].max()) < 0.5  # degrees: the fit to noisy centres, not the pull
    # fitted to all of them, the far camera would have turned and scaled the others off by many times the noise
    from nerf_lightning.geometry.alignment import umeyama_similarity

    plain = umeyama_similarity(recovered[:, :3, 3], reference[:, :3, 3])
    pulled = (recovered[:, :3, 3] @ plain[:3, :3].T + plain[:3, 3] - reference[:, :3, 3]).norm(dim=-1)
    assert float(pulled[others].median()) > 3 * float(errors["position_error"][others].median())
