"""Write the procedural scene as a phone would have captured it, to measure the depth loss on (docs/guides/real-captures.md):

    python scripts/phone_depth_capture.py /tmp/phone

writes ``/tmp/phone/phone/transforms.json`` (every view; each depth map a 16-bit PNG of millimetres a quarter of the
photo's side, the mean of its 4x4 block, with 2% noise: a LiDAR's) and ``/tmp/phone/truth/transforms.json`` (the same
views, each depth map the true one as a ``.npy`` at the photo's size), whose held-out views ``nerf-eval root=`` scores
depth error against. The splits are the procedural scene's (named in the json)."""

from __future__ import annotations

import argparse
from pathlib import Path

from nerf_lightning.data.formats import load_procedural
from nerf_lightning.data.formats.depth_capture import write_depth_capture


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("root", type=Path)
    parser.add_argument("--shrink", type=int, default=4, help="the depth maps' side is the photo's divided by this")
    parser.add_argument("--noise", type=float, default=0.02, help="the depth maps' relative noise (standard deviation)")
    arguments = parser.parse_args()
    scene = load_procedural()
    phone = write_depth_capture(scene, arguments.root / "phone", suffix=".png", shrink=arguments.shrink, noise=arguments.noise)
    truth = write_depth_capture(scene, arguments.root / "truth", suffix=".npy")
    print(f"{phone}\n{truth}")


if __name__ == "__main__":
    main()
