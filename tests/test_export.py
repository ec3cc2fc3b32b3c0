"""Export's machinery on a field whose surface is known exactly: a sphere."""

import numpy as np
import torch

from nerf_lightning.export import density_grid, marching_cubes, ply_bytes, vertex_colours


class SphereField(torch.nn.Module):
    """Density 100 inside a sphere of radius 0.8 around (0.1, 0, -0.2), 0 outside, with a smooth edge;
    colour red seen from +x, blue seen from -x."""

    centre = torch.tensor([0.1, 0.0, -0.2])

    def density(self, points):
        return 100.0 * torch.sigmoid((0.8 - (points - self.centre).norm(dim=-1)) * 40.0)

    def forward(self, points, directions):
        side = (directions[..., :1] < 0).float()  # looking towards -x: sees the +x side
        return {"rgb": torch.cat([side, torch.zeros_like(side), 1 - side], -1), "density": self.density(points)}


def test_marching_cubes_finds_the_sphere_and_colours_it_from_outside():
    field = SphereField()
    low, high = torch.full((3,), -1.5), torch.full((3,), 1.5)
    vertices, faces = marching_cubes(density_grid(field.density, low, high, 64), 50.0, low, high)
    radius = np.linalg.norm(vertices - field.centre.numpy(), axis=1)
    grid_step = 3.0 / 63
    assert np.abs(radius - 0.8).max() < grid_step / 2  # on the true surface, to within half a grid step
    assert len(faces) > 1000 and faces.max() < len(vertices)
    colours = vertex_colours(field, vertices)
    plus_x = vertices[:, 0] > field.centre[0].item() + 0.3
    assert (colours[plus_x, 0] == 255).all() and (colours[plus_x, 2] == 0).all()  # seen from outside: red
    assert (colours[vertices[:, 0] < -0.5, 2] == 255).all()


def test_ply_layout():
    data = ply_bytes(np.zeros((3, 3)), np.array([[0, 1, 2]]), np.full((3, 3), 7, dtype=np.uint8))
    header, body = data.split(b"end_header\n")
    assert b"element vertex 3" in header and b"element face 1" in header
    assert len(body) == 3 * (12 + 3) + 1 * (1 + 12)
