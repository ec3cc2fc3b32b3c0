"""Quality metrics: of images (PSNR and SSIM from kornia, depth error; an SSIM map for losses, equal to kornia's; the
colour correction before the ``cc_`` scores) and of meshes (Chamfer distance); the masks' opacity loss (binary
cross-entropy against the object masks) and the depth loss (L1 against a capture's depth maps)."""

from __future__ import annotations

import math

import kornia
import numpy as np
import torch


# model.train_background (NeRF) and model.loss.train_background (splats): what a training view is composited over
# where the model leaves it transparent: the scene space's colour, or one random colour a step
TRAIN_BACKGROUNDS = ("scene", "random")


def check_train_background(value: str, key: str = "model.train_background") -> str:
    """``value`` if it is one of :data:`TRAIN_BACKGROUNDS`, else one line naming ``key``."""
    if value not in TRAIN_BACKGROUNDS:
        raise ValueError(f"{key} must be one of {', '.join(TRAIN_BACKGROUNDS)}, got '{value}'")
    return value


def check_loss_weight(weight: float, key: str) -> float:
    """``weight`` of a loss (``key``: ``model.mask_loss``, ``model.loss.depth_loss``, ...) if it is a finite number
    >= 0, else one line naming the key."""
    if isinstance(weight, bool) or not (isinstance(weight, (int, float)) and math.isfinite(weight) and weight >= 0):
        raise ValueError(f"{key} must be a number >= 0 (0: none), got {weight!r}")
    return float(weight)


def opacity_mask_loss(accumulation: torch.Tensor, object_mask: torch.Tensor, weight: torch.Tensor | None = None,
                      eps: float = 1e-3) -> torch.Tensor:
    """() mean binary cross-entropy of (...) opacities in [0, 1] against (...) object masks (bool, or the share of
    each pixel on the object): opaque on the object, clear off it (NeuS's mask loss). Clamped to [eps, 1 - eps], so
    that a pixel already right gives a finite loss. ``weight`` (...): a weighted mean instead (0 leaves a pixel out)."""
    entropy = torch.nn.functional.binary_cross_entropy(accumulation.clamp(eps, 1.0 - eps), object_mask.to(accumulation.dtype),
                                                       reduction="none")
    if weight is None:
        return entropy.mean()
    return (entropy * weight).sum() / weight.sum().clamp(min=1)


def depth_l1(depth: torch.Tensor, target: torch.Tensor, weight: torch.Tensor | None = None) -> torch.Tensor:
    """() mean absolute difference of rendered ``depth`` (...) and a capture's ``target`` (...) (both distances along
    unit rays) over the pixels whose target is known (finite and > 0: NaN unknown, inf no surface); 0 where none is.
    ``weight`` (...): a weighted mean instead (0 leaves a pixel out). Of fixed shapes, so a compiled step takes it."""
    known = torch.isfinite(target) & (target > 0)
    if weight is not None:
        known = known & (weight > 0)
    difference = torch.where(known, depth - torch.where(known, target, torch.zeros_like(target)), torch.zeros_like(depth)).abs()
    counted = known.to(depth.dtype) if weight is None else known.to(depth.dtype) * weight
    return (difference * counted).sum() / counted.sum().clamp(min=1)


def mse_to_psnr(mse: torch.Tensor) -> torch.Tensor:
    """PSNR in dB of colours in [0, 1] from their mean squared error: -10 log10(mse)."""
    return -10.0 * torch.log10(mse)


def ssim_map(images: torch.Tensor, targets: torch.Tensor, window_size: int = 11) -> torch.Tensor:
    """(B, C, H, W) images and targets in [0, 1] -> (B, C, H, W) the SSIM map of ``kornia.metrics.ssim`` (Gaussian
    window of sigma 1.5, reflect padding, the same constants), for a loss that is differentiated every step.

    kornia blurs the five moments (x, y, x^2, y^2, xy) one after another; here they are stacked and blurred by one
    padding and one pair of grouped 1D convolutions, so that the forward and backward passes each run a few large
    convolutions instead of many small ones. The tests hold it equal to kornia's in values and gradients."""
    if images.shape != targets.shape or images.ndim != 4:
        raise ValueError(f"ssim_map expects (B, C, H, W) images and targets of one shape, got {tuple(images.shape)} "
                         f"and {tuple(targets.shape)}")
    channels, radius = images.shape[1], window_size // 2
    kernel = kornia.filters.get_gaussian_kernel1d(window_size, 1.5, device=images.device, dtype=images.dtype)
    moments = torch.cat([images, targets, images * images, targets * targets, images * targets], dim=1)
    groups = moments.shape[1]
    blurred = torch.nn.functional.pad(moments, [radius] * 4, mode="reflect")
    blurred = torch.nn.functional.conv2d(blurred, kernel.reshape(1, 1, 1, -1).expand(groups, 1, 1, -1), groups=groups)
    blurred = torch.nn.functional.conv2d(blurred, kernel.reshape(1, 1, -1, 1).expand(groups, 1, -1, 1), groups=groups)
    mu1, mu2, mu1_sq_blur, mu2_sq_blur, mu12_blur = blurred.split(channels, dim=1)
    c1, c2 = 0.01**2, 0.03**2
    mu1_mu2, mu1_sq, mu2_sq = mu1 * mu2, mu1 * mu1, mu2 * mu2
    numerator = (2.0 * mu1_mu2 + c1) * (2.0 * (mu12_blur - mu1_mu2) + c2)
    denominator = (mu1_sq + mu2_sq + c1) * ((mu1_sq_blur - mu1_sq) + (mu2_sq_blur - mu2_sq) + c2)
    return numerator / (denominator + 1e-12)


