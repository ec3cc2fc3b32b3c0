"""Helpers of scripts/gpu_check.sh (issue 47's GPU lease): a suite row cut to the minutes the lease has left, and the
summary of everything the check wrote.

    python scripts/gpu_check_tools.py scale SUITE ROW_ID MINUTES OUT_SUITE [--smoke]   # prints the new row's id
    python scripts/gpu_check_tools.py summary OUT WORK                                 # writes OUT/summary.txt
    python scripts/gpu_check_tools.py data ../shared/data .gpu_data [--scenes ...]     # what the lease carries
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import sys
import xml.etree.ElementTree as ElementTree
from pathlib import Path
from typing import Any

import yaml

# the targets, lego 800x800 on one H100: (row name, mark in minutes) -> dB
TARGETS = {("fast", 1.0): 33.0, ("fast", 3.0): 35.0}
# the scenes a lease can carry (scripts/gpu_check.yaml's rows)
SCENES = ("lego", "fox", "moldGoldCape")
# on a CPU (GPU_CHECK_SMOKE=1): tiny views and few Gaussians, so that each row takes seconds
SMALL_GRID = ["model.field.encoding.log2_table_size=14", "model.field.encoding.compile_evaluation=false", "model.sampler.grid.resolution=32", "model.sampler.samples_per_step=16384", "model.sampler.density_pass_samples=65536",
              "data.batch_size=256"]
SMOKE_OVERRIDES = {"fast_blender_gpu": ["data.scene.downscale=8", *SMALL_GRID],
                   "splat_blender_gpu": ["data.scene.downscale=8", "model.start.random.count=2000"],
                   "splat_360_gpu": ["data.scene.downscale=16", "model.start.random.count=2000"],
                   "splat_object_gpu": ["data.scene.downscale=16", "model.strategy.max_count=20000"],
                   "nerfacto_360_gpu": ["data.scene.downscale=16", "model.field.encoding.log2_table_size=14", "data.batch_size=256"]}


def scale(suite_path: str, row_id: str, minutes: float, out_path: str, smoke: bool) -> str:
    """Write ``out_path``: the suite with only the row ``row_id`` (scene/preset/<m>min/seed<s>), trained ``minutes``
    (its marks before them kept, the end a mark; with ``smoke``, on the CPU, the marks scaled alike and the views
    tiny); returns the new row's id."""
    from nerf_lightning.bench.suite import load_suite

    suite = load_suite(suite_path)
    [row] = [row for row in suite.rows if row.id == row_id]
    spec = yaml.safe_load(Path(suite_path).read_text())
    factor = minutes / row.minutes
    entry = {"scene": row.scene, "preset": row.preset, "minutes": round(minutes, 3), "data": row.data,
             "marks": sorted({round(mark * factor, 3) for mark in row.marks} if smoke else
                             {mark for mark in row.marks if mark < minutes} | {round(minutes, 3)}), "seeds": [row.seed],
             "overrides": list(row.overrides)}
    if smoke:
        entry["overrides"] += SMOKE_OVERRIDES.get(row.preset, [])
        spec["device"] = "cpu"
        entry["eval_views"] = 2
    elif row.eval_views:
        entry["eval_views"] = row.eval_views
    spec["rows"] = [{key: value for key, value in entry.items() if value not in (None, [])}]
    Path(out_path).parent.mkdir(parents=True, exist_ok=True)
    Path(out_path).write_text(yaml.safe_dump(spec, sort_keys=False))
    [scaled] = load_suite(out_path).rows
    return scaled.id


def _number(value: Any, digits: int = 2) -> str:
    return "-" if value is None else f"{value:.{digits}f}"


