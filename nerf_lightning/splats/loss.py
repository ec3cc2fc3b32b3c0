"""The splats' photometric loss, the reference: (1 - w) L1 + w (1 - SSIM) of a drawn view against its photo (3DGS's),
in PyTorch over :func:`~nerf_lightning.metrics.ssim_map`. :mod:`~nerf_lightning.splats.loss_fast` gives the same
value and gradient in one numba pass on a CPU; the tests hold the two equal. :class:`SplatLoss` holds what a model's
step is scored by (``model.loss``): the SSIM's weight, the mask and depth losses and the training background."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from nerf_lightning.metrics import check_loss_weight, check_train_background, depth_l1, opacity_mask_loss, ssim_map


def photometric_loss(rgb: torch.Tensor, image: torch.Tensor, ssim_weight: float,
                     mask: torch.Tensor | None = None) -> torch.Tensor:
    """() (1 - ssim_weight) L1 + ssim_weight (1 - SSIM) of rgb (H, W, 3) against image (H, W, 3): means over the
    pixels, or over ``mask`` (H, W) bool where given. SSIM is kornia's (11x11 Gaussian window, reflect padding)."""
    similarity = ssim_map(rgb.permute(2, 0, 1)[None], image.permute(2, 0, 1)[None])
    if mask is None:
        l1, ssim = (rgb - image).abs().mean(), similarity.mean()
    else:
        count = mask.sum().clamp(min=1)
        l1 = ((rgb - image).abs().mean(dim=-1) * mask).sum() / count
        ssim = (similarity[0].mean(dim=0) * mask).sum() / count
    return (1.0 - ssim_weight) * l1 + ssim_weight * (1.0 - ssim)


@dataclass(frozen=True)
class SplatLoss:
    """What a splat model's training step is scored by (``model.loss``).

    Args:
        ssim_weight: the photometric loss is (1 - w) L1 + w (1 - SSIM) (:func:`photometric_loss`; 3DGS's 0.2).
        mask_loss: the weight of a binary cross-entropy between each training pixel's opacity and its object mask
            (NeuS's mask loss; logged as ``train/loss_mask``), with ``data.masks=background``: the Gaussians are
            taught where the object ends by the masks themselves, not only by the background's colour. 0: none.
        train_background: what a training view shows where its Gaussians leave it transparent: ``scene`` (the scene
            space's background colour) or ``random`` (one random colour a step, gsplat's ``random_bkgd``; with
            ``data.masks=background`` the photo's pixels outside the mask show that colour too): a Gaussian then
            cannot stand for the background by being transparent, nor a dark surface by letting black through.
            Held-out views are drawn over the scene's background.
        depth_loss: the weight of the mean absolute difference between each training pixel's drawn depth (the
            distance along its unit ray) and the capture's (its depth maps; logged as ``train/loss_depth``), over the
            pixels whose depth is known (and, with ``data.masks=exclude``, inside the mask). 0: none.
    """

    ssim_weight: float = 0.2
    mask_loss: float = 0.0
    train_background: str = "scene"
    depth_loss: float = 0.0

    def __post_init__(self) -> None:
        if isinstance(self.ssim_weight, bool) or not (isinstance(self.ssim_weight, (int, float)) and 0 <= self.ssim_weight <= 1):
            raise ValueError(f"model.loss.ssim_weight must be a number in [0, 1], got {self.ssim_weight!r}")
        for key in ("mask_loss", "depth_loss"):
            check_loss_weight(getattr(self, key), f"model.loss.{key}")
        check_train_background(self.train_background, "model.loss.train_background")

    def photometric(self, rgb: torch.Tensor, image: torch.Tensor, mask: torch.Tensor | None,
                    fused: bool = False) -> tuple[torch.Tensor, float | None]:
        """() (1 - w) L1 + w (1 - SSIM) of rgb (H, W, 3) against image (H, W, 3), means over ``mask`` (H, W) where
        given, and the mean squared error where it comes free: with ``fused`` (where numba draws) in one numba pass
        (:mod:`~nerf_lightning.splats.loss_fast`), else :func:`photometric_loss` and None."""
        if fused:
            from nerf_lightning.splats.loss_fast import photometric_loss_fast

            return photometric_loss_fast(rgb, image, self.ssim_weight, mask)
        return photometric_loss(rgb, image, self.ssim_weight, mask), None

    def of_mask(self, accumulation: torch.Tensor, object_mask: torch.Tensor | None) -> torch.Tensor:
        """() ``mask_loss`` x the binary cross-entropy of the opacity ``accumulation`` (H, W) against ``object_mask``
        (H, W), the training batch's; without it, one line saying what the mask loss needs."""
        if object_mask is None:
            raise ValueError("model.loss.mask_loss > 0 needs the object's masks in each training batch: data.masks=background "
                             "(and a capture with masks); set model.loss.mask_loss=0 otherwise")
        return self.mask_loss * opacity_mask_loss(accumulation, object_mask)

    def of_depth(self, depth: torch.Tensor, target: torch.Tensor | None, mask: torch.Tensor | None = None) -> torch.Tensor:
        """() ``depth_loss`` x the mean absolute difference of the drawn ``depth`` (H, W) and the training batch's
        ``target`` (H, W) over its known pixels (:func:`~nerf_lightning.metrics.depth_l1`; within ``mask`` (H, W) where
        given); without a target, one line saying what the depth loss needs."""
        if target is None:
            raise ValueError("model.loss.depth_loss > 0 needs depth in each training batch: a capture whose frames have a "
                             "'depth_file_path' (data/scene=transforms) or the procedural scene; set model.loss.depth_loss=0 otherwise")
        return self.depth_loss * depth_l1(depth, target, None if mask is None else mask.to(depth.dtype))
