"""Chamfer distance between an exported mesh and the procedural scene's true surfaces, JSON out.

    .venv/bin/python scripts/mesh_chamfer.py outputs/nerf_procedural/<time>/export/<time>/mesh.ply [--out FILE.json]

Mesh to surface: the mean absolute signed distance of the vertices (exact). Surface to mesh: the mean
distance from the surface points the procedural test views see (their true depth) to the nearest vertex.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from nerf_lightning.data.formats import load_procedural
from nerf_lightning.data.formats.procedural import surface_distance
from nerf_lightning.outputs.mesh import read_mesh
from nerf_lightning.metrics import chamfer_distance


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("mesh", type=Path)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    vertices = torch.from_numpy(np.asarray(read_mesh(args.mesh).vertices)).double()
    surface = load_procedural().splits["test"].surface_points()
    result = {"mesh": str(args.mesh), "vertices": len(vertices), **chamfer_distance(vertices, surface, surface_distance(vertices))}
    text = json.dumps(result, indent=2)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
