"""nerf-bench: run a benchmark suite through the real commands and keep one JSON of results per suite.

    nerf-bench run cpu-quick                      # a few minutes a scene (the procedural row needs no data)
    nerf-bench run cpu --data-dir ../shared/data  # the 10-minute rows the README quotes
    nerf-bench run cpu --only 'fern/*' --resume   # one scene; rows already measured on this machine are skipped
    nerf-bench report                             # docs/results.md and its plots, from docs/results/*.json
    nerf-bench rescore cpu --only 'fox/*'         # the rows' kept checkpoints scored again (new scores)
    nerf-bench rescore cpu --lpips-weights ../shared/data/lpips   # ... with LPIPS's weights from a file or folder
    nerf-bench list                               # the suites and their rows

For each row of the suite (scene x preset x minutes x seed, :mod:`nerf_lightning.bench.suite`): ``nerf-train``
trains the preset for that many minutes of training time (validation off), keeping a checkpoint at each of the
row's minute marks; ``nerf-eval`` scores every mark on the held-out views (PSNR, SSIM, LPIPS where its weights are here, seconds a frame). The row,
with the machine, the versions, the date and the exact commands, is written into ``<results>/<suite>.json`` as soon
as it is measured, and the results table regenerated.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import shlex
import shutil
import subprocess
import sys
import time
from collections.abc import Sequence
from fnmatch import fnmatch
from pathlib import Path
from typing import Any

from nerf_lightning.bench.report import read_results, write_report
from nerf_lightning.bench.suite import Row, Suite, SuiteError, load_suite, shipped_suites
from nerf_lightning.outputs.choices import LPIPS_WEIGHTS_VARIABLE

DEFAULT_RESULTS = Path("docs/results")
DEFAULT_REPORT = Path("docs/results.md")
DEFAULT_README = Path("README.md")
DEFAULT_WORK = Path("outputs/bench")
# where the real captures are found: --data-dir, else this variable, else the project's shared data folder
DATA_DIR_VARIABLE = "NERF_LIGHTNING_DATA"
DEFAULT_DATA_DIR = Path("../shared/data")


class BenchmarkError(RuntimeError):
    """A command of a row failed: the message names the command and its log."""


def name_lpips_weights(weights: Path | None) -> None:
    """``--lpips-weights``: LPIPS's weights (a file, or a folder of them) for every ``nerf-eval`` this process runs,
    through the variable ``nerf-eval`` reads (``NERF_LIGHTNING_LPIPS``), so that the rows' commands stay as a user
    types them; without it, that variable as the user set it, else the torch hub cache."""
    if weights is None:
        return
    if not weights.exists():
        raise BenchmarkError(f"--lpips-weights: no such file or folder {weights}")
    os.environ[LPIPS_WEIGHTS_VARIABLE] = str(weights.resolve())


def command(name: str) -> list[str]:
    """The console script ``name`` (``nerf-train``) installed beside this Python, else ``python -m`` its module."""
    script = Path(sys.executable).parent / name
    if script.exists():
        return [str(script)]
    module = {"nerf-train": "train", "nerf-eval": "evaluate"}[name]
    return [sys.executable, "-m", f"nerf_lightning.cli.{module}"]


def shown(name: str, arguments: list[str]) -> str:
    """The command as a user types it."""
    return shlex.join([name, *arguments])


def run_logged(name: str, arguments: list[str], log_path: Path) -> None:
    """Run command ``name`` with ``arguments``, its output into ``log_path``; a failure raises with the log's end."""
    log_path.parent.mkdir(parents=True, exist_ok=True)
    with log_path.open("w") as log:
        log.write(shown(name, arguments) + "\n\n")
        log.flush()
        finished = subprocess.run([*command(name), *arguments], stdout=log, stderr=subprocess.STDOUT, check=False)
    if finished.returncode != 0:
        tail = "\n".join(log_path.read_text(errors="replace").splitlines()[-15:])
        raise BenchmarkError(f"{name} failed (exit {finished.returncode}); its log: {log_path}\n{tail}")


def data_root(row: Row, data_dir: Path) -> Path | None:
    """The row's ``data.root`` under ``data_dir`` (None: the preset's own scene)."""
    return None if row.data is None else data_dir / row.data


