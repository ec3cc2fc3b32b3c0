"""Each training photo's exposure and white balance, learnt: three gains a photo, one a colour, that the rendered
colours are multiplied by before they are compared with it (the per-photo part of PPISP's camera model, gsplat #858;
LichtFeld's per-image exposure and white balance).

A gain a colour is the smallest model of what a camera changes between photos of one capture: the exposure (the
three gains' common factor) and the white balance (their ratios). Learnt as logarithms, so a photo twice as bright
is +log 2 however bright the scene is. It acts on the rendered colours, which are what the photo's pixels are, after
the camera's response curve: for a power-law response ``y = x^g`` a gain before the curve is a gain after it too
(``(k x)^g = k^g x^g``), so the gains need no response curve to stand for an exposure change; a response shared by
every photo is learnt by the colours themselves.

The photos get their gains less the gains' mean over the training photos (zero-mean in the logarithm): the mean
photo is drawn with no gain at all, and that is how held-out views are drawn (validation, ``nerf-eval``, renders, the
viewer): nothing learnt says how their camera exposed them. Without the centring every gain and every colour could
drift together (a darker scene, brighter gains) and the identity would match no photo.

Where the gains pay, and where they do not, is measured in ``docs/guides/real-captures.md``: a capture whose photos
share their exposure (a Blender scene, a locked camera) has nothing for them to learn.
"""

from __future__ import annotations

import torch

from nerf_lightning.parameters.per_view import CentredViewTable


class ViewExposure(CentredViewTable):
    """Three log gains a training photo (``rows`` (V, 3): red, green, blue; zero at the start, sized by
    :meth:`~nerf_lightning.parameters.per_view.PerViewTable.resize`); a photo gets its row less the rows' mean, so
    that the mean photo, and every held-out view, is drawn with gain 1.

    ``forward(rgb, camera_index, accumulation, background)``: rendered colours (..., 3) of training photos
    ``camera_index`` (0-d for a whole view, or (...) a ray's own) -> the colours the photos are compared with;
    ``camera_index`` None (a held-out view) -> ``rgb`` as it is.

    Args:
        lr: the rows' learning rate (their own optimiser group). A photo's row moves only on the steps that draw it
            (a view a step: one in V), so it is larger than a colour's.
        penalty: weight of the centred rows' mean squared norm in the loss (logged as ``train/loss_appearance`` by
            splats, ``train/loss_exposure_appearance`` by a radiance field); 0 for none.
    """

    def __init__(self, lr: float = 1e-2, penalty: float = 1e-3) -> None:
        super().__init__(3, lr, penalty)

    def gains(self, camera_index: torch.Tensor) -> torch.Tensor:
        """(...) long training photos -> (..., 3) their gains (exp of the centred rows)."""
        self.check_views(camera_index.reshape(-1))
        return self.centred()[camera_index].exp()

    def forward(self, rgb: torch.Tensor, camera_index: torch.Tensor | None, accumulation: torch.Tensor | None = None,
                background: torch.Tensor | None = None) -> torch.Tensor:
        """rgb (..., 3) -> (..., 3) with the photos' gains. With ``accumulation`` (...) and ``background`` (3,) (what
        the renderer blended in by the transmittance left), only the scene's part ``f = rgb - (1 - a) background`` is
        multiplied: a background colour the loader put into the photos (a mask's, an alpha's) is no camera's. A 0-d
        ``camera_index`` gains every colour alike; a (...) one, each colour its own photo's."""
        if camera_index is None:
            return rgb
        gain = self.gains(camera_index).to(rgb.dtype)
        if accumulation is None or background is None:
            return rgb * gain
        drawn = rgb - (1.0 - accumulation[..., None].to(rgb.dtype)) * background.to(rgb)
        return rgb + drawn * (gain - 1.0)
