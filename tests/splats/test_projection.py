"""The projection (:func:`~nerf_lightning.splats.projection.project`) checked on its own, against computations that
share none of its code: the footprints' covariances against the empirical 2D covariance of many 3D samples of each
Gaussian projected by kornia's camera, and against J W Sigma W^T J^T built here from axis-angle rotations (not the
module's :func:`~nerf_lightning.splats.projection.covariances` nor kornia's quaternion conversion); the conics, the
boxes (nothing drawable lies outside them, and they are no larger than that), Mip-Splatting's opacity compensation and
the culling. Then two things the splat model builds on it: the patch-gradient share (a patch's screen-space gradient,
scaled by patch pixels / view pixels, is the whole view's, so the strategy grows a patch-trained scene as a whole-view
one) and the depth's scaling (camera z times the pixel's ray length is the distance along the unit ray).

Pixels: the project names pixel (i, j)'s centre (j + 0.5, i + 0.5) and kornia (j, i), but both map a camera point
to the continuous coordinate K p / z, which is all that is compared here (the same K goes to both).
"""

from __future__ import annotations

import functools
import math
import warnings

import pytest
import torch
from kornia.geometry.camera import PinholeCamera
from kornia.geometry.camera.perspective import unproject_points
from torch import nn

from nerf_lightning.data.views import patch_camera
from nerf_lightning.geometry.cameras import pixel_ray_lengths, pixel_to_ray
from nerf_lightning.geometry.space import SceneSpace
from nerf_lightning.models.splat import SplatModule
from nerf_lightning.splats.gaussians import PARAMETERS, Gaussians
from nerf_lightning.splats.loss import SplatLoss
from nerf_lightning.splats.projection import LOW_PASS, MAX_SIGMAS, MIN_ALPHA, NEAR_PLANE, project
from nerf_lightning.splats.draw import RASTERIZERS
from nerf_lightning.splats.sh import rgb_to_sh
from nerf_lightning.splats.strategy import DefaultStrategy

F64 = torch.float64

# -- independent maths: rotations from axis-angle, the camera, and EWA's footprint written out -------------------


def rotation(axis: list[float], angle: float) -> torch.Tensor:
    """(3, 3) the rotation by ``angle`` about ``axis``: the matrix exponential of its skew matrix."""
    a = torch.nn.functional.normalize(torch.tensor(axis, dtype=F64), dim=0) * angle
    skew = torch.tensor([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]], dtype=F64)
    return torch.linalg.matrix_exp(skew)


def quaternion(axis: list[float], angle: float) -> torch.Tensor:
    """(4,) the same rotation as a unit quaternion (w, x, y, z), from its half angle."""
    a = torch.nn.functional.normalize(torch.tensor(axis, dtype=F64), dim=0)
    return torch.cat([torch.tensor([math.cos(angle / 2)], dtype=F64), math.sin(angle / 2) * a])


WIDTH, HEIGHT = 400, 300
# fx != fy, the principal point off the image's centre
K = torch.tensor([[1000.0, 0.0, WIDTH / 2 + 17.3], [0.0, 900.0, HEIGHT / 2 - 11.6], [0.0, 0.0, 1.0]], dtype=F64)
CAMERA_ROTATION = rotation([0.3, -1.0, 0.4], 0.7)  # camera axes in the world (c2w's rotation)
CAMERA_CENTRE = torch.tensor([0.4, -1.2, 2.5], dtype=F64)


def c2w_of(rotation_: torch.Tensor, centre: torch.Tensor) -> torch.Tensor:
    c2w = torch.eye(4, dtype=rotation_.dtype)
    c2w[:3, :3], c2w[:3, 3] = rotation_, centre
    return c2w


def w2c_of(rotation_: torch.Tensor, centre: torch.Tensor) -> torch.Tensor:
    """The inverse of :func:`c2w_of`, written out (R^T, -R^T C), not by a matrix inverse."""
    w2c = torch.eye(4, dtype=rotation_.dtype)
    w2c[:3, :3], w2c[:3, 3] = rotation_.T, -rotation_.T @ centre
    return w2c


C2W = c2w_of(CAMERA_ROTATION, CAMERA_CENTRE)


def world_from_camera(points: torch.Tensor) -> torch.Tensor:
    return points @ CAMERA_ROTATION.T + CAMERA_CENTRE


