"""Peak memory of training on a full-size scene: nerf-train in a child process, its peak resident memory, JSON out.

    .venv/bin/python scripts/bench_memory.py --root ../shared/data/nerf_synthetic/lego --out docs/bench/memory_lego800.json
    .venv/bin/python scripts/bench_memory.py --root ../shared/data/nerf_synthetic/lego --image-cache /tmp/nerf_images \
        --out docs/bench/memory_lego800_mapped.json

Trains ``experiment=<--preset>`` (default ``fast_blender``) at ``data.scene.downscale=1`` (lego: 100 train and 100 val
images of 800x800) for ``--steps`` steps with one validation view, in a child process. Reports the child's peak
resident set size (``getrusage``) and, sampled every 50 ms from ``/proc/<pid>/status``, the peaks of its anonymous
memory (``RssAnon``: what the process itself holds) and of its file-backed pages (``RssFile``: mapped files, the
memory-mapped images among them, which the kernel can drop and read again). Also reports the bytes of the loaded
images (uint8), what float32 images and precomputed rays of every training pixel (origin and direction, float32)
would take. With ``--image-cache`` the images are memory-mapped from that folder (``data.scene.image_cache``); the
first run there writes the files, so run twice and record the second. With ``--memory-limit-gib`` the child runs in
a memory cgroup of that size (Linux, root: cgroup v1 ``memory.limit_in_bytes`` or v2 ``memory.max``), which counts
the page cache of the mapped images too but can reclaim it, and the result says whether the run finished or was
killed for memory; the cache files are first dropped from the page cache so that the cgroup pays for reading them.
Exits 0 with "skipped" when --root is missing.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

GIB = 1024**3


def status_kib(pid: int) -> dict[str, int]:
    """VmRSS, RssAnon and RssFile of a running process, in KiB (empty once it has exited, or off Linux)."""
    try:
        lines = Path(f"/proc/{pid}/status").read_text().splitlines()
    except OSError:
        return {}
    fields = (line.split(":", 1) for line in lines if line.startswith(("VmRSS", "RssAnon", "RssFile")))
    return {name: int(value.split()[0]) for name, value in fields}


def memory_cgroup(limit_bytes: int) -> Path:
    """A fresh memory cgroup limited to ``limit_bytes``, without swap; a process joins it through its ``cgroup.procs``."""
    v1, v2 = Path("/sys/fs/cgroup/memory"), Path("/sys/fs/cgroup")
    if (v1 / "cgroup.procs").is_file():
        limits = {"memory.limit_in_bytes": str(limit_bytes), "memory.memsw.limit_in_bytes": str(limit_bytes)}
        base = v1
    elif "memory" in (v2 / "cgroup.controllers").read_text() if (v2 / "cgroup.controllers").is_file() else False:
        limits = {"memory.max": str(limit_bytes), "memory.swap.max": "0"}
        base = v2
    else:
        sys.exit("--memory-limit-gib needs a cgroup memory controller (Linux)")
    group = base / f"nerf_bench_memory_{os.getpid()}"
    try:
        group.mkdir()
        for name, value in limits.items():
            if (group / name).exists():
                (group / name).write_text(value)
    except OSError as error:
        sys.exit(f"--memory-limit-gib: cannot make a memory cgroup in {base} ({error}); run as root")
    return group


def evict(folder: Path) -> None:
    """Drop the page cache of the files in ``folder``, so that the child's cgroup is charged for reading them again
    (pages another process read first would otherwise stay charged to that process's cgroup)."""
    for path in folder.glob("*.u8"):
        with open(path, "rb") as file:
            os.posix_fadvise(file.fileno(), 0, 0, os.POSIX_FADV_DONTNEED)


def peak_charge(group: Path) -> int | None:
    """The most memory the cgroup was charged (page cache included), in bytes."""
    for name in ("memory.max_usage_in_bytes", "memory.peak"):
        if (group / name).is_file():
            return int((group / name).read_text())
    return None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, required=True)
    parser.add_argument("--preset", default="fast_blender")
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--image-cache", type=Path, default=None, help="memory-map the images from this folder")
    parser.add_argument("--memory-limit-gib", type=float, default=None, help="run the child in a memory cgroup of this size")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("overrides", nargs="*", help="more Hydra overrides, after --")
    args = parser.parse_args()
    if not args.root.exists():
        print(json.dumps({"skipped": f"data not found: {args.root}"}))
        return
    cache = None if args.image_cache is None else args.image_cache.resolve()

    with tempfile.TemporaryDirectory() as run:
        command = [sys.executable, "-m", "nerf_lightning.cli.train", f"experiment={args.preset}", f"data.root={args.root.resolve()}",
                   "data.scene.downscale=1", f"trainer.max_steps={args.steps}", f"data.val_every={args.steps}", "data.val_views=1",
                   "trainer.enable_progress_bar=false", f"hydra.run.dir={run}", *args.overrides]
        if cache is not None:
            command.append(f"data.scene.image_cache={cache}")
        group = None if args.memory_limit_gib is None else memory_cgroup(int(args.memory_limit_gib * GIB))
        if group is not None and cache is not None and cache.is_dir():
            evict(cache)
        join = None if group is None else (lambda: (group / "cgroup.procs").write_text(str(os.getpid())))
        started = time.perf_counter()
        child = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, preexec_fn=join)
        peaks = {"RssAnon": 0, "RssFile": 0}
        while child.poll() is None:
            for name, kib in status_kib(child.pid).items():
                if name in peaks:
                    peaks[name] = max(peaks[name], kib)
            time.sleep(0.05)
        output = child.stdout.read()
        seconds = time.perf_counter() - started
        charged = None if group is None else peak_charge(group)
        if group is not None:
            group.rmdir()
        killed = group is not None and child.returncode == -signal.SIGKILL
        if child.returncode != 0 and not killed:
            sys.exit(f"nerf-train failed ({child.returncode}):\n{output[-3000:]}")
        peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024  # kilobytes on Linux
        metrics = {"step": None} if killed else json.loads((Path(run) / "metrics.json").read_text())

    from nerf_lightning.data.formats import load_blender

    scene = load_blender(args.root, downscale=1, image_cache=cache)
    held = {id(views.images): views.images.nbytes for views in scene.splits.values() if views.images is not None}
    train = scene.train
    pixels = len(train) * train.height * train.width
    result = {
        "preset": args.preset, "root": str(args.root), "steps": metrics["step"], "seconds": round(seconds, 1),
        "images": "memory-mapped" if cache is not None else "in memory",
        "memory_limit_gib": args.memory_limit_gib, "finished": not killed,
        "cgroup_peak_charge_gib": None if charged is None else round(charged / GIB, 3),
        "peak_rss_gib": round(peak / GIB, 3),
        "peak_rss_anon_gib": round(peaks["RssAnon"] * 1024 / GIB, 3), "peak_rss_file_gib": round(peaks["RssFile"] * 1024 / GIB, 3),
        "train_views": len(train), "size": [train.height, train.width],
        "image_gib_by_split": {name: round(views.images.nbytes / GIB, 3) for name, views in scene.splits.items() if views.images is not None},
        "image_gib_held": round(sum(held.values()) / GIB, 3),
        "float32_images_would_be_gib": round(4 * sum(held.values()) / GIB, 3),
        "precomputed_rays_would_add_gib": round(pixels * 6 * 4 / GIB, 3),
        "torch": __import__("torch").__version__, "machine": platform.machine(),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
