"""Benchmark suites: YAML files listing scene x preset x training minutes (x seeds) rows.

A suite file (the shipped ones are ``nerf_lightning/bench/suites/<name>.yaml``)::

    device: cpu                 # where to train and evaluate: cpu, auto, cuda, mps
    marks: [1, 2, 5, 10]        # minutes of training at which a checkpoint is kept and scored (the curve)
    seeds: [0]
    rows:
      - {scene: lego, data: nerf_synthetic/lego, preset: fast_blender, minutes: 10, overrides: [trainer.max_steps=200000]}

A row's ``data`` is a folder (or file) under the data directory (``--data-dir``), passed as ``data.root``; a row
without it trains on its preset's own scene (the built-in procedural one). ``marks``, ``seeds``, ``device`` and
``eval_views`` (held-out views scored, evenly spaced; null: all) may be set for the suite or a row.
"""

from __future__ import annotations

import fnmatch
from dataclasses import dataclass, field
from importlib.resources import files
from pathlib import Path
from typing import Any

import yaml

SUITE_KEYS = {"device", "marks", "seeds", "eval_views", "rows"}
ROW_KEYS = {"scene", "preset", "minutes", "data", "overrides", "marks", "seeds", "device", "eval_views"}


class SuiteError(ValueError):
    """A suite file that cannot be run: the message names the file, the row and the key."""


@dataclass(frozen=True)
class Row:
    """One benchmark: ``preset`` trained on ``scene`` for ``minutes`` of training time with ``seed``, checkpoints
    kept at ``marks`` (minutes) and each scored on the held-out views."""

    scene: str
    preset: str
    minutes: float
    seed: int = 0
    data: str | None = None
    overrides: tuple[str, ...] = ()
    marks: tuple[float, ...] = ()
    device: str = "cpu"
    eval_views: int | None = None

    @property
    def id(self) -> str:
        """``scene/preset/<minutes>min/seed<seed>``: what ``--only`` matches and ``--resume`` skips by."""
        return f"{self.scene}/{self.preset}/{self.minutes:g}min/seed{self.seed}"

    @property
    def slug(self) -> str:
        """The row's id as one folder name."""
        return self.id.replace("/", "_")


@dataclass
class Suite:
    name: str
    path: Path
    rows: list[Row] = field(default_factory=list)

    def select(self, patterns: list[str] | None) -> list[Row]:
        """The rows whose id matches any of the glob ``patterns`` (``lego/*``, ``*/fast_blender/*``); all without any."""
        if not patterns:
            return list(self.rows)
        chosen = [row for row in self.rows if any(fnmatch.fnmatch(row.id, p) or fnmatch.fnmatch(row.id, p + "/*") for p in patterns)]
        if not chosen:
            ids = ", ".join(row.id for row in self.rows)
            raise SuiteError(f"--only {' '.join(patterns)} matches no row of suite '{self.name}'; its rows: {ids}")
        return chosen


def shipped_suites() -> dict[str, Path]:
    """The suites that come with the package: name -> file."""
    folder = files("nerf_lightning.bench") / "suites"
    return {Path(entry.name).stem: Path(str(entry)) for entry in folder.iterdir() if entry.name.endswith(".yaml")}


def _marks(value: Any, where: str, minutes: float) -> tuple[float, ...]:
    if value is None:
        return (float(minutes),)
    if not isinstance(value, list) or not all(isinstance(m, (int, float)) and m > 0 for m in value):
        raise SuiteError(f"{where}: marks must be a list of minutes > 0, got {value!r}")
    # marks past the row's minutes would only repeat its last weights; the row's end is always a mark
    return tuple(sorted({float(m) for m in value if m < minutes} | {float(minutes)}))


def load_suite(name_or_path: str) -> Suite:
    """A shipped suite by name (``cpu-quick``, ``cpu``, ``gpu``) or a suite file by path; unknown keys, missing ones
    and wrong types are refused naming the file, the row and the key."""
    shipped = shipped_suites()
    path = shipped.get(name_or_path) or Path(name_or_path)
    if not path.is_file():
        raise SuiteError(f"no suite '{name_or_path}': expected one of {', '.join(sorted(shipped))} or a suite .yaml file")
    try:
        spec = yaml.safe_load(path.read_text())
    except yaml.YAMLError as error:
        raise SuiteError(f"{path} is not valid YAML: {error}") from None
    if not isinstance(spec, dict) or not isinstance(spec.get("rows"), list) or not spec["rows"]:
        raise SuiteError(f"{path}: expected a mapping with a non-empty list 'rows' of {{scene, preset, minutes, ...}}")
    unknown = set(spec) - SUITE_KEYS
    if unknown:
        raise SuiteError(f"{path}: unknown key(s) {', '.join(sorted(unknown))}; a suite has {', '.join(sorted(SUITE_KEYS))}")
    rows = []
    for index, entry in enumerate(spec["rows"]):
        where = f"{path} row {index + 1}"
        if not isinstance(entry, dict):
            raise SuiteError(f"{where}: expected a mapping {{scene, preset, minutes, ...}}, got {entry!r}")
        unknown = set(entry) - ROW_KEYS
        missing = {"scene", "preset", "minutes"} - set(entry)
        if unknown or missing:
            problem = f"unknown key(s) {', '.join(sorted(unknown))}" if unknown else f"missing {', '.join(sorted(missing))}"
            raise SuiteError(f"{where}: {problem}; a row has {', '.join(sorted(ROW_KEYS))}")
        minutes = entry["minutes"]
        if not isinstance(minutes, (int, float)) or minutes <= 0:
            raise SuiteError(f"{where}: minutes must be a number > 0, got {minutes!r}")
        overrides = entry.get("overrides") or []
        if not isinstance(overrides, list) or not all(isinstance(o, str) and "=" in o for o in overrides):
            raise SuiteError(f"{where}: overrides must be a list of Hydra overrides key=value, got {overrides!r}")
        seeds = entry.get("seeds", spec.get("seeds", [0]))
        if not isinstance(seeds, list) or not seeds or not all(isinstance(s, int) for s in seeds):
            raise SuiteError(f"{where}: seeds must be a non-empty list of integers, got {seeds!r}")
        eval_views = entry.get("eval_views", spec.get("eval_views"))
        if eval_views is not None and (not isinstance(eval_views, int) or eval_views < 1):
            raise SuiteError(f"{where}: eval_views must be a number of views >= 1 or null (all), got {eval_views!r}")
        for seed in seeds:
            rows.append(Row(
                scene=str(entry["scene"]), preset=str(entry["preset"]), minutes=float(minutes), seed=seed,
                data=entry.get("data"), overrides=tuple(overrides), marks=_marks(entry.get("marks", spec.get("marks")), where, minutes),
                device=str(entry.get("device", spec.get("device", "cpu"))), eval_views=eval_views,
            ))
    ids = [row.id for row in rows]
    twice = sorted({i for i in ids if ids.count(i) > 1})
    if twice:
        raise SuiteError(f"{path}: rows {', '.join(twice)} appear twice")
    return Suite(name=path.stem, path=path, rows=rows)
