"""The plain multi-layer perceptron every field here is built from."""

from __future__ import annotations

from torch import nn


class MLP(nn.Sequential):
    """``hidden_layers`` Linear+ReLU layers of ``hidden_width``, then a Linear to ``out_dim``.

    (..., in_dim) -> (..., out_dim); the output has no activation, the field adds the one it needs.
    """

    def __init__(self, in_dim: int, hidden_width: int, hidden_layers: int, out_dim: int) -> None:
        if hidden_layers < 1 or hidden_width < 1:
            raise ValueError(f"MLP needs hidden_layers >= 1 and hidden_width >= 1, got {hidden_layers}, {hidden_width}")
        layers: list[nn.Module] = []
        width_in = in_dim
        for _ in range(hidden_layers):
            layers += [nn.Linear(width_in, hidden_width), nn.ReLU(inplace=True)]
            width_in = hidden_width
        layers.append(nn.Linear(width_in, out_dim))
        super().__init__(*layers)
