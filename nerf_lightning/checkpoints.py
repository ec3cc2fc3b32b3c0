"""Checkpoints: written whole or not at all, never with non-finite weights, and enough to rebuild a trained model."""

from __future__ import annotations

import io
import logging
from pathlib import Path
from typing import Any

import lightning as L
import torch
from hydra.utils import instantiate
from lightning.pytorch.plugins.io import TorchCheckpointIO
from omegaconf import OmegaConf

from nerf_lightning import __version__
from nerf_lightning.config import run_dir_of  # noqa: F401 (its home was here; imported from here by earlier code)
from nerf_lightning.devices import resolve_device
from nerf_lightning.io import write_atomic

log = logging.getLogger(__name__)


class AtomicCheckpointIO(TorchCheckpointIO):
    """Saves a checkpoint through a temporary file in the same folder and a rename, so that a crash or ``kill -9``
    while saving leaves the previous checkpoint whole (Lightning's own writer may copy across file systems), and
    never writes one whose weights are not finite: after a NaN or inf the last good checkpoint stays as it was."""

    def save_checkpoint(self, checkpoint: dict[str, Any], path: str | Path, storage_options: Any | None = None) -> None:
        state = checkpoint.get("state_dict", {})
        bad = next((name for name, value in state.items() if torch.is_tensor(value) and value.is_floating_point() and not bool(torch.isfinite(value).all())), None)
        if bad is not None:
            log.warning("not writing %s: its weights are not finite (%s); the last checkpoint written stays as it was", path, bad)
            return
        buffer = io.BytesIO()
        torch.save(checkpoint, buffer)
        write_atomic(path, buffer.getvalue())


# What a checkpoint's layout is, kept in its "nerf_lightning" entry. 1: nerf-lightning 0.1; 2: 0.2, where samplers and
# the scene space became objects (a radiance field's weights moved under model.sampler, its bounds into "scene_space").
CHECKPOINT_FORMAT = 2
LAST_COMMIT_OF_FORMAT_1 = "5bab3ec"


def read_checkpoint(ckpt_path: str | Path, map_location: str | torch.device = "cpu") -> dict[str, Any]:
    """A nerf-train checkpoint, checked: FileNotFoundError for a missing file; ValueError for a file that is not a
    nerf-train checkpoint, or one whose layout this version cannot load (naming the version that wrote it)."""
    path = Path(ckpt_path).expanduser()
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {path}")
    try:
        checkpoint = torch.load(path, map_location=map_location, weights_only=False, mmap=True)
    except Exception as error:
        raise ValueError(f"could not read checkpoint {path}: {error}") from error
    info = checkpoint.get("nerf_lightning") if isinstance(checkpoint, dict) else None
    if not info or "config" not in info:
        raise ValueError(f"{path} is not a nerf-train checkpoint: it has no 'nerf_lightning' entry with the run's config")
    layout = int(info.get("format", 1))
    if layout > CHECKPOINT_FORMAT:
        raise ValueError(f"{path} was written by nerf-lightning {info.get('version', 'newer')} (checkpoint format {layout}); this is "
                         f"nerf-lightning {__version__} (format {CHECKPOINT_FORMAT}): upgrade it to load the checkpoint")
    if layout < 2 and info.get("kind") == "radiance_field":
        raise ValueError(f"{path} was written by nerf-lightning 0.1 (checkpoint format 1), whose radiance fields this version "
                         f"({__version__}) cannot load: samplers and the scene space changed in 0.2 (see the README). Train it again, "
                         f"or use the 0.1 code for it (git checkout {LAST_COMMIT_OF_FORMAT_1})")
    return checkpoint


def load_model(
    ckpt_path: str | Path, device: str | torch.device = "cpu", kind: str | None = None, command: str = "this command"
) -> tuple[L.LightningModule, dict[str, Any]]:
    """Load a nerf-train checkpoint (:func:`read_checkpoint`) on the CPU, then move it to ``device`` (``auto``, ``cpu``,
    ``cuda``, ``mps``: :func:`~nerf_lightning.devices.resolve_device`): the model in eval mode and the run's resolved config.

    Raises ValueError, besides :func:`read_checkpoint`'s, when ``kind`` is given and the checkpoint holds another kind
    of model than ``command`` works with, or ``device`` is not one this machine has.
    """
    path = Path(ckpt_path).expanduser()
    target = resolve_device(device)
    checkpoint = read_checkpoint(path, "cpu")
    info = checkpoint["nerf_lightning"]
    if kind is not None and info.get("kind") != kind:
        raise ValueError(f"{path} holds a model of kind '{info.get('kind')}'; {command} works with {kind} checkpoints")
    config = info["config"]
    model = instantiate(OmegaConf.create(config["model"]))
    model.on_load_checkpoint(checkpoint)
    model.load_state_dict(checkpoint["state_dict"])
    model.eval()
    model.to(target)
    return model, {"kind": info["kind"], "config": config, "global_step": checkpoint.get("global_step")}


def load_run_data(config: dict[str, Any]):
    """The run's DataModule rebuilt from its resolved config and set up (its scene loaded)."""
    datamodule = instantiate(OmegaConf.create(config["data"]))
    datamodule.setup()
    return datamodule