def bench_lines(name: str, path: Path, work: Path) -> list[str]:
    """A nerf-bench row's figures (its results JSON), or what a row cut short left in its run folder."""
    lines = [f"== {name}"]
    if not path.exists():
        runs = sorted((work / "bench" / name).glob("*/*"))  # <work>/bench/<name>/<suite>/<row slug>
        lines.append(f"  no results JSON ({path.name}): the row failed, was cut short or did not run; see log.txt")
        lines += warning_lines(work / "bench" / name)
        for run in runs:  # what it left: the marks kept and any that were scored
            marks = run / "marks" / "marks.json"
            if marks.exists():
                for mark in json.loads(marks.read_text()):
                    scored = run / "eval" / f"minute_{mark['minutes']:g}" / "eval.json"
                    psnr = json.loads(scored.read_text())["mean"].get("psnr") if scored.exists() else None
                    lines.append(f"  partial {run.name}: minute {mark['minutes']:g}: step {mark['step']} in {mark['training_seconds']} s "
                                 f"({mark['step'] / max(mark['training_seconds'], 1e-9):.2f} steps/s), PSNR {_number(psnr)}")
        return lines
    rows = json.loads(path.read_text())["rows"]
    for row in rows:
        lines.append(f"  {row['id']} {' '.join(row['overrides'])} on {row['machine']['name']} ({row['versions'].get('torch')})")
        lines.append(f"  {row['steps']} steps in {row['training_minutes']} training minutes: {1 / row['seconds_per_step']:.2f} steps/s; "
                     f"wall {row['wall_seconds']} s ({row['wall_seconds_training']} s of it nerf-train)")
        before = {"step": 0, "training_seconds": 0.0}
        for point in row["curve"]:
            rate = point["step"] / max(point["training_seconds"], 1e-9)
            # since the mark before: the steady rate, without the first minute's compile and grid warm-up
            between = (point["step"] - before["step"]) / max(point["training_seconds"] - before["training_seconds"], 1e-9)
            before = point
            target = TARGETS.get((name, float(point["minutes"])))
            masked = "" if point.get("psnr_masked") is None else f" (inside the masks {_number(point['psnr_masked'])})"
            verdict = "" if target is None or point["psnr"] is None else f"  target >= {target:g}: {'MET' if point['psnr'] >= target else 'NOT MET'}"
            lines.append(f"  minute {point['minutes']:g}: step {point['step']} ({rate:.2f} steps/s, {between:.2f} since the mark before), "
                         f"PSNR {_number(point['psnr'])} dB{masked}, "
                         f"SSIM {_number(point['ssim'], 3)}, {_number(point['seconds_per_frame'], 3)} s a frame "
                         f"({point['views']} views {point['frame_size']}){verdict}")
        lines.append(f"  last step: samples/ray {_number(row.get('samples_per_ray'), 1)}, rays {_number(row.get('rays_per_step'), 0)}, "
                     f"samples {_number(row.get('samples_per_step'), 0)}, Gaussians {_number(row.get('gaussians'), 0)}; "
                     f"peak GPU memory {_number(row.get('peak_memory_gb'))} GiB")
        lines.append(f"  {row['commands']['bench']}")
    return lines + warning_lines(work / "bench" / name)


def warning_lines(folder: Path) -> list[str]:
    """What a row's nerf-train said about compiling: a failed torch.compile (the step then ran plainly), recompiles,
    graph breaks, out of memory."""
    lines = []
    for log in sorted(folder.glob("*/*/train.log")):
        said = [line.strip() for line in log.read_text(errors="replace").splitlines()
                if any(word in line for word in ("torch.compile failed", "recompil", "graph break", "Graph break", "OutOfMemory",
                                                 "out of memory", "Traceback", "Error"))]
        lines += [f"  train.log: {line[:300]}" for line in said[:10]]
    return lines


def test_lines(junit: Path, log: Path, which: str = "tests") -> list[str]:
    lines = [f"== {which} (CUDA where the machine has it)"]
    if not junit.exists():
        # killed before pytest wrote its XML: the failures its -v lines named as they ended
        text = log.read_text(errors="replace") if log.exists() else ""
        named = [line.strip() for line in text.splitlines() if re.search(r"\b(FAILED|ERROR) tests/", line)]
        return [*lines, "  no junit.xml: the tests did not run or were killed; see log.txt",
                *(f"  {line[:300]}" for line in named)]
    root = ElementTree.parse(junit).getroot()
    suites = [root] if root.tag == "testsuite" else list(root)
    counts = {key: sum(int(suite.get(key, 0)) for suite in suites) for key in ("tests", "failures", "errors", "skipped")}
    seconds = sum(float(suite.get("time", 0)) for suite in suites)
    lines.append(f"  {counts['tests']} tests: {counts['failures']} failed, {counts['errors']} errors, {counts['skipped']} skipped; {seconds:.0f} s")
    for case in root.iter("testcase"):
        for kind in ("failure", "error"):
            for problem in case.findall(kind):
                message = (problem.get("message") or "").strip().splitlines()
                lines.append(f"  {kind.upper()} {case.get('classname')}::{case.get('name')}: {message[0][:300] if message else ''}")
        for skipped in case.findall("skipped"):
            message = (skipped.get("message") or "").strip()
            if "CUDA" in message or "cuda" in message:
                lines.append(f"  skipped {case.get('classname')}::{case.get('name')}: {message[:200]}")
    text = log.read_text(errors="replace") if log.exists() else ""
    if "KeyboardInterrupt" in text or "Interrupted" in text or "!!!!" in text:
        lines.append("  INTERRUPTED at the time limit: the tests not listed did not run")
    return lines


def sync_lines(path: Path, warmup: int) -> list[str]:
    lines = ["== host syncs (CountHostSyncs: aten ops that wait, and CUDA's own synchronizing-call reports)"]
    if not path.exists():
        return [*lines, "  no syncs.json: the run failed or was cut short; see log.txt"]
    steps = json.loads(path.read_text())
    totals: dict[str, int] = {}
    for counts in steps:
        for op, count in counts.items():
            totals[op] = totals.get(op, 0) + count
    after = steps[warmup:] if len(steps) > warmup + 1 else steps[2:]
    start = warmup if len(steps) > warmup + 1 else 2
    clean = sum(1 for counts in after if not counts)
    lines.append(f"  {len(steps)} steps; after step {start}: {clean} of {len(after)} with none "
                 f"({100 * clean / max(len(after), 1):.0f}%; target 90%: {'MET' if after and clean >= 0.9 * len(after) else 'NOT MET'})")
    lines.append(f"  by op over all steps: {json.dumps(totals, sort_keys=True)}")
    waiting = [(index, counts) for index, counts in enumerate(steps) if counts]
    for index, counts in waiting[:25]:
        lines.append(f"  step {index}: {json.dumps(counts, sort_keys=True)}")
    if len(waiting) > 25:
        lines.append(f"  ... {len(waiting) - 25} more steps that waited")
    return lines


