"""LPIPS (Zhang et al. 2018, "The Unreasonable Effectiveness of Deep Features as a Perceptual Metric"), version 0.1
with the AlexNet backbone: the variant nerfstudio, gsplat, nerfacc and the 3DGS paper report.

Both images go through AlexNet's five convolutions (after LPIPS's input scaling); at each ReLU the features are
normalised to unit length along the channels, their squared difference weighted channel by channel (the "linear
heads", 1x1 convolutions trained on human judgements), averaged over the pixels and summed over the five layers.
0 for equal images, larger for more different ones.

The backbone is written here (five convolutions) rather than taken from torchvision: torchvision would add a
dependency pinned to each torch release for one ``nn.Sequential``; its weights file loads into it as it is.

Where the weights come from (:func:`load_lpips`), the first that has them:

- the backbone: a file or folder the user names, with ``eval.lpips_weights`` or once for every command with the
  environment variable ``NERF_LIGHTNING_LPIPS`` (``nerf-bench --lpips-weights`` sets it for the ``nerf-eval`` it runs);
  else torchvision's ``alexnet-owt-7be5be79.pth`` in the torch hub cache (``torch.hub.get_dir()/checkpoints``,
  where ``torchvision.models.alexnet(weights=...)`` leaves it), or a download of it (``mode="download"``, the
  machine on the internet);
- the linear heads: ``alex.pth`` of LPIPS 0.1, from the file the user names, else from the copy torchmetrics ships
  (Lightning installs torchmetrics), else from the ``lpips`` package's.

A file the user names holds torchvision's keys (``features.<i>.weight`` and ``.bias``), LPIPS's
(``lin<k>.model.1.weight``), or both; a folder, its ``*.pth`` files, read in name order.
"""

from __future__ import annotations

import importlib.util
import logging
import os
from pathlib import Path

import torch
from torch import nn

from nerf_lightning.outputs.choices import LPIPS_MODES, LPIPS_WEIGHTS_VARIABLE

log = logging.getLogger(__name__)

ALEXNET_FILE = "alexnet-owt-7be5be79.pth"
ALEXNET_URL = f"https://download.pytorch.org/models/{ALEXNET_FILE}"
# the convolutions of torchvision's alexnet.features: (index in the Sequential, out channels, in channels, kernel,
# stride, padding); LPIPS reads the ReLU after each
CONVOLUTIONS = ((0, 64, 3, 11, 4, 2), (3, 192, 64, 5, 1, 2), (6, 384, 192, 3, 1, 1), (8, 256, 384, 3, 1, 1), (10, 256, 256, 3, 1, 1))
# LPIPS's input scaling: images in [-1, 1] shifted and scaled to the statistics AlexNet was trained on
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)


