"""nerf-eval: render every held-out view of a trained model's scene (or of a second capture file, ``root=``) and
write eval.json with PSNR, SSIM, LPIPS (where its weights can be had) and depth error (:mod:`nerf_lightning.outputs.evaluation`)."""

from __future__ import annotations

import hydra
from omegaconf import DictConfig

import nerf_lightning.config  # noqa: F401 (registers ${run_dir_of:...}, which the config's output_dir uses)
from nerf_lightning.cli.keys import check_eval_keys
from nerf_lightning.errors import ensure_writable, report_errors


def evaluate(cfg: DictConfig) -> dict:
    check_eval_keys(cfg)
    # imported here, not at the top: a wrong key is answered before torch and Lightning load (seconds)
    from nerf_lightning.outputs.evaluation import evaluate_checkpoint

    ensure_writable(cfg.output_dir, "output_dir")
    return evaluate_checkpoint(cfg.ckpt_path, cfg.output_dir, cfg.split, cfg.get("root"), cfg.max_views, cfg.device, trust=cfg.trust_checkpoint,
                               lpips=str(cfg.eval.lpips), lpips_weights=cfg.eval.get("lpips_weights"))


@hydra.main(version_base="1.3", config_path="pkg://nerf_lightning.conf", config_name="eval")
@report_errors("nerf-eval")
def main(cfg: DictConfig) -> None:
    evaluate(cfg)


if __name__ == "__main__":
    main()
