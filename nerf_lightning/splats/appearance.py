"""A learnt colour transform for each training view of Gaussian splats: an affine map of the colours a view's
Gaussians draw, so that one photo's exposure or white balance is not baked into the Gaussians' colours.

Each training view gets twelve numbers, a 3x3 matrix ``A`` (as an offset from the identity) and a bias ``b``, zero
at the start, so the transform starts as the identity: the Gaussians' contribution to a pixel ``f`` becomes
``f (I + A)^T + a b`` (``a`` the pixel's accumulation), which is the transform applied to each Gaussian's colour
before compositing (the composite is linear in the colours and its weights sum to ``a``).

The background is left as it is. Where a photo shows the background colour, the loader put it there (a synthetic
capture's alpha, a ``background`` mask), not the camera; a real capture's photos are opaque everywhere and the
Gaussians cover them, so the background shows only through holes, which a transform of it would hide rather than fix.

The views get their rows less the rows' mean (:meth:`ViewColourAffine.centred`): the mean transform is the identity
exactly, so the Gaussians' colours are the views' mean exposure, which is what a held-out view is drawn with.
Without it, all the rows and the colours could drift together (a darker scene, brighter transforms), and the
identity would match no training view (a tiny test scene lost 2 dB on its held-out views that way). A small L2
penalty on the centred rows keeps each view's transform near the mean.

Held-out views (validation, ``nerf-eval``, ``nerf-render``, the viewer) are drawn with no transform (the identity,
the training views' mean): nothing learnt says how their camera saw the scene; nerfstudio's splatfacto draws its
held-out views without a per-image appearance too.
"""

from __future__ import annotations

import torch

from nerf_lightning.parameters.per_view import CentredViewTable


class ViewColourAffine(CentredViewTable):
    """An affine colour transform for each training view (``rows`` (V, 12): ``A`` (3x3, row-major, an offset from
    the identity), then ``b`` (3,); zero at the start, sized by
    :meth:`~nerf_lightning.parameters.per_view.PerViewTable.resize`; a view gets its row less the rows' mean), with an L2
    penalty that keeps each near the identity.

    ``forward(rgb, camera_index, accumulation, background)``: a training view's rendered colours -> the colours its
    photo is compared with; ``camera_index`` None (a held-out view) -> ``rgb`` as it is.

    Args:
        lr: the rows' learning rate (their own optimiser group; gsplat's bilateral grids', whose cells are such
            transforms: 2e-3).
        penalty: weight of the centred rows' mean squared norm in the loss (``train/loss_appearance``); 0 for none.
    """

    def __init__(self, lr: float = 2e-3, penalty: float = 0.01) -> None:
        super().__init__(12, lr, penalty)

    def offset_and_bias(self, camera_index: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """() or (V',) long training views -> ``A`` (..., 3, 3) (the matrix is ``I + A``) and ``b`` (..., 3), from
        the centred rows."""
        self.check_views(camera_index.reshape(-1))
        row = self.centred()[camera_index]
        return row[..., :9].unflatten(-1, (3, 3)), row[..., 9:]

    def forward(self, rgb: torch.Tensor, camera_index: torch.Tensor | None, accumulation: torch.Tensor | None = None,
                background: torch.Tensor | None = None) -> torch.Tensor:
        """rgb (..., 3) of one training view ``camera_index`` (0-d long) -> the transformed (..., 3).

        With ``accumulation`` (...) and ``background`` (3,) (what the rasteriser blended in by the transmittance
        left), only the Gaussians' part ``f = rgb - (1 - a) background`` is transformed: ``rgb + f A^T + a b``;
        without them, the whole colour: ``rgb (I + A)^T + b``. ``camera_index`` None: ``rgb`` unchanged."""
        if camera_index is None:
            return rgb
        if camera_index.dim() != 0:
            raise ValueError(f"ViewColourAffine transforms one view at a time: camera_index must be 0-d, got shape {tuple(camera_index.shape)}")
        offset, bias = (part.to(rgb.dtype) for part in self.offset_and_bias(camera_index))
        if accumulation is None or background is None:
            return rgb + rgb @ offset.T + bias
        alpha = accumulation[..., None].to(rgb.dtype)
        drawn = rgb - (1.0 - alpha) * background.to(rgb)
        return rgb + drawn @ offset.T + alpha * bias
