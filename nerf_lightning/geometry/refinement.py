"""Camera refinement: a learnt pose correction for each training view (nerfstudio's ``CameraOptimizer``, SO3xR3).

Poses from structure from motion are off by a little, and a field fits that error as blur. Each training view gets
six numbers, a rotation vector (so(3), turned into a rotation by the exponential map, kornia's
``axis_angle_to_rotation_matrix``) and a translation (R^3), learnt with the field. A ray of view i is corrected
about its camera centre, ``o' = o + t_i`` and ``d' = exp(w_i) d``: the same corrections as nerfstudio's
``c2w @ [exp(w), t]`` (a rotation about the camera centre, whatever frame it is written in), with the same norms
for the penalties. Held-out and rendered views are not corrected: nothing learnt says how.

Models that render whole views (splats) correct the cameras instead of the rays: :meth:`CameraRefinement.corrected_c2w`
gives ``c2w' = [exp(w) R | c + t]`` (R, c: the camera's rotation and centre), which is nerfstudio's
``c2w @ [exp(w'), t']`` with the correction written in the camera's frame (``w' = R^T w``, ``t' = R^T t``); the
rays of ``c2w'`` are the rays :meth:`~CameraRefinement.forward` corrects, ``o + t`` and ``exp(w) d``.
"""

from __future__ import annotations

import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix

from nerf_lightning.parameters.per_view import PerViewTable


class CameraRefinement(PerViewTable):
    """SO3xR3 corrections of the training views' poses (``rows`` (V, 6): rotation vector, translation; zero at the
    start, sized by :meth:`~nerf_lightning.parameters.per_view.PerViewTable.resize`), with L2 penalties that keep them small.

    Args:
        lr: the corrections' learning rate (their own optimiser group; nerfstudio: 6e-4).
        rotation_penalty: weight of the mean squared rotation angle (radians; nerfstudio: 1e-3).
        translation_penalty: weight of the mean squared translation (scene units; nerfstudio: 1e-2).
    """

    def __init__(self, lr: float = 6e-4, rotation_penalty: float = 1e-3, translation_penalty: float = 1e-2) -> None:
        super().__init__(6, init="zeros")
        if lr <= 0 or rotation_penalty < 0 or translation_penalty < 0:
            raise ValueError(f"CameraRefinement needs lr > 0 and penalties >= 0, got {lr}, {rotation_penalty}, {translation_penalty}")
        self.lr, self.rotation_penalty, self.translation_penalty = lr, rotation_penalty, translation_penalty

    def forward(self, rays_o: torch.Tensor, rays_d: torch.Tensor, camera_indices: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(N, 3) rays of training views and (N,) their views -> the corrected (N, 3) origins and unit directions."""
        self.check_views(camera_indices)
        deltas = self.rows[camera_indices]  # (N, 6)
        rotation = axis_angle_to_rotation_matrix(deltas[:, :3])  # (N, 3, 3)
        return rays_o + deltas[:, 3:], (rotation @ rays_d[..., None])[..., 0]

    def corrected_c2w(self, c2w: torch.Tensor, camera_indices: torch.Tensor) -> torch.Tensor:
        """(V', 4, 4) camera-to-world of training views and (V',) their views -> the corrected (V', 4, 4): rotation
        ``exp(w) R``, centre ``c + t`` (the module's docstring), so that their rays equal :meth:`forward`'s."""
        if c2w.shape[-2:] != (4, 4) or c2w.shape[:-2] != camera_indices.shape or c2w.dim() != 3:
            raise ValueError(f"corrected_c2w needs c2w (V, 4, 4) and camera_indices (V,), got {tuple(c2w.shape)} and {tuple(camera_indices.shape)}")
        self.check_views(camera_indices)
        deltas = self.rows[camera_indices].to(c2w.dtype)  # (V, 6)
        rotation = axis_angle_to_rotation_matrix(deltas[:, :3])  # (V, 3, 3)
        top = torch.cat([rotation @ c2w[:, :3, :3], (c2w[:, :3, 3] + deltas[:, 3:])[..., None]], dim=-1)
        return torch.cat([top, c2w[:, 3:]], dim=-2)

    def penalties(self) -> dict[str, torch.Tensor]:
        """``camera_rotation`` and ``camera_translation``: the weighted mean squared sizes of the corrections."""
        return {"camera_rotation": self.rotation_penalty * self.rows[:, :3].square().sum(-1).mean(),
                "camera_translation": self.translation_penalty * self.rows[:, 3:].square().sum(-1).mean()}

    def extra_repr(self) -> str:
        return f"views={self.rows.shape[0]}, lr={self.lr:g}, rotation_penalty={self.rotation_penalty:g}, translation_penalty={self.translation_penalty:g}"
