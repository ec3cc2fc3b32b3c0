"""Per-image appearance embeddings (NeRF in the Wild's, nerfacto's): a learnt vector for each training image that the
colour network sees, so that one image's exposure or white balance is not baked into the scene as fog."""

from __future__ import annotations

import torch

from nerf_lightning.parameters.per_view import PerViewTable


class AppearanceEmbedding(PerViewTable):
    """``dim`` learnt numbers a training image, sized by :meth:`~nerf_lightning.parameters.per_view.PerViewTable.resize` once
    the data is loaded.

    ``forward(camera_indices, n_points)``: (n_points,) long indices of training images -> (n_points, dim); ``None``
    (a view that is not a training image: validation, evaluation, renders) -> the mean of the rows, as nerfstudio's
    ``use_average_appearance_embedding``.

    The mean row is what every held-out view is rendered with, so it has to be a vector the colour MLP knows.
    nerfstudio draws the rows from N(0, 1) and leaves them free: the mean of such rows lies far inside the cloud
    of rows (a trained row is several times longer than the mean), where the MLP was never trained, and the
    held-out PSNR falls while the training PSNR rises. Rows that start at zero and pay ``penalty`` times their mean
    squared norm (:meth:`penalties`, NeRF-W's and Zip-NeRF's small-embedding prior) stay near the mean, which lifts
    the held-out views (docs/benchmarks.md, "Appearance rows from zero with a penalty").

    Args:
        dim: the width of a row (nerfacto: 32).
        init: ``zeros`` or ``normal`` (N(0, 1), nerfstudio's): the rows' start.
        penalty: weight of the rows' mean squared norm in the loss; 0 for none.
    """

    def __init__(self, dim: int = 32, init: str = "zeros", penalty: float = 0.01) -> None:
        super().__init__(dim, init=init)
        if penalty < 0:
            raise ValueError(f"{type(self).__name__}: penalty must be >= 0, got {penalty}")
        self.penalty = penalty

    def penalties(self) -> dict[str, torch.Tensor]:
        """``appearance``: ``penalty`` times the rows' mean squared norm (empty when ``penalty`` is 0)."""
        if self.penalty == 0:
            return {}
        return {"appearance": self.penalty * self.rows.square().sum(-1).mean()}

    def forward(self, camera_indices: torch.Tensor | None, n_points: int) -> torch.Tensor:
        """(n_points,) training-image indices, or None -> (n_points, dim)."""
        if camera_indices is None:
            if self.rows.shape[0] == 0:
                raise IndexError("this AppearanceEmbedding has no training views yet: resize(n_training_views) first")
            return self.rows.mean(dim=0).expand(n_points, self.width)
        self.check_views(camera_indices)
        return self.rows[camera_indices]

    def extra_repr(self) -> str:
        return f"images={self.rows.shape[0]}, dim={self.width}, init={self.init}, penalty={self.penalty:g}"