def train_arguments(row: Row, run_dir: Path, root: Path | None) -> list[str]:
    """``nerf-train`` overrides for a row: its preset and seed, validation off, a stop after ``row.minutes`` of
    training time and checkpoints at the marks (:mod:`nerf_lightning.bench.callbacks`), then the row's overrides."""
    marks = ", ".join(f"{m:g}" for m in row.marks)
    return [
        f"experiment={row.preset}", f"seed={row.seed}", f"paths.output_dir={run_dir}",
        *([f"data.root={root}"] if root is not None else []),
        # validation off (the marks are scored afterwards, on every held-out view): training time is all that runs
        "data.val_every=null", "trainer.enable_progress_bar=false",
        f"+callbacks.bench_stop={{_target_: nerf_lightning.bench.callbacks.StopAtTrainingMinutes, minutes: {row.minutes:g}}}",
        f"+callbacks.bench_marks={{_target_: nerf_lightning.bench.callbacks.CheckpointAtMinutes, dirpath: {run_dir / 'marks'}, minutes: [{marks}]}}",
        *row.overrides,
    ]


def eval_arguments(row: Row, checkpoint: Path, output_dir: Path) -> list[str]:
    return [f"ckpt_path={checkpoint}", f"output_dir={output_dir}", f"device={row.device}",
            *([f"max_views={row.eval_views}"] if row.eval_views else [])]


def step_figures(metrics: dict[str, Any]) -> dict[str, Any]:
    """What a run's last training step measured, from its metrics.json: samples a ray, rays and samples a step (a
    radiance field), Gaussians (splats), and the peak GPU memory in GiB (CUDA); None where the run has no such figure."""
    samples_per_ray, rays = metrics.get("train/samples_per_ray"), metrics.get("train/rays")
    return {"samples_per_ray": samples_per_ray, "rays_per_step": rays,
            "samples_per_step": round(samples_per_ray * rays) if samples_per_ray is not None and rays is not None else None,
            "gaussians": metrics.get("train/gaussians"), "peak_memory_gb": metrics.get("peak_memory_gb")}


def suite_argument(suite: Suite) -> str:
    """The suite as ``nerf-bench run`` is given it: a shipped suite's name, else its file."""
    return suite.name if shipped_suites().get(suite.name) == suite.path else str(suite.path)


# the scores after nerf-eval's colour correction (nerf_lightning.outputs.evaluation), beside the raw ones
COLOUR_CORRECTED = ("cc_psnr", "cc_ssim", "cc_lpips", "cc_psnr_masked")


def measure_row(row: Row, suite: Suite, data_dir: Path, work_dir: Path, written: Sequence[Path] = ()) -> dict[str, Any]:
    """Train, then score every mark, of one row; returns its result (see the module docstring)."""
    from nerf_lightning.bench.machine import provenance

    # as the row starts (a commit made while it trains is not what it measured); the runner's own outputs (``written``)
    # do not make the checkout dirty
    measured_on = provenance(row.device, written)
    root = data_root(row, data_dir)
    run_dir = (work_dir / suite.name / row.slug).resolve()
    arguments = train_arguments(row, run_dir, root.resolve() if root is not None else None)
    if run_dir.exists():  # an earlier measurement of the row: its marks and checkpoints must not be taken for this one's
        shutil.rmtree(run_dir)
    started = time.perf_counter()
    print(f"[{row.id}] training {row.minutes:g} min: {run_dir / 'train.log'}", flush=True)
    run_logged("nerf-train", arguments, run_dir / "train.log")
    wall_train = time.perf_counter() - started
    marks = json.loads((run_dir / "marks" / "marks.json").read_text())
    metrics = json.loads((run_dir / "metrics.json").read_text())
    curve = []
    for mark in marks:
        output_dir = run_dir / "eval" / f"minute_{mark['minutes']:g}"
        print(f"[{row.id}] scoring minute {mark['minutes']:g} (step {mark['step']})", flush=True)
        run_logged("nerf-eval", eval_arguments(row, Path(mark["path"]), output_dir), output_dir / "eval.log")
        scored = json.loads((output_dir / "eval.json").read_text())
        curve.append({"minutes": mark["minutes"], "step": mark["step"], "training_seconds": mark["training_seconds"],
                      "psnr": scored["mean"].get("psnr"), "ssim": scored["mean"].get("ssim"), "lpips": scored["mean"].get("lpips"),
                      "psnr_masked": scored["mean"].get("psnr_masked"), "depth_error": scored["mean"].get("depth_error"),
                      **{key: scored["mean"].get(key) for key in COLOUR_CORRECTED}, "seconds_per_frame": scored.get("seconds_per_frame"),
                      "views": scored["views"], "frame_size": scored.get("frame_size")})
    last = curve[-1]
    # the commands as a user types them, with the data where the suite names it
    shown_root = Path(os.path.relpath(root, Path.cwd())) if root is not None else None
    shown_run = work_dir / suite.name / row.slug
    last_checkpoint = shown_run / "marks" / f"minute_{last['minutes']:g}.ckpt"
    return {
        "id": row.id, "suite": suite.name, "scene": row.scene, "preset": row.preset, "minutes": row.minutes, "seed": row.seed,
        "data": row.data, "overrides": list(row.overrides), "device": row.device,
        "steps": last["step"], "training_minutes": round(last["training_seconds"] / 60, 2),
        "seconds_per_step": round(last["training_seconds"] / max(last["step"], 1), 4),
        "psnr": last["psnr"], "ssim": last["ssim"], "lpips": last["lpips"], "psnr_masked": last["psnr_masked"], "depth_error": last["depth_error"],
        **{key: last[key] for key in COLOUR_CORRECTED},
        "seconds_per_frame": last["seconds_per_frame"], "frame_size": last["frame_size"], "views": last["views"],
        **step_figures(metrics), "curve": curve,
        "wall_seconds": round(time.perf_counter() - started, 1), "wall_seconds_training": round(wall_train, 1),
        "commands": {
            "bench": shown("nerf-bench", ["run", suite_argument(suite), "--only", row.id, *(["--data-dir", str(data_dir)] if row.data else [])]),
            "train": shown("nerf-train", train_arguments(row, shown_run, shown_root)),
            "eval": shown("nerf-eval", eval_arguments(row, last_checkpoint, shown_run / "eval")),
        },
        **measured_on,
    }