def footprint(mean: torch.Tensor, axes: torch.Tensor, scales: torch.Tensor, K_: torch.Tensor = K,
              rotation_: torch.Tensor = CAMERA_ROTATION, centre: torch.Tensor = CAMERA_CENTRE) -> torch.Tensor:
    """(2, 2) J W Sigma W^T J^T, Sigma = A diag(s^2) A^T with the Gaussian's axes A (3, 3) (a rotation's columns),
    W the world-to-camera rotation, J the projection's Jacobian at the camera point (no clamp: the Gaussians here
    lie well inside the view or a little beyond its edges, inside the module's 30 % margin)."""
    W = rotation_.T
    x, y, z = (W @ (mean - centre)).tolist()
    fx, fy = float(K_[0, 0]), float(K_[1, 1])
    J = torch.tensor([[fx / z, 0.0, -fx * x / z**2], [0.0, fy / z, -fy * y / z**2]], dtype=F64)
    sigma = axes @ torch.diag(scales**2) @ axes.T
    return J @ W @ sigma @ W.T @ J.T


# Six Gaussians 5 to 8 units in front of the camera, four of them off-axis (x / z up to 0.15), rotated, with
# anisotropic scales whose footprints have variances of about 2 to 10 px^2 (checked below), so that the 0.3 px^2
# low-pass is 3 % or more of every footprint variance; their sizes are 0.2 to 0.8 % of their distance, so the
# projection's linearisation errs by about (s / z)^2 < 1e-4 relative (and its mean by about 0.005 sd).
CAMERA_POINTS = torch.tensor([[0.0, 0.0, 6.0], [0.9, 0.1, 6.5], [-0.8, 0.6, 5.5], [0.5, -0.7, 7.0], [-1.0, -0.8, 8.0],
                              [0.2, 0.5, 5.0]], dtype=F64)
AXES = [([1.0, 0.0, 0.0], 0.0), ([0.2, 0.9, -0.3], 0.8), ([1.0, 1.0, 1.0], 2.1), ([-0.5, 0.2, 1.0], -1.2),
        ([0.0, 0.3, 1.0], 0.5), ([0.7, -0.7, 0.1], 2.9)]
SCALES = torch.tensor([[0.012, 0.012, 0.012], [0.01, 0.007, 0.022], [0.01, 0.018, 0.01], [0.022, 0.012, 0.035],
                       [0.016, 0.026, 0.012], [0.01, 0.005, 0.015]], dtype=F64)
OPACITIES = torch.tensor([0.9, 0.3, 0.05, 0.01, 0.6, 0.2], dtype=F64)


def scene(dtype: torch.dtype = F64) -> dict[str, torch.Tensor]:
    means = world_from_camera(CAMERA_POINTS)
    quats = torch.stack([quaternion(axis, angle) for axis, angle in AXES])
    return {"means": means.to(dtype), "quats": quats.to(dtype), "log_scales": torch.log(SCALES).to(dtype),
            "opacities": OPACITIES.to(dtype)}


def expected_footprints() -> torch.Tensor:
    """(N, 2, 2) J W Sigma W^T J^T of :func:`scene`'s Gaussians, without the low-pass."""
    means = world_from_camera(CAMERA_POINTS)
    return torch.stack([footprint(mean, rotation(*axis), scales) for mean, axis, scales in zip(means, AXES, SCALES)])


def projected(antialiased: bool = False, dtype: torch.dtype = F64):
    g = scene(dtype)
    return project(g["means"], g["quats"], g["log_scales"], g["opacities"], K.to(dtype), C2W.to(dtype), HEIGHT, WIDTH, antialiased)


def conic_matrix(conics: torch.Tensor) -> torch.Tensor:
    a, b, c = conics.unbind(-1)
    return torch.stack([a, b, b, c], dim=-1).reshape(-1, 2, 2)


@functools.lru_cache(maxsize=1)
def empirical() -> tuple[torch.Tensor, torch.Tensor]:
    """(N, 2) means and (N, 2, 2) covariances of 200k samples of each 3D Gaussian, x = mu + A diag(s) e with e
    standard normal (fixed seed, float64), projected into the camera by kornia's PinholeCamera."""
    generator = torch.Generator().manual_seed(0)
    intrinsics = torch.eye(4, dtype=F64)
    intrinsics[:3, :3] = K
    camera = PinholeCamera(intrinsics[None], w2c_of(CAMERA_ROTATION, CAMERA_CENTRE)[None], torch.tensor([HEIGHT], dtype=F64),
                           torch.tensor([WIDTH], dtype=F64))
    means, covariances = [], []
    for mean, axis, scales in zip(world_from_camera(CAMERA_POINTS), AXES, SCALES):
        samples = mean + (torch.randn(200_000, 3, generator=generator, dtype=F64) * scales) @ rotation(*axis).T
        pixels = camera.project(samples[None])[0]  # (S, 2)
        means.append(pixels.mean(dim=0))
        covariances.append(torch.cov(pixels.T))
    return torch.stack(means), torch.stack(covariances)


