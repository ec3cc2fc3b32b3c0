"""Checkpoints: written whole or not at all, never with non-finite weights, and enough to rebuild a trained model."""

from __future__ import annotations

import io
import logging
import pickle
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import lightning as L
import torch
from hydra.utils import instantiate
from lightning.pytorch.plugins.io import TorchCheckpointIO
from omegaconf import OmegaConf

from nerf_lightning import __version__
from nerf_lightning.config import run_dir_of  # noqa: F401 (its home was here; imported from here by earlier code)
from nerf_lightning.config import upgraded_model_config
from nerf_lightning.devices import enable_tf32, resolve_device
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


# What a checkpoint may hold beyond torch's own weights_only allow-list (tensors and their storages, dtypes, devices,
# OrderedDict and Python's plain types): nothing. Every preset's checkpoints, trained a few steps with the default
# callbacks (best.ckpt, last.ckpt, validation history), hold only collections.OrderedDict, torch._utils._rebuild_tensor_v2
# and torch.{Float,Byte,Bool}Storage, all in torch's list; Lightning's own entries (loops, optimiser and scheduler
# states, callback states, ModelCheckpoint's scores) are tensors, numbers, strings, lists and dicts. A class this
# project starts storing in checkpoints goes here, or the files that hold it are refused without trust_checkpoint=true.
CHECKPOINT_GLOBALS: tuple[Any, ...] = ()
TRUST_HINT = "if you trust whoever made the file, pass trust_checkpoint=true"


class UntrustedCheckpointError(ValueError):
    """A checkpoint that needs more than :func:`allowed_globals` to load, opened without ``trust``."""


def allowed_globals() -> list[Any]:
    """The classes and functions a nerf-train checkpoint may hold beyond torch's weights_only defaults
    (:data:`CHECKPOINT_GLOBALS`), for ``torch.serialization.safe_globals``."""
    return list(CHECKPOINT_GLOBALS)


@contextmanager
def checkpoint_globals() -> Iterator[None]:
    """Torch's weights_only loads in the block also take :func:`allowed_globals` (and nothing more once it ends).

    For Lightning's own reading of a checkpoint when a run resumes, which reads the file again after
    :func:`read_checkpoint` checked it::

        with checkpoint_globals():
            trainer.fit(model, datamodule=datamodule, ckpt_path=ckpt_path, weights_only=not trust)
    """
    with torch.serialization.safe_globals(allowed_globals()):
        yield


def _needed_globals(path: Path) -> list[str]:
    """The globals (``module.name``) the pickle in ``path`` names beyond torch's list and :func:`allowed_globals`,
    found by reading it, not running it; [] where it cannot be read that way."""
    try:
        return sorted(torch.serialization.get_unsafe_globals_in_checkpoint(path))
    except Exception:  # noqa: BLE001 (only a better message depends on it: the load has failed already)
        return []


def _load_restricted(path: Path, map_location: str | torch.device) -> dict[str, Any]:
    """``torch.load`` with weights_only and :func:`allowed_globals`; UntrustedCheckpointError naming what else the
    file needs, raised before anything in it runs."""
    with checkpoint_globals():
        try:
            return torch.load(path, map_location=map_location, weights_only=True, mmap=True)
        except pickle.UnpicklingError as error:  # weights_only met something outside the allow-list
            needed = _needed_globals(path)
            if needed:
                names = ", ".join(f"`{name}`" for name in needed)
                raise UntrustedCheckpointError(f"{path} needs {names}, which nerf-lightning checkpoints never hold; {TRUST_HINT}") from None
            lines = [line.strip() for line in str(error).splitlines() if line.strip()]
            reason = next((line for line in lines if "GLOBAL" in line or "Unsupported" in line or "WeightsUnpickler" in line), lines[-1] if lines else "")
            raise UntrustedCheckpointError(f"{path} holds something nerf-lightning checkpoints never hold ({reason}); {TRUST_HINT}") from None


def what_file_is(path: Path) -> str:
    """A few words on what a file that is not a checkpoint holds: empty, text (with its first line) or other bytes."""
    head = path.read_bytes()[:200]
    if not head:
        return "empty"
    try:
        first = head.decode("utf-8").strip().splitlines()
    except UnicodeDecodeError:
        return f"{path.stat().st_size} bytes of something else"
    return f"text ({first[0][:60]!r} ...)" if first else "blank text"


