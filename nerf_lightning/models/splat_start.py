"""Where a splat model's Gaussians start, as objects ``model/start`` chooses (3DGS starts from COLMAP's sparse points,
and the synthetic scenes, which have none, from a random cube):

- :class:`SparsePointsStart` (``model/start=points``, the default): the capture's sparse points; a capture without
  them starts from its random start, ``model.start.random``;
- :class:`TriangulatedStart` (``model/start=triangulated``): the same, but a capture without sparse points (poses
  alone: instant-ngp's transforms.json, LLFF) gets them triangulated from its training views and their poses first
  (:func:`~nerf_lightning.capture.triangulate.triangulate_views_once`: COLMAP's point triangulator through pycolmap,
  the colmap extra); where pycolmap is missing or too few points come back, one warning and the random start.

The random starts (``model/start/random=box|views``): :class:`BoxStart`, uniform in a cube with random colours (3DGS's
start for the synthetic scenes), and :class:`ViewsStart`, on random training pixels' rays with their pixels' colours
(real captures, where most of a cube is never seen or lies behind the cameras: :mod:`~nerf_lightning.splats.start`).

A start is called once, when fitting starts on a new run (a resumed run's Gaussians come from its checkpoint), with
the Gaussians, the training scene and the DataModule's mask mode; it draws from a generator seeded 0, so a run's start
is the same every time. The start is what the model's first step is set up from, not what the model is: here, above
the splats, where the scene's format and the capture tools may be read.
"""

from __future__ import annotations

import logging
from typing import Protocol

import torch

from nerf_lightning.capture.choices import COLMAP_EXTRA
from nerf_lightning.data.points import SparsePoints
from nerf_lightning.data.scene import Scene, Views
from nerf_lightning.errors import MissingExtraError
from nerf_lightning.splats.gaussians import Gaussians
from nerf_lightning.splats.start import points_in_visual_hull, points_seen_by_views

log = logging.getLogger(__name__)

# fewer triangulated points than this start no Gaussians: a capture whose views barely match, for the random start
MIN_TRIANGULATED = 100


class Start(Protocol):
    def __call__(self, gaussians: Gaussians, scene: Scene, mask_mode: str | None = None) -> None: ...


class RandomStart:
    """``count`` Gaussians at random places (:meth:`place`, a subclass's), at ``scale`` times their 3 nearest
    neighbours' mean distance (None: ``gaussians.initial_scale``, which sparse points start at): a random cloud is
    denser than its detail, and below 1 it covers each pixel with fewer Gaussians while densification has not yet
    shaped them."""

    def __init__(self, count: int = 100_000, scale: float | None = None) -> None:
        if isinstance(count, bool) or not isinstance(count, int) or count < 0:
            raise ValueError(f"model.start.random.count must be an integer >= 0, got {count!r}")
        if scale is not None and scale <= 0:
            raise ValueError(f"model.start.random.scale must be > 0 (or null), got {scale}")
        self.count, self.scale = count, scale

    def __call__(self, gaussians: Gaussians, scene: Scene, mask_mode: str | None = None, said: str = "") -> None:
        generator = torch.Generator().manual_seed(0)
        positions, colours = self.place(scene, mask_mode, self.count, generator, said)
        gaussians.initialise(positions, colours, generator, scale=self.scale)

    def place(self, scene: Scene, mask_mode: str | None, count: int, generator: torch.Generator,
              said: str = "") -> tuple[torch.Tensor, torch.Tensor]:
        """``count`` random points -> positions (P, 3) in the scene's world and colours (P, 3) in [0, 1]; the log says
        where, after ``said``."""
        raise NotImplementedError


class BoxStart(RandomStart):
    """Uniform in the cube [-``extent``, ``extent``]^3 about the origin, with random colours (3DGS's start for the
    synthetic scenes, whose objects lie within it)."""

    def __init__(self, count: int = 100_000, extent: float = 1.3, scale: float | None = None) -> None:
        super().__init__(count, scale)
        if not extent > 0:
            raise ValueError(f"model.start.random.extent must be > 0, got {extent}")
        self.extent = extent

    def place(self, scene: Scene, mask_mode: str | None, count: int, generator: torch.Generator,
              said: str = "") -> tuple[torch.Tensor, torch.Tensor]:
        log.info("%s%d Gaussians start uniform in [-%g, %g]^3 with random colours", said, count, self.extent, self.extent)
        positions = (torch.rand(count, 3, generator=generator) * 2.0 - 1.0) * self.extent
        return positions, torch.rand(count, 3, generator=generator)