# -- 1. the footprint's mean and covariance against samples projected by kornia ----------------------------------


def test_the_footprints_are_the_empirical_mean_and_covariance_of_samples_projected_by_kornia_plus_the_low_pass():
    """Sampling noise: the standard error of an empirical covariance entry C_ij of N samples is
    sqrt((C_ii C_jj + C_ij^2) / N) <= sqrt(2 / N) sqrt(C_ii C_jj) = 0.32 % of sqrt(C_ii C_jj) at N = 200k, and the
    linearisation's bias is about (s / z)^2 < 1e-4 relative: 1.5 % of sqrt(C_ii C_jj) is 4.7 standard errors.
    Leaving the low-pass out would err by 0.3 / C_ii >= 3 % (the variances are at most 10 px^2, checked).
    The mean's standard error is sqrt(C_ii / N) = 0.0022 sd, its linearisation bias about 0.005 sd: 0.02 sd allowed
    (a half-pixel slip would be 0.15 sd or more)."""
    sample_means, sample_covariances = empirical()
    projection = projected()
    assert projection.ids.tolist() == list(range(len(CAMERA_POINTS)))
    variances = torch.diagonal(sample_covariances, dim1=1, dim2=2)
    assert variances.min() > 1.5 and variances.max() < 10.0, f"footprint variances {variances} out of the range the test is sized for"
    filtered = sample_covariances + LOW_PASS * torch.eye(2, dtype=F64)
    from_conics = torch.linalg.inv(conic_matrix(projection.conics))
    scale = torch.sqrt(torch.diagonal(filtered, dim1=1, dim2=2))
    relative = (from_conics - filtered) / (scale[:, :, None] * scale[:, None, :])
    assert relative.abs().max() < 0.015, f"the conics' covariances against the samples' (+ low-pass), relative: {relative}"
    # the off-diagonal terms and anisotropy are there to be checked: not a scene of round footprints
    correlation = filtered[:, 0, 1] / (scale[:, 0] * scale[:, 1])
    assert correlation.abs().max() > 0.3 and (scale[:, 0] / scale[:, 1]).max() > 1.3
    error = (projection.means2d - sample_means) / torch.sqrt(variances)
    assert error.abs().max() < 0.02, f"means2d against the samples' mean, in standard deviations: {error}"


# -- 2. the conic, analytically --------------------------------------------------------------------------------


def test_the_conic_is_the_inverse_of_the_analytic_footprint_plus_the_low_pass():
    projection = projected()
    expected = torch.linalg.inv(expected_footprints() + LOW_PASS * torch.eye(2, dtype=F64))
    torch.testing.assert_close(conic_matrix(projection.conics), expected, rtol=1e-10, atol=1e-12)
    # in float32, as the model runs it
    projection32 = projected(dtype=torch.float32)
    torch.testing.assert_close(conic_matrix(projection32.conics).double(), expected, rtol=2e-4, atol=1e-6)
    torch.testing.assert_close(projection.depths, CAMERA_POINTS[:, 2], rtol=1e-12, atol=1e-12)


