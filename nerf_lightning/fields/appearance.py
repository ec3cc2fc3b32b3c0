"""Per-image appearance embeddings (NeRF in the Wild's, nerfacto's): a learnt vector for each training image that the
colour network sees, so that one image's exposure or white balance is not baked into the scene as fog."""

from __future__ import annotations

from typing import Any

import torch
from torch import nn


class AppearanceEmbedding(nn.Module):
    """A table of ``dim`` learnt numbers a training image, one row each.

    The number of rows is the number of training images, known once the data is loaded: :meth:`resize` sets it (the
    radiance-field module does, in ``setup``), and a checkpoint's table is loaded at the size it was saved with.
    ``forward(camera_indices)``: (M,) long indices of training images -> (M, dim); ``None`` (a view that is not a
    training image: validation, evaluation, renders) -> the mean of the rows, as nerfstudio's
    ``use_average_appearance_embedding``.

    Args:
        dim: the width of a row (nerfacto: 32).
    """

    def __init__(self, dim: int = 32) -> None:
        super().__init__()
        if dim < 1:
            raise ValueError(f"AppearanceEmbedding needs dim >= 1, got {dim}")
        self.dim = dim
        self.table = nn.Parameter(torch.zeros(0, dim))

    def resize(self, n_images: int) -> None:
        """One row a training image, drawn from N(0, 1) as ``nn.Embedding`` does; kept when the size already fits."""
        if n_images < 1:
            raise ValueError(f"an appearance embedding needs at least one training image, got {n_images}")
        if self.table.shape[0] != n_images:
            self.table = nn.Parameter(torch.randn(n_images, self.dim, device=self.table.device))

    def forward(self, camera_indices: torch.Tensor | None, n_points: int) -> torch.Tensor:
        """(n_points,) training-image indices, or None -> (n_points, dim)."""
        if self.table.shape[0] == 0:
            raise RuntimeError("AppearanceEmbedding has no rows yet: resize(n_training_images) before rendering")
        if camera_indices is None:
            return self.table.mean(dim=0).expand(n_points, self.dim)
        if int(camera_indices.max()) >= self.table.shape[0]:
            raise IndexError(f"camera index {int(camera_indices.max())} for an appearance table of {self.table.shape[0]} training images")
        return self.table[camera_indices]

    def _load_from_state_dict(self, state_dict: dict[str, Any], prefix: str, *args: Any, **kwargs: Any) -> None:
        saved = state_dict.get(prefix + "table")
        if saved is not None and saved.shape != self.table.shape:
            self.table = nn.Parameter(torch.zeros_like(saved, device=self.table.device))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def extra_repr(self) -> str:
        return f"images={self.table.shape[0]}, dim={self.dim}"