def results_path(results_dir: Path, suite: Suite) -> Path:
    return results_dir / f"{suite.name}.json"


def write_results(path: Path, results: dict[str, Any]) -> None:
    from nerf_lightning.io import write_json

    results["rows"].sort(key=lambda r: (r["scene"], r["preset"], r["minutes"], r["seed"], r["machine"]["name"]))
    write_json(path, results)


def run_suite(suite: Suite, rows: list[Row], data_dir: Path, results_dir: Path, work_dir: Path, resume: bool = False,
              report: Path | None = DEFAULT_REPORT, readme: Path | None = None, allow_dirty: bool = False) -> list[dict[str, Any]]:
    """Measure ``rows`` of ``suite`` one after another, each written into ``<results_dir>/<suite>.json`` as soon as it
    is measured (replacing that row's earlier result from this machine); rows without their data are skipped with a
    line. ``resume``: skip rows this machine has measured already. Regenerates ``report`` (and ``readme``'s table)
    after each row. A checkout with uncommitted changes is refused unless ``allow_dirty``: a row names the commit it
    measured, and uncommitted code has none."""
    from nerf_lightning.bench.machine import machine, source_revision


    path = results_path(results_dir, suite)
    here = machine(rows[0].device if rows else "cpu")["name"]
    measured = []
    for row in rows:
        results = read_results(path)
        done = [r for r in results["rows"] if r["id"] == row.id and r["machine"]["name"] == here]
        if resume and done:
            print(f"[{row.id}] measured on {here} on {done[0]['date'][:10]}: skipped (--resume)", flush=True)
            continue
        root = data_root(row, data_dir)
        if root is not None and not root.exists():
            print(f"[{row.id}] skipped: {root} not found (--data-dir, or {DATA_DIR_VARIABLE}, names the data folder)", flush=True)
            continue
        written = [path for path in (results_dir, report, readme) if path is not None]
        revision = source_revision(written)
        if revision is not None and revision.endswith("+dirty") and not allow_dirty:
            raise BenchmarkError(f"the checkout has uncommitted changes (at {revision}): commit them, so that each row "
                                 "names the code it measured, or pass --allow-dirty (the rows then say +dirty)")
        result = measure_row(row, suite, data_dir, work_dir, written)
        results = read_results(path)  # again: another suite run may have written meanwhile
        results["rows"] = [r for r in results["rows"] if not (r["id"] == row.id and r["machine"]["name"] == result["machine"]["name"])]
        results["rows"].append(result)
        write_results(path, results)
        measured.append(result)
        print(f"[{row.id}] {result['psnr']:.2f} dB, SSIM {result['ssim']:.3f}, {result['steps']} steps, "
              f"{result['seconds_per_step']:.4f} s a step, {result['seconds_per_frame']:.2f} s a frame -> {path}", flush=True)
        if report is not None:
            write_report(results_dir, report, readme)
    return measured


# -- nerf-bench rescore: a row's kept checkpoint scored again, without training it again (a score added since, such
# as the colour-corrected cc_ ones, or LPIPS where its weights have come). Its training figures (steps, seconds a
# step and a frame: the machine it trained on) stay; ``rescored`` says when, at which commit, and whether the raw PSNR
# came out as before (the same checkpoint and views give the same PSNR unless the scoring changed).

