"""Seconds of the splat rasterisers alone, forward and forward + backward, on one view's footprints saved by
``scripts/profile_splat_step.py --save-view FILE`` (a view of a run in progress).

    .venv/bin/python scripts/bench_rasterize.py FILE [--rasterizers tiles pairs] [--repeats 10] [--warmup 2] [--out FILE.json]

Prints the median seconds of each and the (footprint, pixel) pairs the view has (the pairs rasteriser's count).
"""

from __future__ import annotations

import argparse
import sys

import torch

from nerf_lightning.bench.micro import add_common_arguments, finish, start_result, time_call
from nerf_lightning.splats.projection import Projection
from nerf_lightning.splats.draw import RASTERIZERS
from nerf_lightning.splats.rasterize_core import pixel_boxes
from nerf_lightning.splats.rasterize_pairs import drawn_pairs, footprint_table


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog="\n".join(__doc__.splitlines()[1:]))
    parser.add_argument("view", help="a file written by profile_splat_step.py --save-view")
    parser.add_argument("--rasterizers", nargs="+", default=["tiles", "pairs"])
    add_common_arguments(parser, warmup=2, repeats=10, device=False)
    args = parser.parse_args()
    saved = torch.load(args.view, weights_only=False)
    height, width, background = saved["height"], saved["width"], saved["background"]
    with torch.no_grad():
        base = Projection(*saved["projection"])
        pairs = len(drawn_pairs(footprint_table(base), pixel_boxes(base, height, width), 0, height, width)[0])
    result = {**start_result("cpu"), "benchmark": "rasterize", "view": args.view, "height": height, "width": width,
              "footprints": len(base.ids), "pairs": pairs, "rasterizers": {}}
    for name in args.rasterizers:
        drawer = RASTERIZERS[name]().for_device("cpu")

        def forward() -> None:
            with torch.no_grad():
                drawer.rasterize(base, saved["colours"], height, width, background)

        def forward_backward() -> None:
            projection = Projection(base.ids, *(value.clone().requires_grad_() for value in base[1:]))
            colours = saved["colours"].clone().requires_grad_()
            out = drawer.rasterize(projection, colours, height, width, background)
            (out["rgb"].sum() + out["depth"].sum()).backward()

        result["rasterizers"][name] = {"forward": time_call(forward, args.repeats, args.warmup),
                                       "forward_backward": time_call(forward_backward, args.repeats, args.warmup)}
        timings = result["rasterizers"][name]
        print(f"{name}: forward {1000 * timings['forward']['median_s']:.1f} ms, forward + backward "
              f"{1000 * timings['forward_backward']['median_s']:.1f} ms ({len(base.ids)} footprints, {pairs} pairs, "
              f"{height}x{width})", file=sys.stderr)
    finish(result, args.out)


if __name__ == "__main__":
    main()
