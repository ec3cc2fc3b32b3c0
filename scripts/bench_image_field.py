"""Image field: the Lightning module against a plain PyTorch loop of the same MLP, same image, one process.

    .venv/bin/python scripts/bench_image_field.py [--image PATH] [--downscale 4] [--steps 1000] [--out FILE.json]

Both fit the same ImageField (L = 10, width 256, 3 hidden layers) with Adam lr 1e-2 and 10 000 random pixels
a step, from the same initial weights and on the same batches. The plain loop's time runs from its first step to the whole-image PSNR after the last one. The
Lightning time is the whole ``nerf_lightning.training.train`` call with the shipped ``experiment=image``
config: data set-up, the five whole-image snapshots, checkpoints, TensorBoard and metrics.json included
(the progress bar off, as in a log file). The two alternate ``--repeats`` times (default 2) and the ratio is
that of their fastest runs, so a passing hiccup of a shared machine does not decide it; every time is in
the JSON. Prints and writes JSON; exits 0 with "skipped" when the default image (a fox frame from
../shared/data) is absent.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

import kornia
import torch
import torch.nn.functional as F

from nerf_lightning.config import compose_config
from nerf_lightning.data import downscale, load_image, pixel_grid
from nerf_lightning.data.batches import batch_seed
from nerf_lightning.fields import ImageField
from nerf_lightning.training import train

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_IMAGE = ROOT.parent / "shared" / "data" / "nerfstudio" / "fox" / "images" / "0001.jpg"


def plain_loop(image: torch.Tensor, steps: int, batch_size: int, lr: float, seed: int) -> dict[str, float]:
    """The course's loop: random pixels, forward, MSE, backward, Adam step; PSNR of the whole image at the end.

    It draws the very batches the Lightning run draws (each step's generator seeded by the same rule), so the
    two differ only in the framework around the same arithmetic."""
    torch.manual_seed(seed)
    height, width = image.shape[:2]
    xy = pixel_grid(height, width).reshape(-1, 2)
    rgb = image.reshape(-1, 3)
    field = ImageField(num_frequencies=10, hidden_width=256, hidden_layers=3)
    optimizer = torch.optim.Adam(field.parameters(), lr=lr)
    generator = torch.Generator()
    started = time.perf_counter()
    for step in range(steps):
        generator.manual_seed(batch_seed(seed, 0, step))
        index = torch.randint(0, rgb.shape[0], (batch_size,), generator=generator)
        loss = F.mse_loss(field(xy[index]), rgb[index])
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
    with torch.no_grad():
        rendered = torch.cat([field(chunk) for chunk in xy.split(65_536)])
    psnr = float(kornia.metrics.psnr(rendered, rgb, max_val=1.0))
    return {"psnr": psnr, "seconds": time.perf_counter() - started}


def lightning_run(image_path: Path, factor: int, steps: int, seed: int) -> dict[str, float]:
    with tempfile.TemporaryDirectory() as run_dir:
        cfg = compose_config(
            [
                "experiment=image",
                f"data.path={image_path}",
                f"data.downscale={factor}",
                f"trainer.max_steps={steps}",
                f"seed={seed}",
                "trainer.enable_progress_bar=false",
                "trainer.enable_model_summary=false",
                f"paths.output_dir={run_dir}",
            ]
        )
        started = time.perf_counter()
        metrics = train(cfg)
        seconds = time.perf_counter() - started
    return {"psnr": metrics["val/psnr"], "seconds": seconds}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--image", type=Path, default=DEFAULT_IMAGE)
    parser.add_argument("--downscale", type=int, default=4)
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--out", type=Path, default=None, help="write the JSON result here too")
    args = parser.parse_args()

    if not args.image.is_file():
        print(json.dumps({"skipped": f"image not found: {args.image}"}))
        return
    image = downscale(load_image(args.image), args.downscale)
    plains, lightnings = [], []
    for _ in range(args.repeats):
        plains.append(plain_loop(image, args.steps, batch_size=10_000, lr=1e-2, seed=args.seed))
        lightnings.append(lightning_run(args.image, args.downscale, args.steps, args.seed))
    plain = min(plains, key=lambda run: run["seconds"])
    lightning = min(lightnings, key=lambda run: run["seconds"])
    result = {
        "image": str(args.image),
        "size_hw": list(image.shape[:2]),
        "steps": args.steps,
        "seed": args.seed,
        "plain_seconds": round(plain["seconds"], 2),
        "plain_psnr": round(plain["psnr"], 3),
        "lightning_seconds": round(lightning["seconds"], 2),
        "lightning_psnr": round(lightning["psnr"], 3),
        "time_ratio": round(lightning["seconds"] / plain["seconds"], 3),
        "plain_seconds_all": [round(run["seconds"], 2) for run in plains],
        "lightning_seconds_all": [round(run["seconds"], 2) for run in lightnings],
        "lightning_psnr_all": [round(run["psnr"], 3) for run in lightnings],
        "psnr_difference": round(lightning["psnr"] - plain["psnr"], 3),
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "machine": f"{platform.processor() or platform.machine()}, {torch.get_num_threads()} threads, python {sys.version.split()[0]}",
    }
    text = json.dumps(result, indent=2)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
