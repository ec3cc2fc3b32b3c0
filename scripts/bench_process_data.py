"""nerf-process-data on a capture with published poses (fox's 50 photos, or the procedural turntable): how many
register, how far the recovered cameras are from the published ones after a similarity alignment, and the seconds
of each stage.

    .venv/bin/python scripts/bench_process_data.py [--root ../shared/data/nerfstudio/fox | --turntable] [--images images]
        [--masks [masks]] [--mask-change erode:N|dilate:N] [--photo-change dark:F] [--mapper auto] [--photos N] [--max-size 1600]
        [--offset K] [--repeat] [--shuffle] [--mappers-over-seeds 0 1 2 3] [--work DIR]
        [--out FILE.json] [-- more process_capture keys as key=value]

A masked object capture with the photographer's LLFF poses (moldGoldCape, at 912 px):

    .venv/bin/python scripts/bench_process_data.py --root ../shared/data/masked_objects/moldGoldCape --images images_4 \
        --masks masks_4

``--turntable``: the procedural turntable capture (rendered into the temporary folder; its reference poses are the
cameras relative to the object). ``--images``: the photos' folder under ``--root`` (images); ``--masks [FOLDER]``:
hand ``<root>/<FOLDER>`` (masks) to the command (``masks=``); ``--mask-change erode:N`` or ``dilate:N``: those masks
eroded or dilated by N pixels of their own size first (a rougher mask than the photographer's, as a user's often is);
``--photo-change dark:F``: the photos' values times F first, their EXIF kept (a darker subject, as dark bronze is:
less contrast for SIFT's detector, whose threshold is on absolute contrast).
The published poses are ``<root>/transforms.json``, or
``<root>/poses_bounds.npy`` (LLFF: a row a photo in name order). The results table's
posing rows are these JSONs: ``--out docs/results/posing/<name>.json``, then ``nerf-bench report``.

The command's own settings (:func:`nerf_lightning.capture.process_capture`): one shared OPENCV camera, features
read at ``--max-size`` px on the long side (1600), 8192 SIFT features an image, exhaustive matching (under 100
images), ``--mapper`` (auto: both mappers, the model that explains more verified matches kept), seed 0. The photos are
``<root>/<--images>`` (``--photos N``: N of them, evenly spaced by name, for a quick run, ``--offset K`` from the
K-th on; ``--repeat``: the first of them twice; ``--shuffle``: named in a shuffled order: the cases the pose checks
are calibrated on); the capture is written to ``--work`` (a temporary folder by default). Position errors are
percentages of the published cameras' spread (the root mean square distance of their centres from their mean).

``--mappers-over-seeds``: then, on the same images, features once and for each seed the matching (its RANSAC seeded)
and both mappers, global and incremental, each compared with the published poses and scored by the fraction of
verified matches its poses explain (what ``mapper=auto`` keeps the better model by): how often each mapper places the
cameras as published, and whether the score picks the right one.

Prints the JSON (and writes it with ``--out``); exits 0 with ``{"skipped": ...}`` when the capture or pycolmap (the
colmap extra) is missing.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import torch
import yaml

from nerf_lightning.bench.micro import SHARED_DATA, finish, seed_everything, skip, start_result
from nerf_lightning.data.scene import evenly_spaced
from nerf_lightning.io import write_json


def mappers_over_seeds(images: Path, reference: Path, seeds: list[int], work: Path, max_size: int) -> list[dict]:
    """For each seed: the matches verified with that RANSAC seed, then each mapper, compared with ``reference``."""
    from nerf_lightning.capture import compare_with_reference
    from nerf_lightning.capture.colmap import colmap_log, exhaustive_pairs, extract_features, match_features
    from nerf_lightning.capture.reconstruction import map_images, reconstruction_to_transforms, verified_matches_explained

    names = sorted(path.name for path in images.iterdir())
    results = []
    with colmap_log(False):
        extract_features(work / "features.db", images, names, "OPENCV", True, max_size, 8192, False)
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
                results.append({"seed": seed, "mapper": mapper, "registered": model.num_reg_images(), "mapping_seconds": round(seconds, 2),
                                "mean_reprojection_error_px": model.compute_mean_reprojection_error(),
                                "verified_matches_explained": explained / total,
                                "median_position_error_percent_of_spread": errors["median_position_error_percent_of_spread"],
                                "median_rotation_error_deg": errors["median_rotation_error_deg"]})
                print(json.dumps(results[-1]), file=sys.stderr, flush=True)
    return results


def chosen_photos(images: Path, count: int | None, folder: Path, offset: int = 0, repeat: bool = False,
                  shuffle: bool = False) -> tuple[Path, dict[str, str]]:
    """``images`` itself, or ``count`` of its photos, evenly spaced by name from the ``offset``-th on, copied into
    ``folder``; ``repeat``: the first chosen photo once more as ``<stem>_again``; ``shuffle``: the copies named in a
    shuffled order (``photo_<k>``). Returns the folder and each copy's stem -> its photo's stem (for the comparison)."""
    names = sorted(path.name for path in images.iterdir() if path.is_file())
    if count is None and not (repeat or shuffle or offset):
        return images, {}
    picked = [names[(index + offset) % len(names)] for index in evenly_spaced(len(names), count or len(names))]
    copies = [(name, name) for name in picked]
    if repeat:
        copies.append((picked[0], f"{Path(picked[0]).stem}_again{Path(picked[0]).suffix}"))
    if shuffle:
        order = torch.randperm(len(copies), generator=torch.Generator().manual_seed(0)).tolist()
        copies = [(photo, f"photo_{order[k]:03d}{Path(photo).suffix}") for k, (photo, _) in enumerate(copies)]
    folder.mkdir(parents=True)
    for photo, copy in copies:
        shutil.copy(images / photo, folder / copy)
    return folder, {Path(copy).stem: Path(photo).stem for photo, copy in copies}


def named_as_photos(work: Path, stems: dict[str, str], folder: Path) -> Path:
    """``work``'s transforms.json with each frame named by its photo's stem (a copy in ``folder``), for the
    comparison with the published poses; a repeated photo's copy left out (its photo is compared once)."""
    transforms = json.loads((work / "transforms.json").read_text())
    frames, seen = [], set()
    for frame in transforms["frames"]:
        stem = Path(frame["file_path"]).stem
        photo = stems.get(stem, stem)
        if photo in seen:  # a repeated photo's second copy, however it was named
            continue
        seen.add(photo)
        frames.append({**frame, "file_path": f"images/{photo}{Path(frame['file_path']).suffix}"})
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "transforms.json").write_text(json.dumps({**transforms, "frames": frames}))
    return folder


