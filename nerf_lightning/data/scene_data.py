"""The base of the datamodules that serve one :class:`Scene`: loading it, its scene space, validation on whole
held-out views and render paths. Subclasses say only what a training step gets (random rays, whole views)."""

from __future__ import annotations

import inspect
import logging
from collections.abc import Callable

import torch
from torch.utils.data import DataLoader

from nerf_lightning.data.batches import HeldOutView, StepBatchesDataModule
from nerf_lightning.data.choices import OBJECT_BOXES, RENDER_PATHS
from nerf_lightning.data.image_stack import as_float_rgb
from nerf_lightning.data.masks import composite_background, resolve_mode
from nerf_lightning.data.object_box import fit_scene_to_box, visual_hull_box
from nerf_lightning.data.scene import Scene, Views, evenly_spaced
from nerf_lightning.geometry.paths import orbit_path, spiral_path
from nerf_lightning.geometry.space import SceneSpace

log = logging.getLogger(__name__)



def view_batch(views: Views, index: int, masks: str | None = None, background: torch.Tensor | None = None) -> HeldOutView:
    """One whole view (:class:`~nerf_lightning.data.batches.HeldOutView`): its camera ``K`` (3, 3), ``c2w`` (4, 4) (a
    model renders it with ``render_view``), ``image`` (H, W, 3) in [0, 1] and ``depth`` (H, W) where known;
    ``height``, ``width`` and ``index`` (in ``views``). With a ``masks`` mode (:mod:`~nerf_lightning.data.masks`) and
    masks, ``object_mask`` (H, W) bool too, and with ``background`` mode the colours outside it are ``background`` (3,)."""
    batch: HeldOutView = {"K": views.K[index], "c2w": views.c2w[index], "height": views.height, "width": views.width, "index": index}
    mask = views.masks[index] if masks is not None and views.masks is not None else None
    if views.images is not None:
        batch["image"] = as_float_rgb(views.images[index])
        if masks == "background":
            batch["image"] = composite_background(batch["image"], mask, background)
    if mask is not None:
        batch["object_mask"] = mask
    if views.depth is not None:
        batch["depth"] = views.depth[index]
    return batch


