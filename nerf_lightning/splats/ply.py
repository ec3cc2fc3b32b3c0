"""The standard 3D Gaussian splatting PLY (the Inria layout that SuperSplat, the web viewers and nerfstudio's export
use): one binary little-endian ``vertex`` element with float32 properties

    x y z  nx ny nz  f_dc_0..2  f_rest_0..(3 (K - 1) - 1)  opacity  scale_0..2  rot_0..3

where the opacity is a logit, the scales are logs, rot is the quaternion (w, x, y, z) and the higher spherical-harmonic
coefficients are stored channel by channel (all of red's K - 1, then green's, then blue's). The normals are zero.
Written with numpy (the layout is fixed; no dependency needed); read back by :func:`read_splat_ply`, by ``plyfile``
and by ``trimesh``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from nerf_lightning.io import write_atomic


def splat_properties(rest: int) -> list[str]:
    """The vertex properties for ``rest`` higher coefficients a channel ((sh_degree + 1)^2 - 1)."""
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(3 * rest)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def write_splat_ply(path: str | Path, means: torch.Tensor, quats: torch.Tensor, log_scales: torch.Tensor, opacity_logits: torch.Tensor,
                    sh0: torch.Tensor, shN: torch.Tensor) -> Path:
    """Write N Gaussians: means (N, 3), quats (N, 4) w x y z, log_scales (N, 3), opacity_logits (N,), sh0 (N, 1, 3),
    shN (N, K - 1, 3). Gaussians with a non-finite value are left out (a viewer would show them nowhere or everywhere)."""
    n = means.shape[0]
    rest = shN.shape[1]
    columns = [means, torch.zeros(n, 3), sh0.reshape(n, 3), shN.transpose(1, 2).reshape(n, 3 * rest), opacity_logits[:, None],
               log_scales, torch.nn.functional.normalize(quats, dim=-1)]
    table = torch.cat([column.detach().float().cpu() for column in columns], dim=1).numpy()
    table = table[np.isfinite(table).all(axis=1)]
    names = splat_properties(rest)
    header = "\n".join(["ply", "format binary_little_endian 1.0", f"element vertex {len(table)}",
                        *(f"property float {name}" for name in names), "end_header"]) + "\n"
    return write_atomic(path, header.encode("ascii") + np.ascontiguousarray(table, dtype="<f4").tobytes())


def read_splat_ply(path: str | Path) -> dict[str, torch.Tensor]:
    """A splat PLY as written by :func:`write_splat_ply` (binary little-endian float32 vertices, Inria's property
    names) -> means, quats, log_scales, opacity_logits, sh0 (N, 1, 3), shN (N, K - 1, 3). ValueError naming the file
    for anything else."""
    data = Path(path).read_bytes()
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise ValueError(f"{path} is not a PLY file (no 'ply' ... 'end_header' header)")
    lines = data[:end].decode("ascii", errors="replace").splitlines()
    if "format binary_little_endian 1.0" not in lines:
        raise ValueError(f"{path}: expected a binary little-endian PLY")
    count = next((int(line.split()[2]) for line in lines if line.startswith("element vertex")), None)
    names = [line.split()[2] for line in lines if line.startswith("property float")]
    if count is None or not {"x", "f_dc_0", "opacity", "scale_0", "rot_0"} <= set(names):
        raise ValueError(f"{path}: expected a vertex element with Inria's splat properties (x y z f_dc_* opacity scale_* rot_*)")
    table = torch.from_numpy(np.frombuffer(data[end + len(b"end_header\n"):], dtype="<f4", count=count * len(names)).reshape(count, len(names)).copy())
    column = {name: index for index, name in enumerate(names)}

    def take(*keys: str) -> torch.Tensor:
        return table[:, [column[key] for key in keys]]

    rest = sum(name.startswith("f_rest_") for name in names) // 3
    return {
        "means": take("x", "y", "z"), "quats": take("rot_0", "rot_1", "rot_2", "rot_3"),
        "log_scales": take("scale_0", "scale_1", "scale_2"), "opacity_logits": take("opacity")[:, 0],
        "sh0": take("f_dc_0", "f_dc_1", "f_dc_2")[:, None, :],
        "shN": take(*(f"f_rest_{i}" for i in range(3 * rest))).reshape(count, 3, rest).transpose(1, 2),
    }