# what a row takes from a new eval.json's means (its last curve point too)
SCORES = ("psnr", "ssim", "lpips", "psnr_masked", "depth_error", *COLOUR_CORRECTED)


def scored_checkpoint(row: dict[str, Any]) -> tuple[Path, list[str]] | None:
    """The checkpoint a row's ``nerf-eval`` scored and that command's other arguments (the output folder left out),
    or None where the row names no ``nerf-eval`` command."""
    words = shlex.split(row.get("commands", {}).get("eval", ""))
    if not words or words[0] != "nerf-eval":
        return None
    arguments = [word for word in words[1:] if not word.startswith("output_dir=")]
    checkpoint = next((word.split("=", 1)[1] for word in arguments if word.startswith("ckpt_path=")), None)
    return (Path(checkpoint), arguments) if checkpoint else None


def rescore_row(row: dict[str, Any], output_dir: Path, written: Sequence[Path] = ()) -> dict[str, Any]:
    """Score ``row``'s checkpoint again into ``output_dir`` and return the row with the new scores and ``rescored``
    (its revision leaving out the runner's own outputs, ``written``: a row rescored before it does not make it dirty)."""
    from nerf_lightning.bench.machine import source_revision

    checkpoint, arguments = scored_checkpoint(row)
    run_logged("nerf-eval", [*arguments, f"output_dir={output_dir}"], output_dir / "eval.log")
    scored = json.loads((output_dir / "eval.json").read_text())
    mean = scored["mean"]
    before = row.get("psnr")
    # a score this machine cannot give (LPIPS without its weights) keeps the row's earlier one
    scores = {key: mean[key] for key in SCORES if mean.get(key) is not None}
    updated = {**row, **scores}
    if updated.get("curve"):
        updated["curve"] = [*row["curve"][:-1], {**row["curve"][-1], **scores}]
    same = before is not None and mean.get("psnr") is not None and abs(mean["psnr"] - before) < 1e-3
    updated["rescored"] = {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                           "revision": source_revision(written), "checkpoint": str(checkpoint), "psnr_before": before, "psnr_as_before": same,
                           "lpips": scored.get("lpips")}  # the weights LPIPS was scored with, or why it was not
    return updated


