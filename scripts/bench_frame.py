"""Seconds to render one held-out frame (``model.render_view``, as nerf-eval and nerf-render do) of a checkpoint, or
of a freshly built preset model.

    .venv/bin/python scripts/bench_frame.py --ckpt RUN/checkpoints/last.ckpt [--view 0] [--scale 1.0] [--chunk-size N]
        [--repeats 3] [--warmup 1] [--device auto] [--seed 0] [--out FILE.json]
    .venv/bin/python scripts/bench_frame.py [--preset fast_blender] [--root DIR] [...] [-- HYDRA OVERRIDES]

With ``--ckpt``: its model (:func:`nerf_lightning.checkpoints.load_model`) and held-out view ``--view`` of its run's
scene (the test split, else val, as nerf-eval; ``--root`` where the scene has moved). Without: the model of
``experiment=<--preset>`` as built for training, untrained (an occupancy grid still all occupied: every cell marched,
no ray stopping early, so a frame costs more than a trained one's), on that preset's scene (``--root``, else its scene
in ../shared/data; overrides after ``--``). ``--scale`` renders the view that many times as many pixels a side.
``--warmup`` frames first (on a CPU the first compiles the hash-grid encodings: ``warmup_s``), then ``--repeats``
frames, each waited for on a GPU. Prints the JSON (and writes it with ``--out``); exits 0 with ``{"skipped": ...}``
when the checkpoint or scene is missing.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
from hydra.utils import instantiate

from nerf_lightning.bench.micro import (
    add_common_arguments, compose_preset, finish, parse_device, require_path, seed_everything, start_result, time_call,
)
from nerf_lightning.checkpoints import load_model, load_run_data


def checkpoint_model(ckpt: Path, root: Path | None, device: torch.device):
    """The checkpoint's model on ``device``, its run's held-out views and a description of it."""
    model, info = load_model(ckpt, device)
    config = info["config"]
    if root is not None:
        config = {**config, "data": {**config["data"], "root": str(require_path(root).expanduser().resolve())}}
    elif config["data"].get("root"):
        require_path(Path(config["data"]["root"]), "the run's scene (give --root where it has moved)")
    views = load_run_data(config).scene.held_out("test")
    return model, views, {"checkpoint": str(ckpt.resolve()), "global_step": info["global_step"], "root": config["data"].get("root")}


def preset_model(preset: str, root: Path | None, overrides: list[str], device: torch.device):
    """``experiment=<preset>``'s model as ``nerf-train`` builds it, untrained, in its scene's space; its held-out views."""
    cfg, root = compose_preset(preset, overrides, root)
    datamodule = instantiate(cfg.data)
    datamodule.setup()
    model = instantiate(cfg.model)
    # what fitting does first (RadianceFieldModule.setup and on_fit_start): per-view tables sized, the scene's space
    for per_view in (getattr(getattr(model, "field", None), "appearance", None), getattr(model, "camera_refinement", None)):
        if per_view is not None:
            per_view.resize(len(datamodule.scene.train))
    model.to(device)
    if hasattr(model, "use_space"):
        model.use_space(datamodule.space)
    model.eval()
    return model, datamodule.scene.held_out("test"), {"preset": preset, "root": None if root is None else str(root),
                                                      "overrides": overrides, "trained": False}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog="\n".join(__doc__.splitlines()[1:]))
    parser.add_argument("--ckpt", type=Path, default=None, help="a nerf-train checkpoint (default: an untrained --preset model)")
    parser.add_argument("--preset", default="fast_blender", help="without --ckpt: the experiment preset (default fast_blender)")
    parser.add_argument("--root", type=Path, default=None, help="the scene folder (data.root; default: the run's, or the preset's in ../shared/data)")
    parser.add_argument("--view", type=int, default=0, help="which held-out view (default 0)")
    parser.add_argument("--scale", type=float, default=1.0, help="render this many times as many pixels a side (default 1)")
    parser.add_argument("--chunk-size", type=int, default=None, help="rays rendered at once (default: the model's chunk_size)")
    add_common_arguments(parser, warmup=1, repeats=3)
    parser.add_argument("overrides", nargs="*", help="without --ckpt: more Hydra overrides of the preset, after --")
    args = parser.parse_args()
    device = parse_device(args.device)
    seed_everything(args.seed)
    if args.ckpt is not None:
        if args.overrides:
            raise SystemExit("Hydra overrides change a preset's model: with --ckpt there is none to change")
        require_path(args.ckpt, "checkpoint")
        model, views, described = checkpoint_model(args.ckpt, args.root, device)
    else:
        model, views, described = preset_model(args.preset, args.root, args.overrides, device)
    if not hasattr(model, "render_view"):
        raise SystemExit(f"{type(model).__name__} renders no camera (render_view): a radiance-field preset or checkpoint is needed")
    if not 0 <= args.view < len(views):
        raise SystemExit(f"--view {args.view}: the scene has {len(views)} held-out views")
    if args.chunk_size is not None:
        model.chunk_size = args.chunk_size
    rendered = views.scaled(args.scale)
    K, c2w, height, width = rendered.K[args.view], rendered.c2w[args.view], rendered.height, rendered.width

    frame = time_call(lambda: model.render_view(K, c2w, height, width), repeats=args.repeats, warmup=args.warmup, device=device)
    encodings = [module for module in model.modules() if hasattr(module, "compile_evaluation")]
    result = {
        **start_result(device), "benchmark": "frame", **described, "device": str(device), "model": type(model).__name__,
        "view": views.names[args.view] if views.names else args.view, "height": height, "width": width, "scale": args.scale,
        "chunk_size": getattr(model, "chunk_size", None),
        "compiled_encodings": device.type == "cpu" and any(encoding.compile_evaluation for encoding in encodings),
        "seed": args.seed, "rays_per_second": height * width / frame["median_s"], "frame": frame,
    }
    finish(result, args.out)
    print(f"{width}x{height}: {frame['median_s']:.3f} s a frame (median of {args.repeats}), {result['rays_per_second']:,.0f} rays/s "
          f"on {device}", file=sys.stderr)


if __name__ == "__main__":
    main()
