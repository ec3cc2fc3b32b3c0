"""nerf-process-data on fox's 50 photos against the published poses: how many register, how far the recovered cameras
are from the published ones after a similarity alignment, and how long each stage takes.

    .venv/bin/python scripts/bench_process_data.py --root ../shared/data/nerfstudio/fox --mappers-over-seeds 0 1 2 3 \
        --out docs/bench/process_data_fox.json

Fixed settings, the command's defaults: one shared OPENCV camera, features read at 1600 px on the long side, 8192
SIFT features an image, exhaustive matching (under 100 images), ``mapper=auto`` (both mappers, the better model
kept; ``--mapper``), seed 0. The photos are ``<root>/images``, the published poses ``<root>/transforms.json``; the
capture is written to ``--work`` (a temporary folder by default).
Position errors are percentages of the published cameras' spread (the root mean square distance of their centres
from their mean). Exits 0 with "skipped" when --root is missing.

``--mappers-over-seeds``: then, on the same images, features once and for each seed the matching (its RANSAC seeded)
and both mappers, global and incremental, each compared with the published poses and scored by the fraction of
verified matches its poses explain (what ``mapper=auto`` keeps the better model by): how often each mapper places
the cameras as published, and whether the score picks the right one.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import shutil
import tempfile
import time
from pathlib import Path

from nerf_lightning.data.capture import compare_with_reference, process_capture
from nerf_lightning.data.capture.colmap import (
    colmap_log,
    exhaustive_pairs,
    extract_features,
    map_images,
    match_features,
    reconstruction_to_transforms,
    verified_matches_explained,
)
from nerf_lightning.io import write_json


def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def mappers_over_seeds(images: Path, reference: Path, seeds: list[int], work: Path) -> list[dict]:
    """For each seed: the matches verified with that RANSAC seed, then each mapper, compared with ``reference``."""
    names = sorted(path.name for path in images.iterdir())
    results = []
    with colmap_log(False):
        extract_features(work / "features.db", images, names, "OPENCV", True, 1600, 8192, False)
        for seed in seeds:
            database = work / f"seed{seed}.db"
            shutil.copy(work / "features.db", database)
            match_features(database, names, exhaustive_pairs(len(names)), work / "pairs", seed, False)
            for mapper in ("global", "incremental"):
                started = time.perf_counter()
                model = map_images(database, images, work / f"models_{seed}_{mapper}", len(names), mapper, 0, False)[0]
                seconds = time.perf_counter() - started
                explained, total = verified_matches_explained(database, model)
                write_json(work / f"{seed}_{mapper}" / "transforms.json", reconstruction_to_transforms(model))
                errors = compare_with_reference(work / f"{seed}_{mapper}", reference)
                results.append({"seed": seed, "mapper": mapper, "registered": model.num_reg_images(), "mapping_seconds": round(seconds, 1),
                                "mean_reprojection_error_px": round(model.compute_mean_reprojection_error(), 3),
                                "verified_matches_explained": round(explained / total, 4),
                                "median_position_error_percent_of_spread": round(errors["median_position_error_percent_of_spread"], 3),
                                "median_rotation_error_deg": round(errors["median_rotation_error_deg"], 3)})
                print(json.dumps(results[-1]), flush=True)
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, required=True, help="a capture folder with images/ and transforms.json")
    parser.add_argument("--work", type=Path, default=None, help="where to write the processed capture (default: a temporary folder)")
    parser.add_argument("--mapper", choices=("auto", "global", "incremental"), default="auto")
    parser.add_argument("--mappers-over-seeds", type=int, nargs="*", default=[], help="seeds of the mapper comparison (none: skip it)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    if not (args.root / "images").is_dir():
        print(json.dumps({"skipped": f"data not found: {args.root / 'images'}"}))
        return

    import pycolmap

    with tempfile.TemporaryDirectory() as temporary:
        work = args.work or Path(temporary) / "capture"
        report = process_capture(args.root / "images", work, mapper=args.mapper, progress=False, seed=0)
        errors = compare_with_reference(work, args.root / "transforms.json")
        seeds = mappers_over_seeds(work / "images", args.root / "transforms.json", args.mappers_over_seeds, Path(temporary)) if args.mappers_over_seeds else []
    result = {
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "images_given": report["images_given"],
        "registered": report["registered"],
        "unregistered": report["unregistered"],
        "compared_with_published": errors["compared"],
        "median_position_error_percent_of_spread": round(errors["median_position_error_percent_of_spread"], 4),
        "max_position_error_percent_of_spread": round(errors["max_position_error_percent_of_spread"], 4),
        "median_rotation_error_deg": round(errors["median_rotation_error_deg"], 4),
        "max_rotation_error_deg": round(errors["max_rotation_error_deg"], 4),
        "published_spread": round(errors["spread"], 4),
        "mean_reprojection_error_px": round(report["mean_reprojection_error_px"], 4),
        "mean_track_length": round(report["mean_track_length"], 3),
        "points": report["points"],
        "camera": report["camera"],
        "verified_matches_explained": report["verified_matches_explained"],
        "mappers": report["mappers"],
        "settings": {key: report[key] for key in ("matcher", "mapper", "camera_model", "single_camera", "max_size")},
        "seconds": report["seconds"],
        "mappers_over_seeds": seeds,
        "per_image": errors["per_image"],
        "machine": {"cpu": cpu_name(), "cores": os.cpu_count(), "python": platform.python_version(),
                    "pycolmap": pycolmap.__version__, "pycolmap_cuda": bool(getattr(pycolmap, "has_cuda", False))},
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps({key: value for key, value in result.items() if key != "per_image"}, indent=2))


if __name__ == "__main__":
    main()