# -- 3. the boxes ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("antialiased", [False, True])
def test_the_boxes_are_k_sigma_with_k_where_the_opacity_fades_to_1_over_255_and_nothing_drawable_lies_outside(antialiased):
    """A box's half-size along u is k sqrt(C_uu), C the filtered footprint and k = min(3, sqrt(2 ln(255 o))).
    What that guarantees: at d outside the box, |d_u| > k sqrt(C_uu) (or the same along v), and the Mahalanobis
    distance d^T C^-1 d is at least the marginal d_u^2 / C_uu > k^2, so alpha = o exp(-d^T C^-1 d / 2) <
    o exp(-k^2 / 2), which is 1/255 where k < 3: nothing drawable lies outside. Where k = 3 (an opacity above
    255^-1 e^4.5 = 0.35) the box cuts at three standard deviations along each axis instead, through pixels that
    could still be drawn. And the box is no larger than that: on each edge, at d = (e_u, C_uv / C_uu e_u), the
    Mahalanobis distance is exactly k^2 (alpha exactly 1/255 where k < 3)."""
    projection = projected(antialiased)
    filtered = expected_footprints() + LOW_PASS * torch.eye(2, dtype=F64)
    opacity = projection.opacities
    if antialiased:  # the box is where the compensated opacity fades
        assert (opacity < OPACITIES).all()
    else:
        torch.testing.assert_close(opacity, OPACITIES, rtol=0, atol=0)
    k = torch.sqrt(2.0 * torch.log(255.0 * opacity)).clamp(max=MAX_SIGMAS)
    assert (k == MAX_SIGMAS).any() and (k < MAX_SIGMAS - 0.5).any(), "both kinds of box are checked"
    deviations = torch.sqrt(torch.diagonal(filtered, dim1=1, dim2=2))
    torch.testing.assert_close(projection.extents, k[:, None] * deviations, rtol=1e-10, atol=0)

    inverse = torch.linalg.inv(filtered)
    generator = torch.Generator().manual_seed(1)
    for index in range(len(k)):
        e = projection.extents[index]
        # pixel centres over a window twice the box, and continuous points, all relative to the mean
        columns = torch.arange(math.floor(projection.means2d[index, 0] - 2 * e[0]) - 1, math.ceil(projection.means2d[index, 0] + 2 * e[0]) + 1)
        rows = torch.arange(math.floor(projection.means2d[index, 1] - 2 * e[1]) - 1, math.ceil(projection.means2d[index, 1] + 2 * e[1]) + 1)
        v, u = torch.meshgrid(rows.to(F64) + 0.5, columns.to(F64) + 0.5, indexing="ij")
        pixels = torch.stack([u.reshape(-1), v.reshape(-1)], dim=-1) - projection.means2d[index]
        points = (torch.rand(100_000, 2, generator=generator, dtype=F64) * 4.0 - 2.0) * e
        # and points just outside each edge, along the whole edge and beyond
        along = torch.linspace(-2.0, 2.0, 2001, dtype=F64)
        edges = torch.cat([torch.stack([sign * e[0] * (1 + 1e-9) + 0 * along, along * e[1]], -1) for sign in (-1, 1)]
                          + [torch.stack([along * e[0], sign * e[1] * (1 + 1e-9) + 0 * along], -1) for sign in (-1, 1)])
        d = torch.cat([pixels, points, edges])
        outside = (d.abs() > e).any(dim=-1)
        assert outside.sum() > 1000 and (~outside[: len(pixels)]).sum() > 4
        mahalanobis = torch.einsum("pi,ij,pj->p", d[outside], inverse[index], d[outside])
        assert mahalanobis.min() >= k[index] ** 2 * (1 - 1e-9), f"footprint {index}: a point outside its box within k sigma"
        alpha = opacity[index] * torch.exp(-0.5 * mahalanobis)
        if k[index] < MAX_SIGMAS:
            assert alpha.max() <= MIN_ALPHA * (1 + 1e-9), f"footprint {index}: a drawable point outside its box"
        else:
            assert mahalanobis.min() >= MAX_SIGMAS**2 * (1 - 1e-9)
        # tight: the edge's nearest point (in Mahalanobis distance) lies at exactly k
        for axis in (0, 1):
            other = 1 - axis
            touch = torch.zeros(2, dtype=F64)
            touch[axis] = e[axis]
            touch[other] = filtered[index, axis, other] / filtered[index, axis, axis] * e[axis]
            distance = touch @ inverse[index] @ touch
            assert float(distance) == pytest.approx(float(k[index] ** 2), rel=1e-9)
            if k[index] < MAX_SIGMAS:
                assert float(opacity[index] * torch.exp(-0.5 * distance)) == pytest.approx(MIN_ALPHA, rel=1e-9)


# -- 4. Mip-Splatting's compensation -----------------------------------------------------------------------------


