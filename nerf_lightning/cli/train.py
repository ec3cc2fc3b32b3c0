"""nerf-train: compose a run's config with Hydra and train it (:func:`nerf_lightning.training.train`)."""

from __future__ import annotations

import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig

from nerf_lightning.cli.keys import check_train_keys
from nerf_lightning.config import renamed_key_message
from nerf_lightning.errors import fail, report_errors


@hydra.main(version_base="1.3", config_path="pkg://nerf_lightning.conf", config_name="train")
@report_errors("nerf-train")
def run(cfg: DictConfig) -> float | None:
    check_train_keys(cfg)
    # imported here, not at the top: a wrong key is answered before torch and Lightning load (seconds)
    from nerf_lightning.training import train

    metrics = train(cfg)
    folder = Path(cfg.paths.output_dir)
    shown = ", ".join(f"{key} {metrics[key]:.2f}" for key in ("val/psnr", "val/ssim") if key in metrics)
    print(f"{folder}: {metrics['step']} steps in {metrics['wall_seconds']:.0f} s{', ' + shown if shown else ''}; "
          f"next: nerf-render ckpt_path={folder / 'checkpoints' / 'last.ckpt'}")
    # a sweeper optimises the returned value
    return metrics.get("val/psnr")


def main() -> None:
    message = renamed_key_message(sys.argv[1:])
    if message:
        fail("nerf-train", message)
    run()


if __name__ == "__main__":
    main()
