"""How ``nerf-process-data`` poses a capture: :func:`~nerf_lightning.capture.process.process_capture`'s settings in one
object, checked once, that the stages (the images in, the posing passes, the checks that stop a run) read."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from nerf_lightning.capture.choices import CAMERA_MODELS, MAPPERS, MASK_OBJECTS, MATCHERS


@dataclass(frozen=True)
class CaptureSettings:
    """:func:`~nerf_lightning.capture.process.process_capture`'s arguments of the same names (see its docstring for
    each), but the input, the output and the masks' folder; as given, not yet checked (:meth:`check`)."""

    frames: int = 100
    matcher: str = "auto"
    mapper: str = "auto"
    camera_model: str = "OPENCV"
    single_camera: bool = True
    max_size: int = 1600
    max_features: int = 8192
    downscales: Sequence[int] = (2, 4, 8)
    min_registered: float = 0.5
    escalate: bool = True
    seed: int = 0
    min_mask_agreement: float = 0.7
    check_poses: bool = True
    mask_object: str = "white"
    progress: bool = True
    verbose: bool = False

    def check(self) -> None:
        """ValueError, one line naming the setting, where one is not a value it can take."""
        if self.matcher not in MATCHERS:
            raise ValueError(f"matcher must be one of {', '.join(MATCHERS)}, got '{self.matcher}'")
        if self.mapper not in MAPPERS:
            raise ValueError(f"mapper must be one of {', '.join(MAPPERS)}, got '{self.mapper}'")
        if self.camera_model not in CAMERA_MODELS:
            raise ValueError(f"camera_model must be one of {', '.join(CAMERA_MODELS)}, got '{self.camera_model}'")
        if int(self.max_size) < 64:
            raise ValueError(f"max_size must be at least 64 pixels, got {self.max_size}")
        if any(int(factor) != factor or factor < 2 for factor in self.downscales):
            raise ValueError(f"downscales must be integers of 2 or more, got {list(self.downscales)}")
        if not 0.0 <= self.min_registered <= 1.0:
            raise ValueError(f"min_registered must be a fraction between 0 and 1, got {self.min_registered}")
        if self.mask_object not in MASK_OBJECTS:
            raise ValueError(f"mask_object must be {' or '.join(MASK_OBJECTS)}, got '{self.mask_object}'")
        if not 0.0 <= self.min_mask_agreement <= 1.0:
            raise ValueError(f"min_mask_agreement must be a fraction between 0 and 1, got {self.min_mask_agreement}")
