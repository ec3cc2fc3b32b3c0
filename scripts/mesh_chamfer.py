"""Chamfer distance between an exported mesh and the procedural scene's true surfaces, JSON out.

    .venv/bin/python scripts/mesh_chamfer.py outputs/nerf_procedural/<time>/export/<time>/mesh.ply [--out FILE.json]

Mesh to surface: the mean absolute signed distance of the vertices (exact). Surface to mesh: the mean
distance from the surface points the procedural test views see (their true depth) to the nearest vertex.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from nerf_lightning.data.formats import load_procedural
from nerf_lightning.data.formats.surface import chamfer_to_surface
from nerf_lightning.export import read_ply_vertices


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("mesh", type=Path)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    vertices, _ = read_ply_vertices(args.mesh)
    result = {"mesh": str(args.mesh), "vertices": len(vertices), **chamfer_to_surface(vertices, load_procedural().splits["test"])}
    text = json.dumps(result, indent=2)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