def colour_correct(rgb: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """(H, W, 3) rendered colours -> (H, W, 3) the same under the affine colour map (a 3x3 matrix and a bias) that
    brings them closest to ``target`` (H, W, 3) in squared error, clipped to [0, 1]: what the ``cc_`` scores are
    taken on (gsplat's ``cc_psnr``; Zip-NeRF's ``color_correct``).

    The map says how far a render is from its photo in everything but a global colour transform: a held-out photo's
    exposure and white balance, which nothing learnt from the training photos can know. It is fitted over every
    pixel, by the squared error PSNR measures, so a corrected render never scores below the raw one (the identity is
    one of the maps, and clipping to [0, 1] only brings colours closer to a photo's). Zip-NeRF leaves the pixels a
    photo clips out of its fit and applies the map to them anyway; where a white or black background fills most of a
    view that moved them far off (a procedural view scored 7 dB under its raw 18.6).

    With ``mask`` (H, W) bool, the map is fitted over the mask's pixels and changes only them: where a loader put a
    background colour into the photo (``data.masks=background``), that colour is no camera's. Solved on the CPU in
    float64 by SVD (gelsd), which a flat channel (a rank-deficient fit) leaves stable."""
    if rgb.shape != target.shape or rgb.ndim != 3 or rgb.shape[-1] != 3:
        raise ValueError(f"colour_correct expects (H, W, 3) rgb and target of one shape, got {tuple(rgb.shape)} and {tuple(target.shape)}")
    if mask is not None and mask.shape != rgb.shape[:2]:
        raise ValueError(f"colour_correct expects an (H, W) mask of the images' size, got {tuple(mask.shape)} for {tuple(rgb.shape)}")
    inside = torch.ones(rgb.shape[:2], dtype=torch.bool, device=rgb.device) if mask is None else mask.bool()
    if int(inside.sum()) < 4:  # nothing to fit a map on
        return rgb.clone()
    colours, wanted = rgb[inside].detach().cpu().double(), target[inside].detach().cpu().double()
    features = torch.cat([colours, torch.ones_like(colours[:, :1])], dim=1)  # (P, 4)
    transform = torch.linalg.lstsq(features, wanted, driver="gelsd").solution  # (4, 3)
    corrected = rgb.clone()
    corrected[inside] = (features @ transform).clamp(0.0, 1.0).to(rgb)
    return corrected


def image_metrics(
    rgb: torch.Tensor, target: torch.Tensor, depth: torch.Tensor | None = None, true_depth: torch.Tensor | None = None,
    mask: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """The metrics of one rendered view, the same in validation and in ``nerf-eval``.

    Args:
        rgb, target: (H, W, 3) rendered and true colours in [0, 1].
        depth: (H, W) rendered depth (the expected distance along unit rays); true_depth: (H, W) the true distance,
            inf where the pixel sees no surface; both or neither.

    Returns:
        ``psnr`` (dB), ``ssim`` (kornia, 11x11 window) and, with depths, ``depth_error``: the mean absolute
        difference over the pixels that see a surface (NaN when none does). 0-d tensors.
    """
    if rgb.shape != target.shape or rgb.ndim != 3 or rgb.shape[-1] != 3:
        raise ValueError(f"image_metrics expects (H, W, 3) rgb and target of one shape, got {tuple(rgb.shape)} and {tuple(target.shape)}")
    ssim_map = kornia.metrics.ssim(rgb.permute(2, 0, 1)[None], target.permute(2, 0, 1)[None], window_size=11)[0].mean(dim=0)  # (H, W)
    metrics = {"psnr": kornia.metrics.psnr(rgb, target, max_val=1.0), "ssim": ssim_map.mean()}
    if mask is not None:
        nan = rgb.new_tensor(float("nan"))
        masked = bool(mask.any())
        metrics["psnr_masked"] = mse_to_psnr(((rgb - target) ** 2)[mask].mean()) if masked else nan
        metrics["ssim_masked"] = ssim_map[mask].mean() if masked else nan
    if depth is not None and true_depth is not None:
        surface = torch.isfinite(true_depth)
        metrics["depth_error"] = (depth[surface] - true_depth[surface]).abs().mean() if bool(surface.any()) else rgb.new_tensor(float("nan"))
    return metrics


def chamfer_distance(vertices: np.ndarray | torch.Tensor, surface_points: torch.Tensor, mesh_to_surface: torch.Tensor | None = None,
                     chunk: int = 4096) -> dict[str, float]:
    """How far a mesh is from a true surface, in scene units.

    Args:
        vertices: (V, 3) the mesh's vertices.
        surface_points: (P, 3) points of the true surface (for example what views see at their true depth).
        mesh_to_surface: (V,) each vertex's exact distance to the surface where it is known (a signed distance
            function); otherwise the distance to the nearest of ``surface_points``.

    Returns:
        ``mesh_to_surface`` and ``surface_to_mesh`` (mean nearest distances each way) and ``chamfer``, their mean.
    """
    vertices_t = torch.as_tensor(np.asarray(vertices)).double()
    surface_points = surface_points.double()

    def nearest(from_points: torch.Tensor, to_points: torch.Tensor) -> torch.Tensor:
        return torch.cat([torch.cdist(part, to_points).amin(dim=1) for part in from_points.split(chunk)])

    to_surface = float(mesh_to_surface.abs().mean()) if mesh_to_surface is not None else float(nearest(vertices_t, surface_points).mean())
    to_mesh = float(nearest(surface_points, vertices_t).mean())
    return {"mesh_to_surface": to_surface, "surface_to_mesh": to_mesh, "chamfer": 0.5 * (to_surface + to_mesh)}
