"""Meshes of a field whose surface is known exactly (a sphere): marching cubes, colours, floaters, the formats."""

import numpy as np
import pytest
import torch

from nerf_lightning.outputs.mesh import density_grid, keep_pieces, make_mesh, marching_cubes, parse_keep, read_mesh, vertex_colours, write_mesh


class SphereField(torch.nn.Module):
    """Density 100 inside a sphere of radius 0.8 around (0.1, 0, -0.2), 0 outside, with a smooth edge;
    colour red seen from +x, blue seen from -x. ``floater`` adds a small ball of density at (1.2, 1.2, 1.2)."""

    centre = torch.tensor([0.1, 0.0, -0.2])

    def __init__(self, floater: bool = False):
        super().__init__()
        self.floater = floater

    def density(self, points):
        density = 100.0 * torch.sigmoid((0.8 - (points - self.centre).norm(dim=-1)) * 40.0)
        if self.floater:
            density = density + 100.0 * torch.sigmoid((0.15 - (points - 1.2).norm(dim=-1)) * 40.0)
        return density

    def forward(self, points, directions):
        side = (directions[..., :1] < 0).float()  # looking towards -x: sees the +x side
        return {"rgb": torch.cat([side, torch.zeros_like(side), 1 - side], -1), "density": self.density(points)}


def sphere_mesh(field, resolution=64):
    low, high = torch.full((3,), -1.5), torch.full((3,), 1.5)
    vertices, faces = marching_cubes(density_grid(field.density, low, high, resolution), 50.0, low, high)
    colours = vertex_colours(lambda points, viewdirs: field(points, viewdirs)["rgb"], field.density, vertices)
    return make_mesh(vertices, faces, colours)


def test_marching_cubes_finds_the_sphere_and_colours_it_from_outside():
    field = SphereField()
    mesh = sphere_mesh(field)
    vertices, colours = np.asarray(mesh.vertices), np.asarray(mesh.visual.vertex_colors)[:, :3]
    radius = np.linalg.norm(vertices - field.centre.numpy(), axis=1)
    grid_step = 3.0 / 63
    assert np.abs(radius - 0.8).max() < grid_step / 2  # on the true surface, to within half a grid step
    assert len(mesh.faces) > 1000 and mesh.faces.max() < len(vertices)
    plus_x = vertices[:, 0] > field.centre[0].item() + 0.3
    assert (colours[plus_x, 0] == 255).all() and (colours[plus_x, 2] == 0).all()  # seen from outside: red
    assert (colours[vertices[:, 0] < -0.5, 2] == 255).all()


def test_floating_pieces_are_dropped_by_size():
    mesh = sphere_mesh(SphereField(floater=True))
    near_floater = np.linalg.norm(np.asarray(mesh.vertices) - 1.2, axis=1) < 0.3
    assert near_floater.any()
    for keep in ("largest", 1000):  # the floater has 356 faces, the sphere 10 660
        kept = keep_pieces(mesh, keep)
        assert not (np.linalg.norm(np.asarray(kept.vertices) - 1.2, axis=1) < 0.3).any()
        assert len(kept.faces) == len(mesh.faces) - int(near_floater.sum() * 2 - 4)  # a closed piece: F = 2V - 4
        assert len(kept.visual.vertex_colors) == len(kept.vertices)
    assert len(keep_pieces(mesh, "all").faces) == len(mesh.faces)
    assert len(keep_pieces(mesh, 10**7).faces) == 0


def test_keep_is_validated_with_its_name():
    assert parse_keep("largest") == "largest" and parse_keep("ALL") == "all" and parse_keep("300") == 300 and parse_keep(5) == 5
    for bad in ("biggest", "0", -3, "1.5"):
        with pytest.raises(ValueError, match="keep must be largest, all or a number of faces"):
            parse_keep(bad)


@pytest.mark.parametrize("suffix", ["ply", "obj", "glb"])
def test_each_format_reads_back_with_its_vertices_faces_and_colours(suffix, tmp_path):
    mesh = sphere_mesh(SphereField(), resolution=24)
    path = write_mesh(tmp_path / f"mesh.{suffix}", mesh)
    back = read_mesh(path)
    assert len(back.faces) == len(mesh.faces)
    # the same surface (OBJ and GLB may reorder or merge vertices): every vertex read back is one written
    written = {tuple(v) for v in np.round(np.asarray(mesh.vertices), 4)}
    assert all(tuple(v) in written for v in np.round(np.asarray(back.vertices), 4))
    np.testing.assert_array_equal(np.unique(np.asarray(back.visual.vertex_colors)[:, :3], axis=0),
                                  np.unique(np.asarray(mesh.visual.vertex_colors)[:, :3], axis=0))


def test_an_unknown_format_is_refused_with_the_path(tmp_path):
    with pytest.raises(ValueError, match=r"mesh format must be one of ply, obj, glb, got 'stl'"):
        write_mesh(tmp_path / "mesh.stl", sphere_mesh(SphereField(), resolution=16))
    assert not (tmp_path / "mesh.stl").exists()
