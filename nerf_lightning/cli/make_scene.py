"""nerf-make-scene <dir>: render the built-in procedural scene into <dir> in the Blender layout."""

from __future__ import annotations

import argparse

from nerf_lightning.cli.keys import check_make_scene_keys


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="nerf-make-scene", description=__doc__.splitlines()[0])
    parser.add_argument("directory", help="where to write transforms_{train,val,test}.json, the PNGs and depth_<split>.npy")
    parser.add_argument("--views", type=int, default=100, help="cameras on the sphere (80%% train, 10%% val, 10%% test)")
    parser.add_argument("--size", type=int, default=100, help="image side in pixels")
    args = parser.parse_args(argv)
    try:
        check_make_scene_keys(args)
    except ValueError as error:
        parser.exit(2, f"nerf-make-scene: error: {error}\n")
    # imported here, not at the top: a wrong option is answered before torch loads (seconds)
    from nerf_lightning.data.formats.procedural import make_procedural_scene

    root = make_procedural_scene(args.directory, n_views=args.views, size=args.size)
    print(f"wrote the procedural scene ({args.views} views, {args.size}x{args.size}) to {root}")


if __name__ == "__main__":
    main()
