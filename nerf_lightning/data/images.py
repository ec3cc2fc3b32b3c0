"""Reading images and the built-in test image.

An image is read as a float tensor (H, W, 3) in [0, 1]; a scene's views keep theirs as uint8
(:mod:`~nerf_lightning.data.image_stack`).
"""

from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch
import torch.nn.functional as F


def read_pixels(path: Path, what: str) -> np.ndarray:
    """The pixels of an image file as imageio reads them; FileNotFoundError or ValueError naming the file (as an
    ``image`` or a ``mask``: ``what``) when it is missing or cannot be read."""
    if not path.is_file():
        raise FileNotFoundError(f"{what} file not found: {path}")
    try:
        return iio.imread(path)
    except Exception as error:  # imageio raises many types for corrupt or truncated files
        raise ValueError(f"could not read {what} {path}: {error}") from error


def load_image(path: str | Path, background: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> torch.Tensor:
    """Read a PNG or JPG as (H, W, 3) float32 in [0, 1]; alpha is composited onto ``background``.

    Raises FileNotFoundError or ValueError naming the file when it is missing, unreadable or not an image.
    """
    path = Path(path)
    array = read_pixels(path, "image")
    if array.dtype == np.uint8:
        image = torch.from_numpy(array.astype(np.float32) / 255.0)
    elif array.dtype == np.uint16:
        image = torch.from_numpy(array.astype(np.float32) / 65535.0)
    elif np.issubdtype(array.dtype, np.floating):
        image = torch.from_numpy(array.astype(np.float32))
    else:
        raise ValueError(f"image {path} has pixel type {array.dtype}; expected 8- or 16-bit or float")
    if image.ndim == 2:
        image = image[..., None].expand(-1, -1, 3)
    if image.ndim != 3 or image.shape[-1] not in (1, 3, 4):
        raise ValueError(f"image {path} has shape {tuple(array.shape)}; expected (H, W), (H, W, 3) or (H, W, 4)")
    if image.shape[-1] == 1:
        image = image.expand(-1, -1, 3)
    if image.shape[-1] == 4:
        alpha = image[..., 3:]
        image = image[..., :3] * alpha + torch.tensor(background) * (1.0 - alpha)
    return image.contiguous()


def load_mask(path: str | Path, size: tuple[int, int] | None = None, downscale_by: int = 1) -> torch.Tensor:
    """Read a mask image as (H, W) bool, True where it shows the object: where the mask is at least half white (its
    first channel, or its alpha where it has one), or non-zero in a mask stored as 0s and 1s; then downscaled
    ``downscale_by`` times (:func:`downscale_mask`).

    Args:
        size: the (height, width) the mask must have before downscaling (its image's), or None to take any.

    Raises FileNotFoundError or ValueError naming the file when it is missing, unreadable or of another size.
    """
    path = Path(path)
    array = read_pixels(path, "mask")
    array = mask_channel(array)
    if array.ndim != 2 or not (np.issubdtype(array.dtype, np.integer) or np.issubdtype(array.dtype, np.floating) or array.dtype == np.bool_):
        raise ValueError(f"mask {path} has shape {tuple(array.shape)} of {array.dtype}; expected a grey or colour image")
    if size is not None and tuple(array.shape) != tuple(size):
        raise ValueError(f"mask {path} is {array.shape[1]}x{array.shape[0]} but its image is {size[1]}x{size[0]}: a mask must have its image's size")
    return downscale_mask(torch.from_numpy(np.ascontiguousarray(white_pixels(array))), downscale_by)


def mask_channel(values: np.ndarray) -> np.ndarray:
    """(H, W) or (H, W, C) values of a mask image -> (H, W): its alpha where it has one that varies (grey + alpha,
    RGBA), else its first channel."""
    if values.ndim != 3:
        return values
    alpha = values[..., -1]
    return alpha if values.shape[-1] in (2, 4) and alpha.min() < alpha.max() else values[..., 0]


def white_pixels(values: np.ndarray) -> np.ndarray:
    """(H, W) values of a mask's channel -> (H, W) bool, True where at least half white: 128 and up of 8 bits (JPEG
    noise around black and white stays put), 32768 of 16, 0.5 of floats; non-zero in a mask of 0s and 1s."""
    if np.issubdtype(values.dtype, np.integer) and values.max(initial=0) > 1:
        return values >= (128 if values.dtype.itemsize == 1 else 32768)
    return values.astype(np.float32) >= 0.5  # 0s and 1s, bools, floats in [0, 1]


def downscale_mask(mask: torch.Tensor, factor: int) -> torch.Tensor:
    """(H, W) bool -> (H // factor, W // factor) bool: a block is the object where at least half of it is, the
    blocks those of :func:`downscale`, so a mask stays aligned with its downscaled image."""
    if factor == 1:
        return mask
    return downscale(mask[..., None].float(), factor)[..., 0] >= 0.5


def downscale_depth(depth: torch.Tensor, factor: int) -> torch.Tensor:
    """(H, W) distances, NaN where unknown -> (H // factor, W // factor): each block the mean of its known values
    (NaN where it has none), the blocks those of :func:`downscale`, so a depth map stays aligned with its image."""
    if factor == 1:
        return depth
    height, width = depth.shape[0] // factor, depth.shape[1] // factor
    blocks = depth[: height * factor, : width * factor].reshape(height, factor, width, factor).transpose(1, 2)
    return blocks.reshape(height, width, -1).nanmean(dim=-1)


def image_size(path: str | Path) -> tuple[int, int]:
    """(height, width) of a PNG or JPG read from its header, without decoding the pixels."""
    try:
        shape = iio.improps(path).shape
    except Exception as error:  # imageio raises many types for corrupt or truncated files
        raise ValueError(f"could not read image {path}: {error}") from error
    return int(shape[0]), int(shape[1])


def downscale(image: torch.Tensor, factor: int) -> torch.Tensor:
    """(H, W, C) -> (H // factor, W // factor, C) by area averaging (each output pixel the mean of a block)."""
    if factor == 1:
        return image
    if factor < 1 or int(factor) != factor:
        raise ValueError(f"downscale factor must be a positive integer, got {factor}")
    height, width = image.shape[0] // factor, image.shape[1] // factor
    if height < 1 or width < 1:
        raise ValueError(f"downscale factor {factor} is larger than the image {tuple(image.shape[:2])}")
    chw = image[: height * factor, : width * factor].permute(2, 0, 1)[None]
    return F.avg_pool2d(chw, factor)[0].permute(1, 2, 0).contiguous()


def pixel_grid(height: int, width: int, scale: float = 1.0) -> torch.Tensor:
    """Pixel-centre positions of an image rendered ``scale`` times larger: (round(sH), round(sW), 2).

    Entry [i, j] is (x, y) = ((j + 0.5) / W', (i + 0.5) / H') with W', H' the rendered size, so every
    resolution samples the same [0, 1] square and a field fitted at one size renders at any other.
    """
    out_h, out_w = max(1, round(height * scale)), max(1, round(width * scale))
    ys = (torch.arange(out_h, dtype=torch.float32) + 0.5) / out_h
    xs = (torch.arange(out_w, dtype=torch.float32) + 0.5) / out_w
    grid_y, grid_x = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack([grid_x, grid_y], dim=-1)


def default_image(height: int = 256, width: int = 384) -> torch.Tensor:
    """The built-in image, (H, W, 3) in [0, 1]: deterministic, with detail from coarse to fine.

    Left to right: a smooth colour gradient with soft-edged discs (low frequencies), a chirp whose stripes
    narrow from 32 px to 3 px per period (every frequency band, so the encoding's L visibly matters), and a
    zone plate whose rings tighten to a 3 px period at its rim. A thin checkerboard band at the bottom holds the finest
    detail: 2-pixel squares.
    """
    y, x = torch.meshgrid(
        (torch.arange(height, dtype=torch.float64) + 0.5) / height,
        (torch.arange(width, dtype=torch.float64) + 0.5) / width,
        indexing="ij",
    )
    # coarse: a diagonal gradient in all three channels
    image = torch.stack([0.25 + 0.5 * x, 0.3 + 0.4 * y, 0.75 - 0.5 * x * y], dim=-1)

    # coarse to medium: discs with a 2-pixel soft edge
    aspect = width / height
    discs = [((0.12, 0.28), 0.10, (0.9, 0.2, 0.15)), ((0.22, 0.65), 0.14, (0.15, 0.55, 0.9)), ((0.08, 0.8), 0.05, (0.95, 0.85, 0.1))]
    for (cx, cy), radius, colour in discs:
        distance = torch.sqrt(((x - cx) * aspect) ** 2 + (y - cy) ** 2)
        coverage = torch.clamp((radius - distance) * height / 2.0 + 0.5, 0.0, 1.0)[..., None]
        image = image * (1 - coverage) + torch.tensor(colour, dtype=torch.float64) * coverage

    # all bands: a vertical chirp in the middle third, period from 32 px down to 3 px
    in_chirp = ((x > 0.36) & (x < 0.64) & (y < 0.88))[..., None]
    u = (x - 0.36) / 0.28
    periods_px = 32.0 * (3.0 / 32.0) ** u  # geometric sweep of the period
    phase = torch.cumsum(torch.ones_like(x) / periods_px, dim=1) * 2 * torch.pi
    chirp = 0.5 + 0.5 * torch.sin(phase)
    chirp_rgb = torch.stack([chirp, 0.8 * chirp + 0.1, 1.0 - chirp], dim=-1)
    image = torch.where(in_chirp, chirp_rgb, image)

    # medium to fine: a zone plate on the right, cos(pi c r^2) with r in pixels has c r cycles per pixel,
    # so its rings tighten from the centre to a 3-pixel period at the rim
    cx, cy, radius = 0.82, 0.42, 0.36
    r_px = torch.sqrt(((x - cx) * width) ** 2 + ((y - cy) * height) ** 2)
    rim_px = radius * height
    zone = 0.5 + 0.5 * torch.cos(torch.pi * r_px**2 / (3.0 * rim_px))
    in_zone = (r_px < rim_px)[..., None]
    image = torch.where(in_zone, torch.stack([zone, zone * 0.6 + 0.2, 0.3 + 0.4 * zone], dim=-1), image)

    # finest: 2-pixel checkerboard band along the bottom
    rows = torch.arange(height)[:, None].expand(height, width)
    cols = torch.arange(width)[None, :].expand(height, width)
    checker = (((rows // 2) + (cols // 2)) % 2).to(torch.float64)
    in_band = (y > 0.9)[..., None]
    image = torch.where(in_band, torch.stack([checker, checker, 0.5 * checker + 0.25], dim=-1), image)
    return image.clamp(0.0, 1.0).to(torch.float32).contiguous()
