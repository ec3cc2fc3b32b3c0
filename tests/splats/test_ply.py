"""The splat PLY: Inria's layout, read back equal by our reader and by trimesh (a third-party reader), non-finite
Gaussians left out, other files refused by name."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from nerf_lightning.splats.ply import read_splat_ply, splat_properties, write_splat_ply


def splats(n: int = 7, rest: int = 15) -> dict[str, torch.Tensor]:
    generator = torch.Generator().manual_seed(0)
    return {
        "means": torch.randn(n, 3, generator=generator), "quats": torch.nn.functional.normalize(torch.randn(n, 4, generator=generator), dim=-1),
        "log_scales": torch.randn(n, 3, generator=generator) - 3, "opacity_logits": torch.randn(n, generator=generator),
        "sh0": torch.randn(n, 1, 3, generator=generator), "shN": torch.randn(n, rest, 3, generator=generator),
    }


@pytest.mark.parametrize("rest", [15, 3, 0])
def test_a_splat_ply_round_trips(tmp_path, rest):
    written = splats(rest=rest)
    path = write_splat_ply(tmp_path / "splats.ply", **written)
    read = read_splat_ply(path)
    for name, value in written.items():
        torch.testing.assert_close(read[name], value, msg=name)


def test_the_layout_is_inrias_and_trimesh_reads_it(tmp_path):
    written = splats()
    path = write_splat_ply(tmp_path / "splats.ply", **written)
    header = path.read_bytes().split(b"end_header\n")[0].decode()
    names = [line.split()[2] for line in header.splitlines() if line.startswith("property")]
    assert names[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] and len(names) == 62
    assert names[9:54] == [f"f_rest_{i}" for i in range(45)] and names[54:] == ["opacity", "scale_0", "scale_1", "scale_2",
                                                                                 "rot_0", "rot_1", "rot_2", "rot_3"]
    assert names == splat_properties(15)
    cloud = trimesh.load(path)
    np.testing.assert_allclose(np.asarray(cloud.vertices), written["means"].numpy(), rtol=1e-6)
    vertex = cloud.metadata["_ply_raw"]["vertex"]["data"]
    np.testing.assert_allclose(vertex["opacity"].reshape(-1), written["opacity_logits"].numpy(), rtol=1e-6)
    # f_rest is channel by channel: red's 15 coefficients first
    np.testing.assert_allclose(vertex["f_rest_1"].reshape(-1), written["shN"][:, 1, 0].numpy(), rtol=1e-6)
    np.testing.assert_allclose(vertex["f_rest_15"].reshape(-1), written["shN"][:, 0, 1].numpy(), rtol=1e-6)


def test_non_finite_gaussians_are_left_out_and_other_files_refused(tmp_path):
    written = splats()
    written["means"][2, 0] = float("nan")
    assert len(read_splat_ply(write_splat_ply(tmp_path / "s.ply", **written))["means"]) == 6
    (tmp_path / "mesh.ply").write_text("ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nend_header\n")
    with pytest.raises(ValueError, match="mesh.ply: expected a binary little-endian PLY"):
        read_splat_ply(tmp_path / "mesh.ply")
    (tmp_path / "other.txt").write_text("hello")
    with pytest.raises(ValueError, match="other.txt is not a PLY file"):
        read_splat_ply(tmp_path / "other.txt")
