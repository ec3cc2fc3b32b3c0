"""Seconds of the hash-grid encoding (nerf_lightning.fields.hash_grid.HashGridEncoding) on M points, with a preset's
settings: its forward without gradients, its forward + backward, and the same two of the plain reference
interpolation for comparison.

    .venv/bin/python scripts/bench_hash_encoding.py [--preset fast_blender] [--encoding model.field.encoding]
        [--points 65536] [--repeats 10] [--warmup 2] [--device auto] [--seed 0] [--out FILE.json] [-- HYDRA OVERRIDES]
    .venv/bin/python scripts/bench_hash_encoding.py --preset nerfacto_forward_cpu --encoding model.sampler.proposal_fields.0.encoding

``--encoding`` is where the preset's config has the encoding (a proposal network's:
``model.sampler.proposal_fields.<i>.encoding``); overrides after ``--`` change its settings
(``model.field.encoding.compile_evaluation=false``: the forward without gradients in plain PyTorch on a CPU, where it
is otherwise compiled, its first call in ``warmup_s``). ``--points`` random points in the unit cube, fixed seed; the
forward + backward sends a fixed random gradient back into the table. Medians and spread of ``--repeats`` calls after
``--warmup``, each waited for on a GPU. Prints the JSON (and writes it with ``--out``).
"""

from __future__ import annotations

import argparse
import sys

import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

from nerf_lightning.bench.micro import add_common_arguments, compose_preset, finish, parse_device, seed_everything, start_result, time_call
from nerf_lightning.fields.hash_grid import HashGridEncoding

# ---- THE REFERENCE INTERPOLATION: the one place its name is imported and called ---------------------------------------
from nerf_lightning.fields.hash_grid import encode_reference  # noqa: E402


def reference_forward(encoding: HashGridEncoding, points: torch.Tensor) -> torch.Tensor:
    """The plain reference interpolation of ``encoding``'s table at (M, 3) ``points`` in [0, 1] -> (M, L * F)."""
    return encode_reference(points.clamp(0.0, 1.0), *encoding.reference_inputs())
# ----------------------------------------------------------------------------------------------------------------------


def timings(forward, points: torch.Tensor, table: torch.Tensor, upstream: torch.Tensor, args, device) -> dict:
    """``forward(points)`` without gradients and forward + backward (``upstream`` into ``table``'s gradient), timed."""

    def no_grad() -> None:
        with torch.no_grad():
            forward(points)

    def forward_backward() -> None:
        table.grad = None
        forward(points).backward(upstream)

    return {"forward": time_call(no_grad, args.repeats, args.warmup, device),
            "forward_backward": time_call(forward_backward, args.repeats, args.warmup, device)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog="\n".join(__doc__.splitlines()[1:]))
    parser.add_argument("--preset", default="fast_blender", help="the experiment preset whose encoding settings to use (default fast_blender)")
    parser.add_argument("--encoding", default="model.field.encoding", help="the encoding's key in the preset's config (default model.field.encoding)")
    parser.add_argument("--points", type=int, default=65536, help="M, points a call (default 65536: 2048 rays of 32 samples)")
    add_common_arguments(parser, warmup=2, repeats=10)
    parser.add_argument("overrides", nargs="*", help="more Hydra overrides, after --")
    args = parser.parse_args()
    device = parse_device(args.device)
    seed_everything(args.seed)
    cfg, _ = compose_preset(args.preset, args.overrides, need_data=False)
    settings = OmegaConf.select(cfg, args.encoding)
    if settings is None or not str(settings.get("_target_", "")).endswith("HashGridEncoding"):
        raise SystemExit(f"{args.encoding} of experiment={args.preset} is not a HashGridEncoding (it is {settings})")
    encoding = instantiate(settings).to(device).eval()  # eval: as renders run it (training differs only in gradients)
    generator = torch.Generator().manual_seed(args.seed)
    points = torch.rand(args.points, 3, generator=generator).to(device)
    upstream = torch.randn(args.points, encoding.out_dim, generator=generator).to(device)

    encoding_times = timings(encoding, points, encoding.table, upstream, args, device)
    reference = timings(lambda p: reference_forward(encoding, p), points, encoding.table, upstream, args, device)
    with torch.no_grad():
        reference["max_abs_difference"] = float((reference_forward(encoding, points) - encoding(points)).abs().max())
    for key in ("forward", "forward_backward"):  # > 1: the encoding is that many times faster than the reference
        reference[f"{key}_ratio_to_encoding"] = reference[key]["median_s"] / encoding_times[key]["median_s"]
    # the forward without gradients is compiled on a CPU where compile_evaluation is on (the encoding's documented rule)
    compiled = device.type == "cpu" and bool(encoding.compile_evaluation) and args.points > 1
    result = {
        **start_result(device), "benchmark": "hash_encoding", "preset": args.preset, "encoding_key": args.encoding,
        "overrides": args.overrides, "settings": {key: value for key, value in OmegaConf.to_container(settings).items() if key != "_target_"},
        "device": str(device), "points": args.points, "seed": args.seed, "out_dim": encoding.out_dim,
        "table_rows": encoding.table.shape[0], "forward_compiled": compiled,
        "points_per_second": {key: args.points / value["median_s"] for key, value in encoding_times.items()},
        **encoding_times, "reference": reference,
    }
    finish(result, args.out)
    print(f"{args.encoding}: forward {1000 * encoding_times['forward']['median_s']:.2f} ms{' (compiled)' if compiled else ''}, "
          f"forward + backward {1000 * encoding_times['forward_backward']['median_s']:.2f} ms on {args.points} points, {device}",
          file=sys.stderr)


if __name__ == "__main__":
    main()