def utilisation_lines(smi: Path, phases: Path) -> list[str]:
    """Mean GPU utilisation and the most memory nvidia-smi saw, in each phase of the check."""
    if not smi.exists() or not phases.exists():
        return []
    samples = []
    for line in smi.read_text().splitlines():
        parts = [part.strip() for part in line.split(",")]
        if len(parts) >= 3 and parts[1].replace(".", "").isdigit():
            samples.append((parts[0][:19], float(parts[1]), float(parts[2])))
    lines = ["== GPU (nvidia-smi once a second: utilisation %, memory used MiB)"]
    for line in phases.read_text().splitlines():
        name, start, end = line.split("\t")
        inside = [(util, memory) for stamp, util, memory in samples if start <= stamp <= end]
        if inside:
            lines.append(f"  {name}: {len(inside)} s, utilisation mean {sum(u for u, _ in inside) / len(inside):.0f}%, "
                         f"memory max {max(m for _, m in inside):.0f} MiB")
    return lines


def summary(out: Path, work: Path) -> str:
    lines = ["# scripts/gpu_check.sh summary"]
    for name in ("env.txt", "cut.txt"):
        if (work / name).exists():
            lines += (work / name).read_text().rstrip().splitlines()
    if (out / "junit_device.xml").exists():
        lines += test_lines(out / "junit_device.xml", work / "tests.log", "the test files that touch a GPU")
    lines += test_lines(out / "junit.xml", work / "tests.log", "the other tests")
    lines += sync_lines(out / "syncs.json", warmup=int((work / "sync_warmup.txt").read_text()) if (work / "sync_warmup.txt").exists() else 2)
    for name in ("splat", "splatfox", "fast", "cape", "capesplat"):
        lines += bench_lines(name, out / f"{name}.json", work)
    lines += utilisation_lines(work / "smi.csv", work / "phases.txt")
    text = "\n".join(lines) + "\n"
    (out / "summary.txt").write_text(text)
    return text


def carried_data(source: Path, target: Path, train_views: int = 25, val_views: int = 5, scenes: tuple[str, ...] = SCENES) -> None:
    """The data a 64 MiB lease carries, from ``source`` (../shared/data) into ``target``, of ``scenes``: lego at 800x800
    with every 4th of its train views (25) and the first 5 val views, fox whole, moldGoldCape's images_4, masks_4 and
    poses."""
    if "lego" in scenes:
        lego, lego_out = source / "nerf_synthetic/lego", target / "nerf_synthetic/lego"
        for split, count in (("train", train_views), ("val", val_views)):
            meta = json.loads((lego / f"transforms_{split}.json").read_text())
            step = max(1, len(meta["frames"]) // count)
            meta["frames"] = meta["frames"][::step][:count]
            for frame in meta["frames"]:
                image = Path(frame["file_path"] + ".png")
                (lego_out / image.parent).mkdir(parents=True, exist_ok=True)
                shutil.copy(lego / image, lego_out / image)
            (lego_out / f"transforms_{split}.json").write_text(json.dumps(meta, indent=2))
    if "fox" in scenes:
        shutil.copytree(source / "nerfstudio/fox", target / "nerfstudio/fox", dirs_exist_ok=True)
    if "moldGoldCape" in scenes:
        cape, cape_out = source / "masked_objects/moldGoldCape", target / "masked_objects/moldGoldCape"
        for name in ("images_4", "masks_4"):
            shutil.copytree(cape / name, cape_out / name, dirs_exist_ok=True)
        shutil.copy(cape / "poses_bounds.npy", cape_out / "poses_bounds.npy")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    scaling = commands.add_parser("scale")
    scaling.add_argument("suite")
    scaling.add_argument("row_id")
    scaling.add_argument("minutes", type=float)
    scaling.add_argument("out_suite")
    scaling.add_argument("--smoke", action="store_true")
    summarising = commands.add_parser("summary")
    summarising.add_argument("out", type=Path)
    summarising.add_argument("work", type=Path)
    carrying = commands.add_parser("data")
    carrying.add_argument("source", type=Path)
    carrying.add_argument("target", type=Path)
    carrying.add_argument("--scenes", nargs="+", choices=SCENES, default=list(SCENES),
                          help="the scenes to carry (all three, 44 MB, leave no room for pycolmap's 38 MB wheel)")
    args = parser.parse_args(argv)
    if args.command == "data":
        carried_data(args.source, args.target, scenes=tuple(args.scenes))
    elif args.command == "scale":
        print(scale(args.suite, args.row_id, args.minutes, args.out_suite, args.smoke))
    else:
        sys.stdout.write(summary(args.out, args.work))


if __name__ == "__main__":
    main()