class SceneDataModule(StepBatchesDataModule):
    """A :class:`Scene` served to a model: ``setup`` loads it (``scene``) and builds its
    :class:`~nerf_lightning.geometry.space.SceneSpace` (``space``), which the model renders in; validation on a few
    whole held-out views (:func:`view_batch` each); the cameras of a render path (:meth:`render_views`).
    Subclasses implement :meth:`draw_batch` (and ``on_after_batch_transfer`` to finish a batch on the device).

    Args:
        scene: loads the :class:`Scene` (a Hydra ``_partial_`` of a loader such as ``load_blender``).
        root: the scene's folder (Blender) or file (npz), handed to ``scene`` as its first argument; None for
            scenes that need none (the procedural one).
        batch_size: samples (rays, views) per training step.
        val_views: how many held-out views to validate on (evenly spaced over the split).
        val_split: ``val`` or ``test``: which held-out split validation uses (the other when it is absent).
        render_path: ``test`` (the scene's render or test cameras), ``orbit`` or ``spiral``.
        render_frames: frames of a generated orbit or spiral.
        ndc: sample forward-facing scenes in normalised device coordinates (LLFF; cameras looking down -z).
        contract: an unbounded scene: fields see all of space contracted into [-2, 2]^3 (real captures with
            their background; the fields' and grids' ``aabb`` must be that cube).
        masks: what the capture's masks do (:mod:`~nerf_lightning.data.masks`): ``exclude`` (pixels outside never in
            the loss), ``background`` (they show the background colour: turntables), ``ignore``; None: ``exclude``
            where the capture has masks. ``mask_mode`` is the one in use after ``setup`` (None: no masks used).
        object_box: ``visual_hull``: the object's box from its masks (:mod:`~nerf_lightning.data.object_box`); the scene
            is moved and scaled so that the box lies in [-1, 1]^3, and every ray's range is cut to it (``space.bounds``).
            A field box of [-1, 1]^3 then spends its cells on the object alone. None: the scene as loaded.
        val_steps, val_every, seed: see :class:`StepBatchesDataModule`.
    """

    def __init__(
        self,
        scene: Callable[..., Scene],
        root: str | None = None,
        batch_size: int = 1,
        val_views: int = 3,
        val_split: str = "val",
        render_path: str = "test",
        render_frames: int = 60,
        ndc: bool = False,
        contract: bool = False,
        masks: str | None = None,
        object_box: str | None = None,
        val_steps: list[int] | tuple[int, ...] = (),
        val_every: int | None = 500,
        seed: int = 0,
    ) -> None:
        super().__init__(batch_size=batch_size, val_steps=val_steps, val_every=val_every, seed=seed)
        if render_path not in RENDER_PATHS:
            raise ValueError(f"data.render_path must be test, orbit or spiral, got '{render_path}'")
        self.load_scene = scene
        self.root = root
        self.val_views = val_views
        self.val_split = val_split
        self.render_path = render_path
        if object_box is not None and object_box not in OBJECT_BOXES:
            raise ValueError(f"data.object_box must be one of {', '.join(OBJECT_BOXES)} or null, got '{object_box}'")
        if object_box is not None and (ndc or contract):
            raise ValueError("data.object_box bounds the scene by its object's box: set data.contract=false and data.ndc=false "
                             "(the field's box then holds the object alone: model.field.aabb=[-1,-1,-1,1,1,1])")
        self.object_box = object_box
        self.render_frames = render_frames
        self.ndc, self.contract = ndc, contract
        self.masks = masks
        self.mask_mode: str | None = None
        self.scene: Scene | None = None
        self.space: SceneSpace | None = None
        self._on_device: dict[torch.device, tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]] = {}
        self._masks_on_device: dict[torch.device, torch.Tensor] = {}
        self._depth_on_device: dict[torch.device, torch.Tensor] = {}
        self._background_on_device: dict[torch.device, torch.Tensor] = {}

    def setup(self, stage: str | None = None) -> None:
        if self.scene is not None:
            return
        arguments = () if self.root is None else (self.root,)
        try:
            inspect.signature(self.load_scene).bind(*arguments)
        except TypeError:
            loader = getattr(getattr(self.load_scene, "func", self.load_scene), "__name__", "the scene loader")
            raise ValueError(f"data.root: {loader} " + ("needs a folder or file: set data.root" if self.root is None else "takes no data.root")) from None
        except ValueError:  # a callable without a signature: let the call say what is wrong
            pass
        scene = self.load_scene(*arguments)
        if self.object_box is not None and scene.train.masks is None:
            raise ValueError(f"data.object_box={self.object_box} needs an object's masks, and {scene.source} has none: "
                             "train without it (data.object_box=null, or a preset other than nerfacto_object_cpu)")
        self.mask_mode = resolve_mode(self.masks, scene.train.masks is not None, scene.source)
        bounds = None
        if self.object_box is not None:
            if self.mask_mode is None:
                raise ValueError(f"data.object_box={self.object_box} needs the capture's masks in use: set data.masks=background "
                                 f"(or exclude), not {self.masks}")
            covered = int(scene.train.masks.sum()) / scene.train.masks.numel()
            if covered > 0.9:  # the hull is then only where the photos' frames overlap
                log.warning("data.object_box: the masks cover %.0f%% of the photos: are they an object's outline? "
                            "(data.masks=exclude masks often mark what to leave out); the box is where the photos overlap",
                            100 * covered)
            scene, bounds = fit_scene_to_box(scene, visual_hull_box(scene.train))
        self.scene = scene
        self.space = SceneSpace.from_scene(self.scene, ndc=self.ndc, contract=self.contract, bounds=bounds)

    def cameras_and_images(self, device: torch.device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """The training cameras K (V, 3, 3), c2w (V, 4, 4) and uint8 images (V, H, W, 3) on ``device``, moved once;
        the images None where they stay on the host (a GPU with less free memory than four times their size)."""
        if device not in self._on_device:
            train = self.scene.train
            images: torch.Tensor | None = train.images
            if device.type == "cuda":
                free, _ = torch.cuda.mem_get_info(device)
                images = train.images.to(device) if train.images.numel() < free / 4 else None
            elif device.type != "cpu":
                images = train.images.to(device) if train.images.numel() < 2 * 2**30 else None
            self._on_device[device] = (train.K.to(device), train.c2w.to(device), images)
        return self._on_device[device]

    def train_masks(self, device: torch.device) -> torch.Tensor:
        """The training views' masks (V, H, W) bool on ``device`` where their images went there (see
        :meth:`cameras_and_images`), else on the host; moved once."""
        if device not in self._masks_on_device:
            on_device = self.cameras_and_images(device)[2] is not None
            self._masks_on_device[device] = self.scene.train.masks.to(device) if on_device else self.scene.train.masks
        return self._masks_on_device[device]

    def train_depth(self, device: torch.device) -> torch.Tensor | None:
        """The training views' depth (V, H, W) (:class:`~nerf_lightning.data.scene.Views`: NaN where unknown) on
        ``device`` where their images went there, else on the host; moved once. None where the scene has none."""
        if self.scene.train.depth is None:
            return None
        if device not in self._depth_on_device:
            on_device = self.cameras_and_images(device)[2] is not None
            self._depth_on_device[device] = self.scene.train.depth.to(device) if on_device else self.scene.train.depth
        return self._depth_on_device[device]

    def background_on(self, device: torch.device) -> torch.Tensor:
        """The scene's background colour (3,) on ``device``, moved once: a copy from the host at every training step
        would make the host wait for a GPU."""
        if device not in self._background_on_device:
            self._background_on_device[device] = self.scene.background.to(device)
        return self._background_on_device[device]

    def view_batch(self, views: Views, index: int) -> HeldOutView:
        """:func:`view_batch` of one of ``views`` with this datamodule's masks mode."""
        return view_batch(views, index, self.mask_mode, self.scene.background)

    def validation_views(self) -> Views:
        held_out = self.scene.held_out(self.val_split)
        return held_out.subset(evenly_spaced(len(held_out), self.val_views))

    def val_dataloader(self) -> DataLoader:
        views = self.validation_views()
        return DataLoader([self.view_batch(views, i) for i in range(len(views))], batch_size=None, num_workers=0)

    def render_views(self, path: str | None = None, n_frames: int | None = None) -> Views:
        """Cameras of a render path (no images): ``test`` (the scene's render split, else its test split),
        ``orbit`` or ``spiral`` (the scene's own path of that name, as LLFF's spiral, else ``n_frames`` frames
        around where the training cameras look)."""
        path = path or self.render_path
        n_frames = n_frames or self.render_frames
        train = self.scene.train
        if path == "test" or path in self.scene.splits:
            if path == "test":
                views = self.scene.splits.get("render") or self.scene.held_out("test")
            else:
                views = self.scene.splits[path]
            return Views(K=views.K, c2w=views.c2w, height=views.height, width=views.width, names=views.names)
        make = {"orbit": orbit_path, "spiral": spiral_path}.get(path)
        if make is None:
            raise ValueError(f"unknown render path '{path}': expected test, orbit or spiral")
        c2w = make(train.c2w, n_frames)
        return Views(K=train.K[:1].expand(n_frames, 3, 3).clone(), c2w=c2w, height=train.height, width=train.width)