def test_the_antialiased_opacity_is_compensated_by_the_low_pass_determinant_ratio():
    """opacity * sqrt(det C / det(C + 0.3 I)). From the samples: the standard error of ln det of an empirical 2x2
    covariance is about 2 / sqrt(N) = 0.45 %, so the ratio's (half a difference of two such) is at most 0.45 %:
    1.5 % allowed; ignoring the compensation would err by 3 % or more here (variances <= 10 px^2, ratio <= 0.97)."""
    plain, compensated = projected(False), projected(True)
    torch.testing.assert_close(compensated.conics, plain.conics, rtol=0, atol=0)  # only the opacity changes
    ratio = compensated.opacities / plain.opacities
    _, sample_covariances = empirical()
    from_samples = torch.sqrt(torch.linalg.det(sample_covariances)
                              / torch.linalg.det(sample_covariances + LOW_PASS * torch.eye(2, dtype=F64)))
    assert from_samples.max() < 0.97
    assert ((ratio - from_samples) / from_samples).abs().max() < 0.015, f"{ratio} against {from_samples}"
    cov = expected_footprints()
    analytic = torch.sqrt(torch.linalg.det(cov) / torch.linalg.det(cov + LOW_PASS * torch.eye(2, dtype=F64)))
    torch.testing.assert_close(ratio, analytic, rtol=1e-10, atol=0)


# -- 5. culling ----------------------------------------------------------------------------------------------------