def rescore(results_path: Path, patterns: list[str] | None, work_dir: Path, report: Path | None = None,
            readme: Path | None = None) -> list[dict[str, Any]]:
    """Rescore the rows of ``results_path`` whose id matches one of ``patterns`` (all without), measured on this
    machine and whose checkpoint is here, writing the JSON after each; the others named. Regenerates ``report`` (and ``readme``'s table)."""
    from nerf_lightning.bench.machine import machine

    results = read_results(results_path)
    done = []
    for row in list(results["rows"]):
        if patterns and not any(fnmatch(row["id"], pattern) for pattern in patterns):
            continue
        here = machine(row.get("device", "cpu"))["name"]
        if row["machine"]["name"] != here:  # another machine's checkpoint path may name one of this machine's runs
            print(f"[{row['id']}, {row['machine']['name']}] skipped: measured on another machine than this ({here})", flush=True)
            continue
        found = scored_checkpoint(row)
        if found is None or not found[0].is_file():
            print(f"[{row['id']}, {row['machine']['name']}] skipped: its checkpoint "
                  f"{found[0] if found else '(none named)'} is not here", flush=True)
            continue
        stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
        output_dir = work_dir / "rescored" / f"{row['id'].replace('/', '_')}_{stamp}"
        print(f"[{row['id']}, {row['machine']['name']}] scoring {found[0]} again", flush=True)
        updated = rescore_row(row, output_dir, [path for path in (results_path.parent, report, readme) if path is not None])
        results["rows"] = [updated if other is row else other for other in results["rows"]]
        done.append(updated)
        write_results(results_path, results)
        said = "as before" if updated["rescored"]["psnr_as_before"] else f"was {updated['rescored']['psnr_before']}"
        print(f"[{row['id']}] {updated.get('psnr') or float('nan'):.2f} dB ({said}), colour-corrected "
              f"{updated.get('cc_psnr') or float('nan'):.2f} dB", flush=True)
    if report is not None and done:
        write_report(results_path.parent, report, readme)
    return done


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="nerf-bench", description=__doc__.splitlines()[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter, epilog="\n".join(__doc__.splitlines()[1:9]))
    commands = parser.add_subparsers(dest="command", required=True)
    run = commands.add_parser("run", help="measure a suite's rows")
    run.add_argument("suite", help=f"a shipped suite ({', '.join(sorted(shipped_suites()))}) or a suite .yaml file")
    run.add_argument("--only", nargs="+", metavar="PATTERN", help="rows whose id (scene/preset/<m>min/seed<s>) matches a glob")
    run.add_argument("--resume", action="store_true", help="skip rows already measured on this machine")
    run.add_argument("--data-dir", type=Path, default=None, help=f"where the rows' data lie (default: ${DATA_DIR_VARIABLE}, else {DEFAULT_DATA_DIR})")
    run.add_argument("--results", type=Path, default=DEFAULT_RESULTS, help="folder of the suites' results JSONs")
    run.add_argument("--report", type=Path, default=None,
                     help=f"the results table regenerated after each row (default: {DEFAULT_REPORT} where --results is {DEFAULT_RESULTS}, "
                          "else <results>.md beside that folder)")
    run.add_argument("--work", type=Path, default=DEFAULT_WORK, help="where the runs (checkpoints, logs, renders) go")
    run.add_argument("--readme", type=Path, default=None,
                     help=f"whose results table (between its marker lines) is regenerated too (default: {DEFAULT_README} where --results is "
                          f"{DEFAULT_RESULTS}, else none: rows kept elsewhere do not replace the README's table)")
    run.add_argument("--allow-dirty", action="store_true", help="measure a checkout with uncommitted changes (the rows say +dirty)")
    lpips_help = (f"LPIPS's AlexNet weights, a file or a folder of them, for nerf-eval (default: ${LPIPS_WEIGHTS_VARIABLE}, "
                  "else the torch hub cache)")
    run.add_argument("--lpips-weights", type=Path, default=None, help=lpips_help)
    report = commands.add_parser("report", help="regenerate the results table and plots from the results JSONs")
    report.add_argument("--results", type=Path, default=DEFAULT_RESULTS)
    report.add_argument("--report", type=Path, default=None, help="as for run")
    report.add_argument("--readme", type=Path, default=None, help="as for run")
    again = commands.add_parser("rescore", help="score rows' kept checkpoints again (new scores; training figures kept)")
    again.add_argument("suite", help="the suite whose results JSON holds the rows")
    again.add_argument("--only", nargs="+", metavar="PATTERN", help="rows whose id matches a glob (default: all)")
    again.add_argument("--results", type=Path, default=DEFAULT_RESULTS)
    again.add_argument("--work", type=Path, default=DEFAULT_WORK, help="where the new scores' renders go")
    again.add_argument("--report", type=Path, default=None, help="as for run")
    again.add_argument("--readme", type=Path, default=None, help="as for run")
    again.add_argument("--lpips-weights", type=Path, default=None, help=lpips_help)
    listing = commands.add_parser("list", help="the suites and their rows")
    listing.add_argument("suite", nargs="?")
    args = parser.parse_args(argv)
    if args.command in ("run", "report", "rescore"):
        # the project's own results write its page and README; any other folder (a smoke run's, a GPU lease's) writes
        # its page beside itself and no README, unless named
        own = args.results.resolve() == DEFAULT_RESULTS.resolve()
        if args.report is None:
            args.report = DEFAULT_REPORT if own else args.results.with_suffix(".md")
        if args.readme is None and own:
            args.readme = DEFAULT_README

    try:
        name_lpips_weights(getattr(args, "lpips_weights", None))
        if args.command == "list":
            for name in [args.suite] if args.suite else sorted(shipped_suites()):
                suite = load_suite(name)
                print(f"{suite.name} ({suite.path}):")
                for row in suite.rows:
                    print(f"  {row.id}  data={row.data or '(built in)'}  marks={', '.join(f'{m:g}' for m in row.marks)}  device={row.device}")
        elif args.command == "report":
            print(write_report(args.results, args.report, args.readme))
        elif args.command == "rescore":
            rescore(args.results / f"{Path(args.suite).stem}.json", args.only, args.work, args.report, args.readme)
        else:
            suite = load_suite(args.suite)
            data_dir = args.data_dir or Path(os.environ.get(DATA_DIR_VARIABLE, DEFAULT_DATA_DIR))
            run_suite(suite, suite.select(args.only), data_dir, args.results, args.work, args.resume, args.report, args.readme,
                      args.allow_dirty)
    except (SuiteError, BenchmarkError) as error:
        print(f"nerf-bench: {error}", file=sys.stderr)
        raise SystemExit(2) from None
    except KeyboardInterrupt:
        print("nerf-bench: interrupted; rows measured so far are in the results JSON (--resume goes on from there)", file=sys.stderr)
        raise SystemExit(130) from None


if __name__ == "__main__":
    main()
