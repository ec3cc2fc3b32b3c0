"""A neural field of a 2D image: pixel position -> colour."""

from __future__ import annotations

import torch
from torch import nn

from nerf_lightning.fields.encodings import SinusoidalEncoding
from nerf_lightning.fields.mlp import MLP


class ImageField(nn.Module):
    """Sinusoidal encoding of (x, y) in [0, 1], an MLP with ReLU, three outputs through a sigmoid.

    Args:
        num_frequencies: the encoding's frequency levels L (input features 2 + 4L).
        hidden_width: width of every hidden layer.
        hidden_layers: number of hidden Linear+ReLU layers.
    """

    def __init__(self, num_frequencies: int = 10, hidden_width: int = 256, hidden_layers: int = 3) -> None:
        super().__init__()
        self.encoding = SinusoidalEncoding(in_dim=2, num_frequencies=num_frequencies)
        self.mlp = MLP(self.encoding.out_dim, hidden_width, hidden_layers, out_dim=3)

    def forward(self, xy: torch.Tensor) -> torch.Tensor:
        """(..., 2) positions, x by width and y by height in [0, 1] -> (..., 3) RGB in (0, 1)."""
        return torch.sigmoid(self.mlp(self.encoding(xy)))