def placed_at_edge(edge: str, gap: float, z: float = 6.0, s: float = 0.02) -> torch.Tensor:
    """A camera point of a round Gaussian (scale s, opacity 0.9: k = 3) whose box's edge nearest the image lies
    ``gap`` px outside the first (or last) pixel centre of ``edge`` (negative: inside); its mean off the image."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    axis = 0 if edge in ("left", "right") else 1
    centre = 0.5 if edge in ("left", "top") else (WIDTH if axis == 0 else HEIGHT) - 0.5
    outward = -1.0 if edge in ("left", "top") else 1.0
    uv = torch.tensor([WIDTH / 2, HEIGHT / 2], dtype=F64)
    for _ in range(20):  # the half-size depends (a little) on where the mean is: a fixed point
        point = torch.tensor([(uv[0] - cx) / fx * z, (uv[1] - cy) / fy * z, z], dtype=F64)
        cov = footprint(world_from_camera(point), torch.eye(3, dtype=F64), torch.full((3,), s, dtype=F64))
        half = MAX_SIGMAS * torch.sqrt(cov[axis, axis] + LOW_PASS)
        uv[axis] = centre + outward * (gap + half)
    return point


def test_culling_leaves_out_what_is_behind_the_near_plane_or_whose_box_misses_the_image():
    cases = {  # name: (camera point, scale, opacity, kept)
        "behind": ([0.0, 0.0, -2.0], 0.02, 0.9, False),
        "before the near plane": ([0.0, 0.0, 0.5 * NEAR_PLANE], 0.001, 0.9, False),
        "just past the near plane": ([0.0, 0.0, 2.0 * NEAR_PLANE], 0.001, 0.9, True),
        "centred": ([0.0, 0.0, 6.0], 0.02, 0.9, True),
        "far outside the view": ([6.0, 0.0, 6.0], 0.02, 0.9, False),
        "too faint to draw anywhere": ([0.0, 0.0, 6.0], 0.02, 0.9 * MIN_ALPHA, False),
    }
    for edge in ("left", "right", "top", "bottom"):
        cases[f"{edge}: its box stops 0.1 px short of the first pixel centre"] = (placed_at_edge(edge, 0.1).tolist(), 0.02, 0.9, False)
        cases[f"{edge}: its box reaches 0.1 px past the first pixel centre"] = (placed_at_edge(edge, -0.1).tolist(), 0.02, 0.9, True)
    names = list(cases)
    points = torch.tensor([cases[name][0] for name in names], dtype=F64)
    n = len(names)
    projection = project(world_from_camera(points), torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=F64).repeat(n, 1),
                         torch.log(torch.tensor([cases[name][1] for name in names], dtype=F64))[:, None].repeat(1, 3),
                         torch.tensor([cases[name][2] for name in names], dtype=F64), K, C2W, HEIGHT, WIDTH)
    kept = {names[i] for i in projection.ids.tolist()}
    assert kept == {name for name in names if cases[name][3]}
    # the kept edge cases are what they say: their means off the image, their boxes over its edge
    for row, i in enumerate(projection.ids.tolist()):
        if "reaches" in names[i]:
            u, v = projection.means2d[row].tolist()
            assert not (0 <= u <= WIDTH and 0 <= v <= HEIGHT), names[i]


# -- 6. the patch-gradient share ---------------------------------------------------------------------------------

VIEW_H, VIEW_W = 48, 64
PATCH, X0, Y0 = 24, 30, 14
VIEW_K = torch.tensor([[70.0, 0.0, VIEW_W / 2 + 1.3], [0.0, 60.0, VIEW_H / 2 - 0.7], [0.0, 0.0, 1.0]])
VIEW_AXIS_ANGLE = ([0.2, 1.0, -0.1], 0.4)
VIEW_ROTATION = rotation(*VIEW_AXIS_ANGLE)
VIEW_CENTRE = torch.tensor([0.3, -0.2, -3.0], dtype=F64)
VIEW_C2W = c2w_of(VIEW_ROTATION, VIEW_CENTRE).float()


def splat_model(means: torch.Tensor, quats: torch.Tensor, log_scales: torch.Tensor, opacities: torch.Tensor,
                colours: torch.Tensor, rasterizer: str, absgrad: bool = False) -> SplatModule:
    """A SplatModule (L1 loss alone, DefaultStrategy growing by the plain or the absolute screen gradient, the given
    rasteriser) holding these Gaussians, not attached to a Trainer: ``training_step`` and ``on_after_backward`` are
    called as Lightning calls them."""
    gaussians = Gaussians(sh_degree=0)
    values = {"means": means, "quats": quats, "log_scales": log_scales,
              "opacity_logits": torch.log(opacities / (1 - opacities)), "sh0": rgb_to_sh(colours)[:, None],
              "shN": torch.zeros(len(means), 0, 3)}
    for name in PARAMETERS:
        setattr(gaussians, name, nn.Parameter(values[name].float().clone()))
    model = SplatModule(gaussians, optimizer=functools.partial(torch.optim.Adam), learning_rates=dict.fromkeys(PARAMETERS, 1e-3),
                        strategy=DefaultStrategy(absgrad=absgrad), loss=SplatLoss(ssim_weight=0.0), rasterizer=RASTERIZERS[rasterizer]())
    assert model.drawer().name == rasterizer, f"the {rasterizer} rasteriser is not what draws here"
    model.use_space(SceneSpace(background=(0.05, 0.1, 0.15)))
    model.view_size = (VIEW_H, VIEW_W)
    return model


def patch_scene() -> dict[str, torch.Tensor]:
    """Five overlapping Gaussians whose boxes lie wholly inside the patch (checked)."""
    pixels = torch.tensor([[X0 + 9.0, Y0 + 10.0], [X0 + 14.2, Y0 + 12.5], [X0 + 11.3, Y0 + 15.1], [X0 + 10.0, Y0 + 8.7],
                           [X0 + 13.0, Y0 + 9.0]], dtype=F64)
    depths = torch.tensor([[3.0], [3.4], [2.8], [3.9], [3.2]], dtype=F64)
    in_camera = unproject_points(pixels, depths, VIEW_K.double())
    axes = [([1.0, 0.2, 0.0], 0.3), ([0.0, 1.0, 1.0], 1.1), ([1.0, -1.0, 0.5], 2.0), ([0.3, 0.3, 1.0], -0.7), ([1.0, 0.0, 0.0], 0.0)]
    return {"means": in_camera @ VIEW_ROTATION.T + VIEW_CENTRE, "quats": torch.stack([quaternion(*a) for a in axes]),
            "log_scales": torch.log(torch.tensor([[0.05, 0.03, 0.04], [0.03, 0.06, 0.02], [0.04, 0.04, 0.04], [0.07, 0.03, 0.05],
                                                  [0.02, 0.03, 0.03]], dtype=F64)),
            "opacities": torch.tensor([0.8, 0.6, 0.9, 0.7, 0.5], dtype=F64),
            "colours": torch.tensor([[0.9, 0.2, 0.1], [0.1, 0.8, 0.3], [0.2, 0.3, 0.9], [0.7, 0.7, 0.2], [0.5, 0.1, 0.6]], dtype=F64)}


def step(model: SplatModule, image: torch.Tensor, K_: torch.Tensor) -> None:
    """What Lightning does with a training batch, up to the optimiser: the step, its loss's backward pass, and
    ``on_after_backward`` (where the share scales the screen-space gradient and the strategy reads it)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*self.log.*")  # no Trainer to log to
        loss = model.training_step({"image": image, "K": K_, "c2w": VIEW_C2W}, 0)
    loss.backward()
    model.on_after_backward()


