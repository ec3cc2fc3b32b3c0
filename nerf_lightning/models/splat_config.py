"""A splat model's config as a checkpoint written before nerf-lightning 0.4 saved it, read as 0.4 builds it: the
start's seven keys became the ``model.start`` object (:mod:`~nerf_lightning.models.splat_start`), the loss's three
the ``model.loss`` object (:class:`~nerf_lightning.splats.loss.SplatLoss`), ``sh_degree_interval`` a key of the
Gaussians, MCMC's strategy moved to :mod:`~nerf_lightning.splats.mcmc`, and the rasteriser's name, ``max_pairs`` and
``antialiased`` became the ``model.rasterizer`` object (:mod:`~nerf_lightning.splats.draw`). :func:`~nerf_lightning.checkpoints.load_model`
asks the model's class for it (``SplatModule.upgrade_config``); a config of 0.4 passes through with only the loss's
``depth_loss`` (0: none) added where it has none."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

START = "nerf_lightning.models.splat_start"
# the old keys of the random start, by what each is called now (the views' extent is their far depth)
RANDOM_KEYS = {"random_count": "count", "random_near": "near", "random_scale": "scale"}
LOSS_KEYS = ("ssim_weight", "mask_loss", "train_background")
OLD_KEYS = (*RANDOM_KEYS, "random_start", "random_extent", "triangulate", "random_beside_points", *LOSS_KEYS, "sh_degree_interval")
MOVED_TARGETS = {"nerf_lightning.splats.strategy.MCMCStrategy": "nerf_lightning.splats.mcmc.MCMCStrategy"}
# what model.rasterizer named before 0.4 (beside max_pairs and antialiased), as the object that draws now
RASTERIZER_TARGETS = {name: f"nerf_lightning.splats.draw.{kind}Rasterizer"
                      for name, kind in (("auto", "Tile"), ("tiles", "Tile"), ("pairs", "Pairs"))}


def config_before_04(model: Mapping[str, Any]) -> dict[str, Any]:
    """The model config (a plain dict, as checkpoints keep it) with the keys of before 0.4 in their 0.4 places; a key
    the old config lacks takes the new object's default."""
    model = dict(model)
    strategy = model.get("strategy")
    if isinstance(strategy, Mapping) and strategy.get("_target_") in MOVED_TARGETS:
        model["strategy"] = {**strategy, "_target_": MOVED_TARGETS[strategy["_target_"]]}
    rasterizer = model.get("rasterizer", "auto" if {"max_pairs", "antialiased"} & set(model) else None)
    if isinstance(rasterizer, str) and rasterizer in RASTERIZER_TARGETS:  # a name, or (before it had one) only its keys
        model.pop("rasterizer", None)
        model["rasterizer"] = {"_target_": RASTERIZER_TARGETS[rasterizer],
                               "max_pairs": model.pop("max_pairs", 4_000_000), "antialiased": model.pop("antialiased", False)}
    if isinstance(model.get("loss"), Mapping):  # a run of before the depth loss trained without it
        model["loss"] = {"depth_loss": 0.0, **model["loss"]}
    old = {key: model.pop(key) for key in OLD_KEYS if key in model}
    if not old:
        return model
    views = old.get("random_start", "box") == "views"
    random = {"_target_": f"{START}.{'ViewsStart' if views else 'BoxStart'}"}
    random.update({new: old[key] for key, new in RANDOM_KEYS.items() if key in old and (views or key != "random_near")})
    if "random_extent" in old:
        random["far" if views else "extent"] = old["random_extent"]
    start = {"_target_": f"{START}.{'TriangulatedStart' if old.get('triangulate') else 'SparsePointsStart'}", "random": random}
    if "random_beside_points" in old:
        start["beside"] = old["random_beside_points"]
    model.setdefault("start", start)
    model.setdefault("loss", {"_target_": "nerf_lightning.splats.loss.SplatLoss", "depth_loss": 0.0,
                              **{key: old[key] for key in LOSS_KEYS if key in old}})
    if "sh_degree_interval" in old and isinstance(model.get("gaussians"), Mapping):
        model["gaussians"] = {**model["gaussians"], "sh_degree_interval": old["sh_degree_interval"]}
    return model
