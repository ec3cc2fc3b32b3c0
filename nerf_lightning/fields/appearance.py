"""Per-image appearance embeddings (NeRF in the Wild's, nerfacto's): a learnt vector for each training image that the
colour network sees, so that one image's exposure or white balance is not baked into the scene as fog."""

from __future__ import annotations

import torch

from nerf_lightning.per_view import PerViewTable


class AppearanceEmbedding(PerViewTable):
    """``dim`` learnt numbers a training image (rows drawn from N(0, 1), as nerfstudio's embedding), sized by
    :meth:`~nerf_lightning.per_view.PerViewTable.resize` once the data is loaded.

    ``forward(camera_indices, n_points)``: (n_points,) long indices of training images -> (n_points, dim); ``None``
    (a view that is not a training image: validation, evaluation, renders) -> the mean of the rows, as nerfstudio's
    ``use_average_appearance_embedding``.

    Args:
        dim: the width of a row (nerfacto: 32).
    """

    def __init__(self, dim: int = 32) -> None:
        super().__init__(dim, init="normal")

    def forward(self, camera_indices: torch.Tensor | None, n_points: int) -> torch.Tensor:
        """(n_points,) training-image indices, or None -> (n_points, dim)."""
        if camera_indices is None:
            if self.rows.shape[0] == 0:
                raise IndexError("this AppearanceEmbedding has no training views yet: resize(n_training_views) first")
            return self.rows.mean(dim=0).expand(n_points, self.width)
        self.check_views(camera_indices)
        return self.rows[camera_indices]

    def extra_repr(self) -> str:
        return f"images={self.rows.shape[0]}, dim={self.width}"