def read_checkpoint(ckpt_path: str | Path, map_location: str | torch.device = "cpu", trust: bool = False) -> dict[str, Any]:
    """A nerf-train checkpoint, checked: FileNotFoundError for a missing file; ValueError for a file that is not a
    checkpoint at all (text, an image: said as such, not as torch's loader's complaint), one that is not a nerf-train
    checkpoint, or one whose layout this version cannot load (naming the version that wrote it).

    Unpickling can run any code a file names, so unless ``trust`` the file is read with torch's weights_only and
    :func:`allowed_globals`: a file that needs anything more is refused (ValueError naming what it needs) before any of
    it runs. ``trust=True`` (``trust_checkpoint=true``) reads it whole, running whatever it holds.
    """
    path = Path(ckpt_path).expanduser()
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {path}")
    if not zipfile.is_zipfile(path):  # torch.save's archive, as every checkpoint nerf-train writes is
        raise ValueError(f"{path} is not a checkpoint: nerf-train writes its checkpoints as torch.save archives "
                         f"(<run>/checkpoints/last.ckpt, <run>/marks/minute_<m>.ckpt), and this file is {what_file_is(path)}")
    try:
        if trust:
            checkpoint = torch.load(path, map_location=map_location, weights_only=False, mmap=True)
        else:
            checkpoint = _load_restricted(path, map_location)
    except UntrustedCheckpointError:
        raise
    except Exception as error:
        first_line = next((line.strip() for line in str(error).splitlines() if line.strip()), type(error).__name__)
        raise ValueError(f"could not read checkpoint {path}: {first_line}") from error
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


def load_model(ckpt_path: str | Path, device: str | torch.device = "cpu", trust: bool = False) -> tuple[L.LightningModule, dict[str, Any]]:
    """Load a nerf-train checkpoint (:func:`read_checkpoint`) on the CPU, then move it to ``device`` (``auto``, ``cpu``,
    ``cuda``, ``mps``: :func:`~nerf_lightning.devices.resolve_device`): the model in eval mode and the run's resolved config.

    What a command needs of the model it asks by protocol (:mod:`nerf_lightning.models.contract`), not here by a kind.
    Raises ValueError, besides :func:`read_checkpoint`'s, when ``device`` is not one this machine has. ``trust``: as
    :func:`read_checkpoint`'s (``trust_checkpoint=true``: the file may run code).
    """
    path = Path(ckpt_path).expanduser()
    target = resolve_device(device)
    # the matrix products at the precision training validated with (TF32 on CUDA), so that nerf-eval gives the
    # numbers the run logged: in full float32 a GPU's eval of a NeRF differed from its validation by 0.01 to 0.02 dB
    enable_tf32()
    checkpoint = read_checkpoint(path, "cpu", trust=trust)
    info = checkpoint["nerf_lightning"]
    config = info["config"]
    model = instantiate(OmegaConf.create(upgraded_model_config(config["model"])))
    model.on_load_checkpoint(checkpoint)
    model.load_state_dict(checkpoint["state_dict"])
    model.eval()
    device_for = getattr(model, "device_for", None)  # a model may draw elsewhere than auto chose (splats: not an Apple GPU)
    if device_for is not None:
        target = device_for(target, asked=str(device).strip().lower() not in ("auto", "none"))
    model.to(target)
    return model, {"kind": info["kind"], "config": config, "global_step": checkpoint.get("global_step")}


def load_run_data(config: dict[str, Any], model: Any = None):
    """The run's DataModule rebuilt from its resolved config and set up (its scene loaded). With the run's ``model``,
    the scene must be where the model learnt it: its similarity from the capture's coordinates (the loader's
    normalisation, and an object's box fitted to its masks, data.object_box) as the checkpoint keeps it; ValueError
    in one line otherwise (the capture's poses or masks changed since training)."""
    datamodule = instantiate(OmegaConf.create(config["data"]))
    datamodule.setup()
    trained = getattr(getattr(model, "space", None), "world_from_capture", None)
    loaded = getattr(getattr(datamodule, "space", None), "world_from_capture", None)
    if trained is not None and loaded is not None and not torch.allclose(trained.detach().cpu().float(), loaded.cpu().float(), atol=1e-4, rtol=1e-4):
        scene = config["data"].get("root") or "the run's scene"
        raise ValueError(f"{scene} no longer loads where the checkpoint learnt it: its "
                         "normalisation from the capture's coordinates differs (poses or masks changed since training); "
                         "train again on the capture as it is")
    return datamodule
