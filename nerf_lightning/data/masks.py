"""What a capture's masks (``views.masks``: True where a pixel shows the object) do in training and evaluation.

Two modes (``data.masks``):

- ``exclude`` (nerfstudio's meaning): pixels outside the mask are never drawn for the loss: random rays are drawn
  among the masked pixels, a view's or patch's loss covers its masked pixels alone. The field learns whatever it
  likes outside: right for a static scene with things to leave out (people walking by, the photographer's shadow).
- ``background``: pixels outside the mask show the scene's background colour, as Blender's alpha does, so the field
  learns the object alone over that colour: right for a turntable capture, where the room stands still while the
  object turns, so the room is not part of the object's scene and would be learnt as fog.

``ignore`` trains on the photos as they are. Left unset (``null``), a capture with masks uses ``exclude`` and one
without none. Evaluation scores the whole image (with ``background``, the object over the background colour) and
the masked pixels alone (:func:`~nerf_lightning.metrics.image_metrics` with a mask).
"""

from __future__ import annotations

import torch

MASK_MODES = ("exclude", "background", "ignore")


def resolve_mode(mode: str | None, has_masks: bool, source: str) -> str | None:
    """The mode training uses: ``mode`` checked, ``exclude`` for a capture with masks where it is None, None where
    there is nothing to do. ValueError where a mode is asked of a capture without masks, naming it."""
    if mode is not None and mode not in MASK_MODES:
        raise ValueError(f"data.masks must be one of {', '.join(MASK_MODES)} or null, got '{mode}'")
    if mode is None:
        return "exclude" if has_masks else None
    if not has_masks and mode != "ignore":
        raise ValueError(f"data.masks={mode}: {source or 'the scene'} has no masks (a transforms.json frame's 'mask_path', "
                         "an LLFF capture's masks/ folder; nerf-process-data masks=<folder> writes them); leave data.masks unset")
    return None if mode == "ignore" else mode


def composite_background(rgb: torch.Tensor, mask: torch.Tensor, background: torch.Tensor) -> torch.Tensor:
    """(..., 3) colours in [0, 1] and (...) bool masks -> the colours where masked, ``background`` elsewhere: one
    colour (3,), or one for each pixel (..., 3)."""
    return torch.where(mask[..., None], rgb, background.to(rgb))