@pytest.mark.parametrize("absgrad", [False, True], ids=["plain", "absgrad"])
@pytest.mark.parametrize("rasterizer", ["pairs", "tiles"])
def test_a_patch_gives_the_strategy_the_screen_gradient_the_whole_view_would(rasterizer, absgrad):
    """A whole view, and a patch of it (its camera from ``patch_camera``), with a target equal to the render outside
    the patch and off it by +-0.1 inside: the whole view's L1 (a mean over its pixels) then has the patch's per-pixel
    loss terms and no others, so its gradient is the patch's L1 gradient times patch pixels / view pixels, exactly
    (bar float rounding). (An L1 alone: SSIM's windows reach across the patch's border.) ``on_after_backward``
    applies that share to the patch's means2d gradient, so the strategy accumulates the same norms, in units of half
    the whole view, from either. With ``absgrad`` (AbsGS) the same holds of the absolute screen gradient the strategy
    then reads: the pixels off the patch pull on nothing (an L1 at zero error has a zero gradient)."""
    s = patch_scene()
    whole, patch = (splat_model(*(s[key] for key in ("means", "quats", "log_scales", "opacities", "colours")), rasterizer,
                                absgrad) for _ in range(2))
    with torch.no_grad():
        rendered, projection = whole.draw(VIEW_K, VIEW_C2W, VIEW_H, VIEW_W)
    assert len(projection.ids) == 5
    low, high = projection.means2d - projection.extents, projection.means2d + projection.extents
    assert (low[:, 0] > X0).all() and (high[:, 0] < X0 + PATCH).all() and (low[:, 1] > Y0).all() and (high[:, 1] < Y0 + PATCH).all()
    target = rendered["rgb"].clone()
    signs = torch.randint(0, 2, (PATCH, PATCH, 3), generator=torch.Generator().manual_seed(2)).float() * 2 - 1
    target[Y0 : Y0 + PATCH, X0 : X0 + PATCH] += 0.1 * signs

    step(whole, target, VIEW_K)
    step(patch, target[Y0 : Y0 + PATCH, X0 : X0 + PATCH], patch_camera(VIEW_K, X0, Y0))
    share = PATCH * PATCH / (VIEW_H * VIEW_W)
    assert whole._drawn[3] == 1.0 and patch._drawn[3] == pytest.approx(share)
    whole_projection, patch_projection = whole._drawn[0], patch._drawn[0]
    assert whole_projection.ids.tolist() == patch_projection.ids.tolist() == list(range(5))
    # the set-up is the identity: the patch's loss gradient is the whole view's over the share (any parameter's)
    torch.testing.assert_close(patch.gaussians.means.grad * share, whole.gaussians.means.grad, rtol=1e-4, atol=1e-9)
    # the model scales the screen gradient by the share before the strategy reads it
    grad = whole_projection.means2d.grad
    assert grad.norm(dim=-1).min() > 1e-5
    torch.testing.assert_close(patch_projection.means2d.grad, grad, rtol=1e-4, atol=1e-9)
    read = grad
    if absgrad:  # the absolute gradient, kept by the rasteriser and scaled by the share as the plain one is
        read = whole_projection.means2d.absgrad
        assert (read.norm(dim=-1) > grad.norm(dim=-1) * 1.01).all()  # the pixels' pulls do not all point one way
        torch.testing.assert_close(patch_projection.means2d.absgrad, read, rtol=1e-4, atol=1e-9)
    else:
        assert getattr(whole_projection.means2d, "absgrad", None) is None  # not asked for, not kept
    # the strategy's norms, in units of half the whole view, the same from either
    torch.testing.assert_close(whole.strategy.grad_sum, (read * torch.tensor([VIEW_W / 2, VIEW_H / 2])).norm(dim=-1))
    torch.testing.assert_close(patch.strategy.grad_sum, whole.strategy.grad_sum, rtol=1e-4, atol=1e-9)
    assert patch.strategy.seen.tolist() == whole.strategy.seen.tolist() == [1.0] * 5


