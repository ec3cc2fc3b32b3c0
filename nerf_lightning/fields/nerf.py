"""The NeRF MLP of Mildenhall et al. (2020): position -> density and a feature; feature + direction -> colour."""

from __future__ import annotations

import torch
from torch import nn

from nerf_lightning.fields.encodings import SinusoidalEncoding


class NeRFField(nn.Module):
    """The paper's network, with its sizes configurable (the course's shallower one is ``hidden_layers=4``).

    Position: sinusoidal encoding with ``position_frequencies`` levels (10: 63 features), ``hidden_layers``
    Linear+ReLU layers of ``hidden_width``, the encoded position concatenated again to the output of layer
    ``skip_layer`` (0-based; the paper's 4, feeding its sixth layer, as in the reference code). Density:
    one linear output through ReLU (or softplus) taken before the view branch. Colour: a linear feature of
    the trunk concatenated with the direction's encoding (``direction_frequencies`` levels; 4: 27 features),
    a ``view_width`` ReLU layer, 3 outputs through a sigmoid.
    """

    def __init__(
        self,
        position_frequencies: int = 10,
        direction_frequencies: int = 4,
        hidden_width: int = 256,
        hidden_layers: int = 8,
        skip_layer: int | None = 4,
        view_width: int = 128,
        density_activation: str = "relu",
    ) -> None:
        super().__init__()
        self.aabb, self.appearance = None, None  # an MLP over all of space, one look for every image (the Field protocol)
        if density_activation not in ("relu", "softplus"):
            raise ValueError(f"density_activation must be relu or softplus, got '{density_activation}'")
        if skip_layer is not None and not 0 <= skip_layer < hidden_layers - 1:
            raise ValueError(f"skip_layer must be between 0 and hidden_layers - 2 ({hidden_layers - 2}) or null, got {skip_layer}")
        self.position_encoding = SinusoidalEncoding(3, position_frequencies)
        self.direction_encoding = SinusoidalEncoding(3, direction_frequencies)
        self.skip_layer = skip_layer
        width_in = self.position_encoding.out_dim
        layers = []
        for index in range(hidden_layers):
            layers.append(nn.Linear(width_in, hidden_width))
            width_in = hidden_width + (self.position_encoding.out_dim if index == skip_layer else 0)
        self.trunk = nn.ModuleList(layers)
        self.density_head = nn.Linear(hidden_width, 1)
        self.feature = nn.Linear(hidden_width, hidden_width)
        self.view = nn.Linear(hidden_width + self.direction_encoding.out_dim, view_width)
        self.rgb_head = nn.Linear(view_width, 3)
        self.density_activation = nn.ReLU() if density_activation == "relu" else nn.Softplus()

    def density_and_feature(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(..., 3) points -> density (...,) >= 0 and the trunk's features (..., hidden_width)."""
        encoded = self.position_encoding(points)
        h = encoded
        for index, layer in enumerate(self.trunk):
            h = torch.relu(layer(h))
            if index == self.skip_layer:
                h = torch.cat([h, encoded], dim=-1)
        return self.density_activation(self.density_head(h))[..., 0], h

    def density(self, points: torch.Tensor) -> torch.Tensor:
        """(..., 3) points -> (...,) densities: what meshes and occupancy grids query."""
        return self.density_and_feature(points)[0]

    def forward(self, points: torch.Tensor, directions: torch.Tensor) -> dict[str, torch.Tensor]:
        """points (..., 3), unit view directions (..., 3) -> ``rgb`` (..., 3) in (0, 1), ``density`` (...,) >= 0."""
        density, h = self.density_and_feature(points)
        view = torch.relu(self.view(torch.cat([self.feature(h), self.direction_encoding(directions)], dim=-1)))
        return {"rgb": torch.sigmoid(self.rgb_head(view)), "density": density}