def changed_masks(masks: Path, change: str, folder: Path) -> Path:
    """``masks`` (white: the object, read as ``nerf-process-data`` reads them) eroded (``erode:N``) or dilated
    (``dilate:N``) by N pixels, written into ``folder``."""
    import imageio.v3 as iio
    import numpy as np
    import torch

    from nerf_lightning.capture.images import read_mask

    kind, _, size = change.partition(":")
    if kind not in ("erode", "dilate") or not size.isdigit():
        raise SystemExit(f"--mask-change must be erode:N or dilate:N (N pixels), got {change!r}")
    folder.mkdir(parents=True)
    for path in sorted(masks.iterdir()):
        white = torch.from_numpy(read_mask(path)).float()[None, None]
        window = 2 * int(size) + 1
        if kind == "dilate":
            white = torch.nn.functional.max_pool2d(white, window, stride=1, padding=int(size))
        else:
            white = 1.0 - torch.nn.functional.max_pool2d(1.0 - white, window, stride=1, padding=int(size))
        iio.imwrite(folder / f"{path.stem}.png", (white[0, 0].numpy() * 255).astype(np.uint8))
    return folder


def changed_photos(images: Path, change: str, folder: Path) -> Path:
    """The photos of ``images`` with their values times F (``dark:F``, 0 < F <= 1), written into ``folder`` as JPEGs
    with their EXIF (the focal length prior comes from it)."""
    import numpy as np
    from PIL import Image

    kind, _, factor = change.partition(":")
    try:
        factor = float(factor)
    except ValueError:
        factor = -1.0
    if kind != "dark" or not 0.0 < factor <= 1.0:
        raise SystemExit(f"--photo-change must be dark:F with 0 < F <= 1, got {change!r}")
    folder.mkdir(parents=True)
    for path in sorted(p for p in images.iterdir() if p.is_file()):
        with Image.open(path) as photo:
            exif = photo.info.get("exif", b"")
            darker = np.round(np.asarray(photo.convert("RGB"), dtype=np.float32) * factor).astype(np.uint8)
        Image.fromarray(darker).save(folder / path.name, format="JPEG", quality=95, exif=exif)
    return folder


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog="\n".join(__doc__.splitlines()[1:]))
    parser.add_argument("--root", type=Path, default=SHARED_DATA / "nerfstudio" / "fox", help="a capture folder with images/ and transforms.json (default: fox)")
    parser.add_argument("--turntable", action="store_true", help="the procedural turntable capture instead of --root")
    parser.add_argument("--images", default="images", help="the photos' folder under --root (default images)")
    parser.add_argument("--masks", nargs="?", const="masks", default=None, help="give the command <root>/MASKS (masks=; default masks)")
    parser.add_argument("--mask-change", default=None, help="erode:N or dilate:N: the masks eroded or dilated by N pixels first")
    parser.add_argument("--photo-change", default=None, help="dark:F: the photos' values times F first (0 < F <= 1)")
    parser.add_argument("--mapper", choices=("auto", "global", "incremental"), default="auto")
    parser.add_argument("--photos", type=int, default=None, help="only this many photos, evenly spaced by name (default all)")
    parser.add_argument("--offset", type=int, default=0, help="with --photos: start the evenly spaced pick this many photos on")
    parser.add_argument("--repeat", action="store_true", help="hand the first chosen photo twice (a repeated photo)")
    parser.add_argument("--shuffle", action="store_true", help="name the photos in a shuffled order (photo_<k>)")
    parser.add_argument("--max-size", type=int, default=1600, help="the long side the features are read at (default 1600, the command's)")
    parser.add_argument("--mappers-over-seeds", type=int, nargs="*", default=[], help="seeds of the mapper comparison (none: skip it)")
    parser.add_argument("--work", type=Path, default=None, help="where to write the processed capture (default: a temporary folder)")
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    parser.add_argument("settings", nargs="*", help="more process_capture keys, key=value (a number or a word)")
    args = parser.parse_args()
    settings = {key: yaml.safe_load(value) for key, value in (item.split("=", 1) for item in args.settings)}
    temporary = tempfile.TemporaryDirectory(prefix="bench_process_data_")
    if args.turntable:
        from nerf_lightning.data.formats import make_turntable_capture

        args.root = make_turntable_capture(Path(temporary.name) / "turntable")
    reference = args.root / "transforms.json" if (args.root / "transforms.json").is_file() else args.root / "poses_bounds.npy"
    if not (args.root / args.images).is_dir() or not reference.is_file():
        skip(f"data not found: {args.root} ({args.images}/ and transforms.json or poses_bounds.npy)")
    if importlib.util.find_spec("pycolmap") is None:
        skip("pycolmap (the colmap extra) is not installed: pip install nerf-lightning[colmap]")
    if args.photos is not None and args.photos < 3:
        raise SystemExit("--photos must be 3 or more (the cameras are compared after a similarity alignment)")
    seed_everything(0)

    import pycolmap

    from nerf_lightning.capture import compare_with_reference, process_capture

    with temporary:
        temporary = temporary.name
        images, stems = chosen_photos(args.root / args.images, args.photos, Path(temporary) / "photos", args.offset, args.repeat, args.shuffle)
        if args.photo_change:
            images = changed_photos(images, args.photo_change, Path(temporary) / "changed_photos")
        work = args.work or Path(temporary) / "capture"
        masks = args.root / args.masks if args.masks else None
        if masks is not None and args.mask_change:
            masks = changed_masks(masks, args.mask_change, Path(temporary) / "masks")
        started = time.perf_counter()
        head = {**start_result("cpu"), "benchmark": "process_data", "root": str(args.root),
                "capture": "procedural turntable" if args.turntable else args.root.name, "images": args.images,
                "masks": args.masks, "mask_change": args.mask_change, "photo_change": args.photo_change, "photos": args.photos,
                "offset": args.offset, "repeat": args.repeat, "shuffle": args.shuffle, "process_capture": settings}
        try:  # min_registered=0, min_mask_agreement=0, check_poses=false: the photos that register are compared, however few, however wrong
            report = process_capture(images, work, mapper=args.mapper, max_size=args.max_size, progress=False, seed=0, masks=masks,
                                     **{"min_registered": 0.0, "min_mask_agreement": 0.0, "check_poses": False, **settings})
        except ValueError as error:  # fewer than 3 registered: nothing to compare, which is the finding
            finish({**head, "images_given": len(list(images.iterdir())), "registered": None, "failed": str(error),
                    "total_s": time.perf_counter() - started}, args.out)
            return
        total = time.perf_counter() - started
        errors = compare_with_reference(named_as_photos(work, stems, Path(temporary) / "named") if stems else work, reference)
        seeds = (mappers_over_seeds(work / "images", reference, args.mappers_over_seeds, Path(temporary), args.max_size)
                 if args.mappers_over_seeds else [])
    result = {
        **head, "pycolmap": pycolmap.__version__, "pycolmap_cuda": bool(getattr(pycolmap, "has_cuda", False)),
        "images_given": report["images_given"], "registered": report["registered"], "unregistered": report["unregistered"],
        "compared_with_published": errors["compared"], "aligned_on": errors["aligned_on"],
        **{key: errors[key] for key in ("median_position_error_percent_of_spread", "max_position_error_percent_of_spread",
                                        "median_rotation_error_deg", "max_rotation_error_deg")},
        "published_spread": errors["spread"],
        **{key: report[key] for key in ("mean_reprojection_error_px", "mean_track_length", "points", "camera", "verified_matches_explained", "mappers",
                                            "matches", "focal_priors")},
        "settings": {key: report[key] for key in ("matcher", "mapper", "camera_model", "single_camera", "max_size")},
        # with masks: the masks' agreement with the poses, which nerf-process-data stops on under min_mask_agreement
        "silhouettes": {key: value for key, value in report["silhouettes"].items() if key != "coverage"} if "silhouettes" in report else None,
        "escalated": report.get("escalated"),
        # the checks that need no masks (nerf-process-data stops on their flags unless check_poses=false)
        "pose_checks": report.get("pose_checks"),
        "total_s": total, "seconds": report["seconds"],
        "mappers_over_seeds": seeds, "per_image": errors["per_image"],
    }
    finish(result, args.out)


if __name__ == "__main__":
    main()
