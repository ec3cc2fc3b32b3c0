"""Which device a command runs on: the ``device=auto|cpu|cuda|cuda:N|mps`` key of nerf-render, nerf-eval, nerf-export
and nerf-viz-cameras (training picks its device through Lightning's ``trainer.accelerator``)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import torch

# torch is imported inside the functions: the commands' key checks (nerf_lightning.cli.keys) read DEVICE_CHOICES
# before torch loads

DEVICE_CHOICES = "auto, cpu, cuda, cuda:<index> or mps"


def available_devices() -> list[str]:
    """The devices this machine has, as ``device=`` values."""
    import torch

    devices = ["cpu"]
    if torch.cuda.is_available():
        devices += ["cuda"] + [f"cuda:{index}" for index in range(torch.cuda.device_count())]
    if torch.backends.mps.is_available():
        devices.append("mps")
    return devices


def resolve_device(name: str | torch.device | None) -> torch.device:
    """``device=`` as a torch device: ``auto`` (or None) is CUDA where there is one, else the Apple GPU (MPS), else the
    CPU. ValueError naming the key for a device that is not one of :data:`DEVICE_CHOICES` or that this machine lacks."""
    import torch

    if isinstance(name, torch.device):
        return name
    text = "auto" if name is None else str(name).strip().lower()
    if text == "auto":
        if torch.cuda.is_available():
            return torch.device("cuda")
        return torch.device("mps") if torch.backends.mps.is_available() else torch.device("cpu")
    try:
        device = torch.device(text)
    except (RuntimeError, ValueError):
        raise ValueError(f"device must be {DEVICE_CHOICES}, got '{name}'") from None
    if device.type not in ("cpu", "cuda", "mps"):
        raise ValueError(f"device must be {DEVICE_CHOICES}, got '{name}'")
    if device.type == "cuda" and (not torch.cuda.is_available() or (device.index or 0) >= torch.cuda.device_count()):
        raise ValueError(f"device={name}: this machine has no such CUDA device (it has {', '.join(available_devices())}); use device=auto or device=cpu")
    if device.type == "mps" and not torch.backends.mps.is_available():
        raise ValueError(f"device={name}: this machine has no Apple GPU (it has {', '.join(available_devices())}); use device=auto or device=cpu")
    return device


def enable_tf32() -> None:
    """On CUDA, let float32 matrix products use TensorFloat-32 (Ampere and later: several times the speed, a 10-bit
    mantissa inside the product, float32 accumulation), as Lightning suggests; nothing elsewhere."""
    import torch

    if torch.cuda.is_available():
        torch.set_float32_matmul_precision("high")


def synchronize(device: torch.device) -> None:
    """Wait for the work queued on ``device`` (CUDA, Apple GPU; nothing to wait for on a CPU), so that a clock read
    after it counts that work."""
    import torch

    if device.type == "cuda":
        torch.cuda.synchronize(device)
    elif device.type == "mps":
        torch.mps.synchronize()


def peak_memory_gb(device: torch.device) -> float | None:
    """The most GPU memory (GiB) torch has held allocated on a CUDA ``device`` in this process
    (``torch.cuda.max_memory_allocated``), or None on any other device."""
    import torch

    if device.type != "cuda":
        return None
    return round(torch.cuda.max_memory_allocated(device) / 2**30, 3)


def memory_of(device: torch.device) -> int | None:
    """The bytes of memory ``device`` has: a GPU's own, the machine's RAM for the CPU (and for an Apple GPU, which
    shares it); None where it cannot be told."""
    import torch

    if device.type == "cuda":
        return int(torch.cuda.get_device_properties(device).total_memory)
    if device.type == "mps" and hasattr(torch.mps, "recommended_max_memory"):
        return int(torch.mps.recommended_max_memory())
    try:
        memory = int(os.sysconf("SC_PHYS_PAGES")) * int(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):  # not a POSIX system
        return None
    # in a container or a SLURM job the cgroup's limit, not the host's RAM, is what the process may use
    for limit in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            text = Path(limit).read_text().strip()
        except OSError:
            continue
        if text.isdigit():
            memory = min(memory, int(text))
    return memory
