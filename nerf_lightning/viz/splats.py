"""A Gaussian-splat model drawn by the browser itself: the arrays viser's splat renderer takes
(``scene.add_gaussian_splats``), made from the model's :class:`~nerf_lightning.models.contract.HasGaussians`.

Coordinates: the viewer's world *is* the scene's world. The page places every training camera's frustum at its
OpenCV c2w as is (viser's cameras, like the scene's, look down +z with y down), and a browser's camera comes back to
``render_view`` unchanged (:func:`~nerf_lightning.viz.scheduler.browser_camera`). So the Gaussians go in as the
model keeps them: centres are the means, covariances R S S^T R^T
(:func:`~nerf_lightning.splats.projection.covariances`), under a scene node at the identity.

Colours: the degree-0 spherical harmonic only, 0.5 + SH_C0 sh0 clamped to [0, 1] (viser's splats have one colour
each): view-independent, so shine and reflections that the higher bands carry are missing. The page's "rendered
frames" draws the model's own render (every band, and depth) instead.

viser sends covariances as float16: Gaussians smaller than about 1e-3 of a world unit lose precision (they are
sub-pixel unless one zooms right in), and entries past float16's largest are clamped.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from nerf_lightning.splats.projection import covariances
from nerf_lightning.splats.sh import sh_to_rgb

# The most Gaussians sent to a browser: each is 32 bytes in viser's buffer (32 MB a million, sent again at every
# refresh of the live view), and the browser depth-sorts all of them whenever its camera moves; past a million or two
# a tab slows to a few frames a second or runs out of memory. The most opaque are kept: they make most of the picture.
MAX_SPLATS = 1_000_000
# the largest finite float16, in which viser sends the covariances
FLOAT16_MAX = 65504.0


@dataclass
class SplatArrays:
    """What the browser is sent: M of the model's N Gaussians, in the viewer's world (the scene's).

    Attributes:
        centers: (M, 3) float32 means.
        covariances: (M, 3, 3) float32.
        rgbs: (M, 3) float32 in [0, 1], the degree-0 colours.
        opacities: (M, 1) float32 in [0, 1].
        total: N, the model's Gaussians (M < N when capped at the most opaque, or where some were not finite).
    """

    centers: np.ndarray
    covariances: np.ndarray
    rgbs: np.ndarray
    opacities: np.ndarray
    total: int

    @property
    def shown(self) -> int:
        return int(self.centers.shape[0])

    def describe(self) -> str:
        """The page's line on them."""
        if self.total == 0:
            return "no Gaussians yet"
        which = f"all {self.total:,}" if self.shown == self.total else f"the {self.shown:,} most opaque of {self.total:,}"
        return (f"the browser draws {which} Gaussians, degree-0 colours (view-independent); "
                "choose 'rendered frames' for the full colours and depth")


def dc_colours(sh0: torch.Tensor) -> torch.Tensor:
    """(N, 1, 3) degree-0 coefficients -> (N, 3) colours in [0, 1] (what every direction sees of that band)."""
    return sh_to_rgb(sh0[:, 0]).clamp(0.0, 1.0)


@torch.no_grad()
def splat_arrays(model, max_splats: int = MAX_SPLATS) -> SplatArrays:
    """The arrays of a :class:`~nerf_lightning.models.contract.HasGaussians` ``model`` that the browser draws: at
    most ``max_splats``, the most opaque (in the model's order), those with a non-finite value left out."""
    parameters = {name: value.detach().float() for name, value in model.gaussian_parameters().items()}
    total = int(parameters["means"].shape[0])
    opacities = torch.sigmoid(parameters["opacity_logits"].reshape(-1))
    finite = torch.isfinite(parameters["means"]).all(-1) & torch.isfinite(parameters["log_scales"]).all(-1)
    finite &= torch.isfinite(parameters["quats"]).all(-1) & torch.isfinite(opacities) & torch.isfinite(parameters["sh0"]).all(-1).all(-1)
    keep = torch.nonzero(finite).squeeze(-1)
    if len(keep) > max_splats:
        keep = keep[torch.topk(opacities[keep], max_splats, sorted=False).indices].sort().values
    means, quats, log_scales = parameters["means"][keep], parameters["quats"][keep], parameters["log_scales"][keep]
    covariance = covariances(quats, log_scales).clamp(-FLOAT16_MAX, FLOAT16_MAX)
    return SplatArrays(
        centers=means.cpu().numpy().astype(np.float32),
        covariances=covariance.cpu().numpy().astype(np.float32),
        rgbs=dc_colours(parameters["sh0"][keep]).cpu().numpy().astype(np.float32),
        opacities=opacities[keep][:, None].cpu().numpy().astype(np.float32),
        total=total,
    )