def test_a_coarse_view_is_a_whole_view_to_the_strategy():
    """A batch of a whole view averaged by ``scale`` (data.coarse_scale) gives the strategy its own size and a share of
    1, not the full views' size, against which it would look like a quarter of a view."""
    s = patch_scene()
    model = splat_model(*(s[key] for key in ("means", "quats", "log_scales", "opacities", "colours")), "tiles")
    model.view_size = (VIEW_H * 2, VIEW_W * 2)  # the training views at full resolution; this batch came averaged by 2
    with torch.no_grad():
        rendered, _ = model.draw(VIEW_K, VIEW_C2W, VIEW_H, VIEW_W)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*self.log.*")
        model.training_step({"image": rendered["rgb"] + 0.05, "K": VIEW_K, "c2w": VIEW_C2W, "scale": 2}, 0)
        assert model._drawn[1:] == (VIEW_W, VIEW_H, 1.0)
        model.training_step({"image": rendered["rgb"][:PATCH, :PATCH], "K": VIEW_K, "c2w": VIEW_C2W}, 0)  # full resolution
    assert model._drawn[1:] == (VIEW_W * 2, VIEW_H * 2, pytest.approx(PATCH * PATCH / (VIEW_H * VIEW_W * 4)))


# -- 7. the depth's scaling ----------------------------------------------------------------------------------------


def test_pixel_ray_lengths_are_the_lengths_of_the_unprojected_pixel_centres_at_z_1():
    ray_lengths = pixel_ray_lengths(K, HEIGHT, WIDTH)
    v, u = torch.meshgrid(torch.arange(HEIGHT, dtype=F64) + 0.5, torch.arange(WIDTH, dtype=F64) + 0.5, indexing="ij")
    homogeneous = torch.stack([u, v, torch.ones_like(u)], dim=-1)
    torch.testing.assert_close(ray_lengths, (homogeneous @ torch.linalg.inv(K).T).norm(dim=-1), rtol=1e-12, atol=0)
    # kornia's unprojection at camera z = 1, and the project's rays: a unit ray reaches z = 1 after the length
    uv = torch.stack([u, v], dim=-1).reshape(-1, 2)
    torch.testing.assert_close(ray_lengths.reshape(-1), unproject_points(uv, torch.ones(len(uv), 1, dtype=F64), K).norm(dim=-1),
                               rtol=1e-12, atol=0)
    _, directions = pixel_to_ray(K, torch.eye(4, dtype=F64), uv)
    torch.testing.assert_close(ray_lengths.reshape(-1), 1.0 / directions[:, 2], rtol=1e-12, atol=0)
    assert ray_lengths.max() > 1.03  # the corners' rays are well off the axis


@pytest.mark.parametrize("rasterizer", ["pairs", "tiles"])
def test_a_splat_models_depth_is_the_distance_along_the_pixels_unit_ray(rasterizer):
    """Opaque, flat, small Gaussians (discs facing the camera) centred on pixel centres near the corners of the view
    and in its middle, each placed by kornia's unprojection at a Euclidean distance d from the camera centre: the
    model's depth at those pixels is d (its camera z alone would be short by up to 4 %)."""
    pixels = torch.tensor([[2, 3], [45, 5], [3, 60], [44, 61], [24, 30], [10, 50]])  # (row, column)
    uv = pixels.flip(-1).to(F64) + 0.5
    distances = torch.tensor([3.0, 4.5, 2.5, 5.0, 3.5, 4.0], dtype=F64)
    in_camera = unproject_points(uv, distances[:, None], VIEW_K.double(), normalize=True)
    means = in_camera @ VIEW_ROTATION.T + VIEW_CENTRE
    torch.testing.assert_close((means - VIEW_CENTRE).norm(dim=-1), distances)
    origins, directions = pixel_to_ray(VIEW_K.double(), VIEW_C2W.double(), uv)  # the project's rays agree
    torch.testing.assert_close(origins + distances[:, None] * directions, means, rtol=0, atol=1e-6)
    n = len(pixels)
    # each disc's thin axis is the camera's z: its rotation is the camera's
    quats = quaternion(*VIEW_AXIS_ANGLE)[None].repeat(n, 1)
    log_scales = torch.log(torch.tensor([[0.03, 0.03, 1e-4]], dtype=F64)).repeat(n, 1)
    model = splat_model(means, quats, log_scales, torch.full((n,), 0.99, dtype=F64), torch.full((n, 3), 0.7, dtype=F64), rasterizer)
    model.eval()
    out = model.render_view(VIEW_K, VIEW_C2W, VIEW_H, VIEW_W)
    rows, columns = pixels.unbind(-1)
    assert (out["accumulation"][rows, columns] > 0.98).all()
    torch.testing.assert_close(out["depth"][rows, columns].double(), distances, rtol=1e-5, atol=0)
    z = in_camera[:, 2]
    assert ((distances - z) / distances).max() > 0.03  # camera z is not the answer