class LPIPS(nn.Module):
    """LPIPS with the AlexNet backbone (see the module's docstring); weights from ``state`` (torchvision's and LPIPS's
    keys), each checked for its shape, ``source`` naming where they came from in the error."""

    def __init__(self, state: dict[str, torch.Tensor], source: str = "the weights") -> None:
        super().__init__()
        self.convolutions = nn.ModuleList(nn.Conv2d(c_in, c_out, kernel, stride, padding)
                                          for _, c_out, c_in, kernel, stride, padding in CONVOLUTIONS)
        self.heads = nn.ParameterList(nn.Parameter(torch.zeros(1, c_out, 1, 1), requires_grad=False) for _, c_out, *_ in CONVOLUTIONS)
        self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1), persistent=False)
        with torch.no_grad():
            for layer, (index, *_) in enumerate(CONVOLUTIONS):
                conv = self.convolutions[layer]
                conv.weight.copy_(_weight(state, f"features.{index}.weight", conv.weight.shape, source))
                conv.bias.copy_(_weight(state, f"features.{index}.bias", conv.bias.shape, source))
                self.heads[layer].copy_(_weight(state, f"lin{layer}.model.1.weight", self.heads[layer].shape, source))
        self.requires_grad_(False)
        self.eval()

    def features(self, images: torch.Tensor) -> list[torch.Tensor]:
        """(N, 3, H, W) in [-1, 1] -> the five ReLU outputs, each normalised along its channels."""
        x = (images - self.shift) / self.scale
        out = []
        for layer, conv in enumerate(self.convolutions):
            if layer in (1, 2):  # max-pooling after the first two ReLUs, as AlexNet has it
                x = nn.functional.max_pool2d(x, kernel_size=3, stride=2)
            x = torch.relu(conv(x))
            out.append(x / (x.pow(2).sum(dim=1, keepdim=True).sqrt() + 1e-10))
        return out

    @torch.no_grad()
    def forward(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """The distance between images ``a`` and ``b``, (N, 3, H, W) or (H, W, 3), in [0, 1] -> (N,) (or a scalar)."""
        single = a.ndim == 3
        if single:
            a, b = a.permute(2, 0, 1)[None], b.permute(2, 0, 1)[None]
        if a.shape != b.shape or a.ndim != 4 or a.shape[1] != 3:
            raise ValueError(f"LPIPS compares two images of the same shape, (N, 3, H, W) or (H, W, 3): got {tuple(a.shape)} and {tuple(b.shape)}")
        device = self.shift.device
        features_a = self.features(a.to(device).float() * 2.0 - 1.0)
        features_b = self.features(b.to(device).float() * 2.0 - 1.0)
        distance = sum(((fa - fb) ** 2 * head).sum(dim=1).mean(dim=(1, 2)) for fa, fb, head in zip(features_a, features_b, self.heads))
        return distance[0] if single else distance


def _weight(state: dict, key: str, shape: torch.Size, source: str) -> torch.Tensor:
    if key not in state:
        raise ValueError(f"{source}: no '{key}': expected torchvision's AlexNet keys (features.<i>.weight) and LPIPS 0.1's heads (lin<k>.model.1.weight)")
    value = state[key]
    if not isinstance(value, torch.Tensor) or value.shape != shape:
        got = tuple(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__
        raise ValueError(f"{source}: '{key}' has shape {got}, expected {tuple(shape)} (LPIPS with the AlexNet backbone)")
    return value.float()


def _read(path: Path) -> dict[str, torch.Tensor]:
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # a torch file that is not a plain state dict, or not a torch file at all
        raise ValueError(f"{path}: not a weights file torch can load as plain tensors ({type(error).__name__}: {error})") from None
    if not isinstance(state, dict):
        raise ValueError(f"{path}: expected a dict of tensors (a state dict), got {type(state).__name__}")
    return state


def hub_backbone() -> Path:
    """Where torchvision keeps AlexNet's weights in the torch hub cache."""
    return Path(torch.hub.get_dir()) / "checkpoints" / ALEXNET_FILE


def shipped_heads() -> Path | None:
    """LPIPS 0.1's AlexNet heads as a package installed here ships them (torchmetrics, else lpips), or None. Found by
    the packages' folders: importing lpips would import torchvision."""
    for package, relative in (("torchmetrics", "functional/image/lpips_models/alex.pth"), ("lpips", "weights/v0.1/alex.pth")):
        spec = importlib.util.find_spec(package)
        if spec is not None and spec.submodule_search_locations:
            for folder in spec.submodule_search_locations:
                candidate = Path(folder) / relative
                if candidate.is_file():
                    return candidate
    return None


def named_weights(weights: str | Path, key: str) -> tuple[dict[str, torch.Tensor], list[str]]:
    """The weights a user names under ``key`` (``eval.lpips_weights`` or the environment variable): a file, or a
    folder whose ``*.pth`` files are read in name order -> (their tensors, the files read). A missing path or a folder
    without ``*.pth`` raises one FileNotFoundError naming ``key``."""
    path = Path(weights).expanduser()
    files = sorted(path.glob("*.pth")) if path.is_dir() else [path] if path.is_file() else []
    if not files:
        said = "no *.pth file in the folder" if path.is_dir() else "no such file or folder"
        raise FileNotFoundError(f"{key}: {said} {path}")
    state: dict[str, torch.Tensor] = {}
    for file in files:
        state.update(_read(file))
    return state, [str(file) for file in files]


def load_lpips(mode: str = "auto", weights: str | Path | None = None) -> tuple[LPIPS | None, str]:
    """LPIPS with the weights found as the module's docstring says -> (the network, where its weights came from), or
    (None, one line on why it was skipped and how to get it). ``mode``: auto (the named file and the caches), download
    (also fetch the backbone into the hub cache) or off. ``weights``: a file or folder (None: the environment variable
    ``NERF_LIGHTNING_LPIPS``'s, where set). A named file that is missing or of the wrong shapes raises one error
    naming it."""
    if mode not in LPIPS_MODES:
        raise ValueError(f"eval.lpips must be {', '.join(LPIPS_MODES[:-1])} or {LPIPS_MODES[-1]}, got '{mode}'")
    if mode == "off":
        return None, "LPIPS off (eval.lpips=off)"
    state: dict[str, torch.Tensor] = {}
    sources: list[str] = []
    named = (weights, "eval.lpips_weights") if weights else (os.environ.get(LPIPS_WEIGHTS_VARIABLE), f"${LPIPS_WEIGHTS_VARIABLE}")
    if named[0]:
        state, sources = named_weights(*named)
    if "features.0.weight" not in state:
        backbone = hub_backbone()
        if not backbone.is_file() and mode == "download":
            log.info("downloading AlexNet's weights for LPIPS into %s", backbone.parent)
            try:
                torch.hub.load_state_dict_from_url(ALEXNET_URL, progress=False, file_name=ALEXNET_FILE)
            except Exception as error:  # no internet, a proxy, a partial file: the scores go on without LPIPS
                return None, (f"LPIPS skipped: downloading {ALEXNET_URL} failed ({type(error).__name__}: {error}); put the "
                              f"file at {backbone} or name it with eval.lpips_weights=<file>")
        if not backbone.is_file():
            return None, (f"LPIPS skipped: no AlexNet weights at {backbone}; set eval.lpips_weights=<file or folder>, "
                          f"${LPIPS_WEIGHTS_VARIABLE}, or eval.lpips=download (fetches them from download.pytorch.org)")
        state.update({key: value for key, value in _read(backbone).items() if key.startswith("features.")})
        sources.append(str(backbone))
    if "lin0.model.1.weight" not in state:
        heads = shipped_heads()
        if heads is None:
            return None, ("LPIPS skipped: no LPIPS 0.1 heads (alex.pth): install torchmetrics or lpips, or name a file "
                          "holding them with eval.lpips_weights=<file>")
        state.update(_read(heads))
        sources.append(str(heads))
    source = " + ".join(sources)
    return LPIPS(state, source), source