class ViewsStart(RandomStart):
    """On random training pixels' rays at camera depths uniform from ``near`` (None: the scene's near bound) to
    ``far`` (or the scene's far bound, if nearer), with their pixels' colours; with ``data.masks=background`` inside
    the visual hull of the masks, where fewer may come back (:mod:`~nerf_lightning.splats.start`)."""

    def __init__(self, count: int = 100_000, near: float | None = None, far: float = 1.3, scale: float | None = None) -> None:
        super().__init__(count, scale)
        self.near, self.far = near, far

    def place(self, scene: Scene, mask_mode: str | None, count: int, generator: torch.Generator,
              said: str = "") -> tuple[torch.Tensor, torch.Tensor]:
        near = float(scene.near) if self.near is None else self.near
        far = min(float(scene.far), self.far)
        if mask_mode == "background" and scene.train.masks is not None:
            positions, colours = points_in_visual_hull(scene.train, near, far, count, generator)
            log.info("%s%d Gaussians start at random inside the visual hull of the capture's masks (on masked pixels' rays at "
                     "depths %g to %g that the other views see inside their masks)", said, len(positions), near, far)
            return positions, colours
        log.info("%s%d Gaussians start at random on training pixels' rays at depths %g to %g, with their pixels' colours",
                 said, count, near, far)
        return points_seen_by_views(scene.train, near, far, count, generator)


class SparsePointsStart:
    """The capture's sparse points (:meth:`sparse_points`) at ``gaussians.initial_scale``, with ``beside`` points of
    the ``random`` start beside them at its scale (where the points miss, surfaces without features and what few
    views see, densification has nothing to grow from); a capture without them starts from ``random`` alone."""

    def __init__(self, random: RandomStart | None = None, beside: int = 0) -> None:
        if isinstance(beside, bool) or not isinstance(beside, int) or beside < 0:
            raise ValueError(f"model.start.beside must be an integer >= 0, got {beside!r}")
        self.random = BoxStart() if random is None else random
        self.beside = beside

    def __call__(self, gaussians: Gaussians, scene: Scene, mask_mode: str | None = None) -> None:
        points = self.sparse_points(scene, mask_mode)
        if points is None:
            self.random(gaussians, scene, mask_mode, "the capture has no sparse points: ")
            return
        generator = torch.Generator().manual_seed(0)
        positions, colours = points.positions, points.colours.float() / 255.0
        if self.beside == 0:
            gaussians.initialise(positions, colours, generator)
            return
        beside, beside_colours = self.random.place(scene, mask_mode, self.beside, generator, "beside the points, ")
        random_scale = gaussians.initial_scale if self.random.scale is None else self.random.scale
        scale = torch.cat([torch.full((len(positions),), gaussians.initial_scale), torch.full((len(beside),), random_scale)])
        gaussians.initialise(torch.cat([positions, beside]), torch.cat([colours, beside_colours]), generator, scale=scale)

    def sparse_points(self, scene: Scene, mask_mode: str | None) -> SparsePoints | None:
        """The capture's sparse points, or None where it has none."""
        points = scene.points
        if points is None or len(points) == 0:
            return None
        log.info("Gaussians start from the capture's %d sparse points", len(points))
        return points


class TriangulatedStart(SparsePointsStart):
    """:class:`SparsePointsStart` for a capture with poses but no sparse points: they are triangulated from its
    training views and their poses first (inside the masks where the views have them), and kept in
    ``$NERF_LIGHTNING_CACHE/triangulated`` (default ``~/.cache/nerf_lightning``) under a digest of the training views:
    later runs on the same views load them, not match again."""

    def sparse_points(self, scene: Scene, mask_mode: str | None) -> SparsePoints | None:
        points = super().sparse_points(scene, mask_mode)
        return triangulated_points(scene.train, masks=mask_mode is not None) if points is None else points


def triangulated_points(views: Views, masks: bool = True) -> SparsePoints | None:
    """The sparse points triangulated from the training ``views`` and their poses (with ``masks``, inside the views'
    masks, where they have them), kept in the cache for the next run on the same views
    (:func:`~nerf_lightning.capture.triangulate.triangulate_views_once`); None, after one warning saying why, where
    pycolmap is missing, fails, or fewer than :data:`MIN_TRIANGULATED` points come back (the random start follows)."""
    try:
        from nerf_lightning.capture.triangulate import triangulate_views_once

        points, report = triangulate_views_once(views, masks=masks)
    except MissingExtraError:
        log.warning("model/start=triangulated needs pycolmap, the colmap extra (%s); the Gaussians start at random instead",
                    COLMAP_EXTRA)
        return None
    except (RuntimeError, ValueError, IndexError, KeyError) as error:  # what pycolmap raises where COLMAP gives up
        log.warning("model/start=triangulated: COLMAP could not triangulate the %d training views (%s: %s); the Gaussians start "
                    "at random instead", len(views), type(error).__name__, error)
        return None
    if len(points) < MIN_TRIANGULATED:
        log.warning("model/start=triangulated: only %d points triangulated from the %d training views (%s); the Gaussians "
                    "start at random instead", len(points), len(views), report["matches"])
        return None
    took = ", ".join(f"{stage} {value:.0f} s" for stage, value in report["seconds"].items())
    if "cached" in report:  # the same training views triangulated by an earlier run
        took = f"loaded from {report['cached']}: an earlier run on the same views made them in {sum(report['seconds'].values()):.0f} s"
    log.info("the capture has no sparse points: %d triangulated from its %d training views and their poses (%s), reprojected "
             "within %.2f px on average; the Gaussians start there", len(points), len(views), took,
             report["mean_reprojection_error_px"])
    return points
