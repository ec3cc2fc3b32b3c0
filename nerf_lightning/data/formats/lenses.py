"""The lens of a ``transforms.json`` frame (its ``camera_model`` and coefficients) and the undistortion of its photo
onto a pinhole camera, so that everything after the loader sees pinhole views.

``camera_model`` (per frame, else the json's, else ``OPENCV``) is one of COLMAP's names for the models nerfstudio and
COLMAP write; any other is refused by name:

- ``SIMPLE_PINHOLE``, ``PINHOLE``, ``SIMPLE_RADIAL``, ``RADIAL``, ``OPENCV``: Brown-Conrady, OpenCV's ``k1``, ``k2``,
  ``p1``, ``p2``, ``k3`` (each 0 where the json leaves it out). Undone by kornia onto the photo's own K.
- ``OPENCV_FISHEYE``: Kannala-Brandt (equidistant), ``k1`` to ``k4``, every one required. A ray at angle theta off
  the optical axis lands at distance theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8) (in
  focal lengths) from the principal point, where a pinhole puts it at tan(theta).

The fisheye's pinhole view (:meth:`FisheyeLens.pinhole`) keeps the photo's size, principal point and focal length, so
its centre keeps the photo's resolution and the fisheye's rim beyond the pinhole's field of view is cropped. A
fisheye squeezes (theta_d <= tan(theta)), so every pixel of that view lies inside the photo; for a lens that does
not (a rectilinear lens with pincushion distortion fitted with this model), the focal length is lengthened just
enough that it does: no pixel of an undistorted view is made up.

Pixels follow the project's convention (:mod:`~nerf_lightning.geometry.cameras`), pixel (i, j)'s centre at
(j + 0.5, i + 0.5), COLMAP's too.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import kornia
import torch
from kornia.geometry.camera import distort_points_kannala_brandt, undistort_points_kannala_brandt

from nerf_lightning.geometry.rays import image_pixels

# camera_model: the models read with OpenCV's coefficients (COLMAP's simpler models are special cases of OPENCV)
OPENCV_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
FISHEYE_MODELS = ("OPENCV_FISHEYE",)
CAMERA_MODELS = OPENCV_MODELS + FISHEYE_MODELS
OPENCV_KEYS = ("k1", "k2", "p1", "p2", "k3")  # OpenCV's order
FISHEYE_KEYS = ("k1", "k2", "k3", "k4")


@dataclass(frozen=True)
class OpenCVLens:
    """Brown-Conrady distortion: ``coefficients`` k1, k2, p1, p2, k3 (OpenCV's order)."""

    coefficients: tuple[float, float, float, float, float]

    def distorts(self) -> bool:
        return any(self.coefficients)

    def pinhole(self, K: torch.Tensor, height: int, width: int) -> tuple[torch.Tensor, OpenCVLens]:
        """The photo's K (3, 3) -> the K (3, 3) of its undistorted view of the same size (the same K), and the lens."""
        return K, self

    def undistort(self, image: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
        """(H, W, C) photo -> (H, W, C) pinhole view of K (3, 3), by kornia (its pixel centres at integers, as this
        loader has always read OpenCV lenses)."""
        distortion = torch.tensor(self.coefficients, dtype=image.dtype)
        chw = image.permute(2, 0, 1)[None]
        return kornia.geometry.calibration.undistort_image(chw, K[None].to(image.dtype), distortion[None])[0].permute(1, 2, 0)


@dataclass(frozen=True)
class FisheyeLens:
    """Kannala-Brandt (OpenCV's fisheye) distortion: ``coefficients`` k1 to k4; ``photo`` the photo's fx, fy, cx, cy
    once :meth:`pinhole` has placed it in a photo of known size (None before)."""

    coefficients: tuple[float, float, float, float]
    photo: tuple[float, float, float, float] | None = None

    def distorts(self) -> bool:
        return True  # even k1..k4 = 0 is the equidistant fisheye, not a pinhole

    def parameters(self, K: torch.Tensor) -> torch.Tensor:
        """(8,) float64 [fx, fy, cx, cy, k1, k2, k3, k4] of the photo of K (3, 3), as kornia's Kannala-Brandt takes them."""
        return torch.tensor([float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), *self.coefficients], dtype=torch.float64)

    def pinhole(self, K: torch.Tensor, height: int, width: int) -> tuple[torch.Tensor, FisheyeLens]:
        """The photo's K (3, 3) and size -> the K (3, 3) of its pinhole view of the same size, and the lens placed in
        that photo. The view keeps K where each of its border pixels, seen through the lens, lands inside the photo;
        else its focal lengths are multiplied by the least factor that makes them land there (the module's docstring).

        A border pixel p at normalised radius r (its offset from the principal point in focal lengths) looks along
        tan(theta) = r / s in a view of focal s f, and lands at theta_d(theta) along the same line in the photo: inside
        where theta <= theta_d^-1(r), that is s >= r / tan(theta_d^-1(r)), and tan(theta_d^-1(r)) is the radius of p
        undistorted (kornia's Gauss-Newton inverse). Pixels the lens sees at 90 degrees or more off axis land inside
        at any focal (theta < 90 degrees in a pinhole)."""
        parameters = self.parameters(K)
        centres = image_pixels(height, width).double().reshape(height, width, 2)
        border = torch.cat([centres[0], centres[-1], centres[:, 0], centres[:, -1]])  # (2 (H + W), 2)
        radius = ((border - parameters[2:4]) / parameters[:2]).norm(dim=-1)
        looks_along = undistort_points_kannala_brandt(border, parameters).norm(dim=-1)  # tan(theta_d^-1(radius))
        in_front = (radius > 0) & (radius < float(fisheye_radius(torch.tensor(math.pi / 2), self.coefficients)))
        scale = max(1.0, float((radius[in_front] / looks_along[in_front]).max())) if in_front.any() else 1.0
        pinhole_K = K.clone()
        pinhole_K[0, 0], pinhole_K[1, 1] = scale * K[0, 0], scale * K[1, 1]
        return pinhole_K, FisheyeLens(self.coefficients, tuple(float(value) for value in parameters[:4]))

    def undistort(self, image: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
        """(H, W, C) photo -> (H, W, C) pinhole view of K (3, 3) (:meth:`pinhole`'s): each pixel's ray through the
        lens to the photo (kornia's Kannala-Brandt), sampled there bilinearly."""
        if self.photo is None:
            raise RuntimeError("FisheyeLens.undistort: the lens has no photo yet: undistort with the lens pinhole() returns")
        height, width = image.shape[:2]
        K = K.double()
        on_plane = (image_pixels(height, width).double().reshape(height, width, 2) - K[:2, 2]) / K.diagonal()[:2]  # on z = 1
        # float32 lands within a thousandth of a pixel of float64 across a 4K photo
        source = distort_points_kannala_brandt(on_plane.float(), torch.tensor([*self.photo, *self.coefficients]))
        grid = source / torch.tensor([width, height]) * 2.0 - 1.0  # align_corners=False: the photo's edges at -1 and 1
        sampled = torch.nn.functional.grid_sample(image.permute(2, 0, 1)[None].float(), grid[None], mode="bilinear",
                                                  padding_mode="border", align_corners=False)
        return sampled[0].permute(1, 2, 0).to(image.dtype)


Lens = OpenCVLens | FisheyeLens


def fisheye_radius(theta: torch.Tensor, coefficients: tuple[float, float, float, float]) -> torch.Tensor:
    """theta_d (...,): where rays at ``theta`` (...,) radians off axis land, in focal lengths from the principal point."""
    k1, k2, k3, k4 = coefficients
    squared = theta * theta
    return theta * (1.0 + squared * (k1 + squared * (k2 + squared * (k3 + squared * k4))))


def read_lens(model: object, number: Callable[[str], float | None], source: str) -> Lens:
    """The lens a frame's ``camera_model`` names, its coefficients read by ``number(key)`` (the key's finite value,
    None where the frame and the json leave it out). ValueError naming ``source`` (the file and frame) and the key:
    an unknown ``camera_model``, or an ``OPENCV_FISHEYE`` without one of ``k1`` to ``k4`` or with ``p1`` or ``p2``."""
    if model in OPENCV_MODELS:
        return OpenCVLens(tuple(number(key) or 0.0 for key in OPENCV_KEYS))
    if model not in FISHEYE_MODELS:
        raise ValueError(f"{source}'camera_model' is {model!r}: this loader reads {', '.join(CAMERA_MODELS)}")
    coefficients = {key: number(key) for key in FISHEYE_KEYS}
    missing = [key for key, value in coefficients.items() if value is None]
    if missing:
        raise ValueError(f"{source}'camera_model' {model} needs {', '.join(FISHEYE_KEYS)}: "
                         f"{', '.join(repr(key) for key in missing)} missing")
    tangential = [key for key in ("p1", "p2") if number(key)]
    if tangential:
        raise ValueError(f"{source}'camera_model' {model} has no tangential terms, but {' and '.join(repr(key) for key in tangential)} "
                         "is not 0 (a lens with them is OPENCV)")
    return FisheyeLens(tuple(coefficients[key] for key in FISHEYE_KEYS))
