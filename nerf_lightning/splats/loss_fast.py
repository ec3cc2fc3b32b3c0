"""The splats' photometric loss and its gradient in one numba pass a direction on a CPU: the idea of fused-ssim,
Taming 3DGS and Brush, beside the PyTorch reference :func:`~nerf_lightning.splats.loss.photometric_loss` that the
tests hold it equal to (values and gradients, float64, masks, borders).

The reference runs some fifty tensor operations forward and as many backward (the five moments stacked, padded,
blurred by two grouped convolutions, then the SSIM formula term by term, each a pass over the image and a launch on
a GPU). Here, for an image x (H, W, C) against y:

- **forward**: the five moments x, y, x^2, y^2, xy blurred by the separable 11-tap Gaussian (sigma 1.5) with
  reflect borders, a pass along the rows and one along the columns; then each pixel's SSIM
  S = (2 mx my + C1)(2 sxy + C2) / ((mx^2 + my^2 + C1)(sx^2 + sy^2 + C2)), its L1, and the three partial derivatives
  of S in the blurred moments that involve x: dS/dmx, dS/d(x^2 blurred), dS/d(xy blurred), weighted by the pixel's
  share of the mean;
- **backward**: those three maps blurred by the blur's transpose (each output row gathering the rows that read it,
  through the reflection at the ends too), so that dL/dx = (1 - w) sign(x - y) share - w (B^T a + 2 x B^T b + y B^T c).

A row's pixels are one line of interleaved colours, so the window's inside taps run over contiguous memory without a
branch and vectorise; only the places within the window's radius of an edge take the reflected taps separately.

Sums are taken row by row and then in row order, so the same input gives the same loss bit for bit whatever the
threads do. The image is the photo, never differentiated.
"""

from __future__ import annotations

import numba
import numpy as np
import torch

# SSIM's window (kornia's, and 3DGS's): 11 taps, sigma 1.5; its stabilising constants for values in [0, 1]
WINDOW, SIGMA = 11, 1.5
C1, C2 = 0.01**2, 0.03**2


def gaussian_window(dtype: np.dtype) -> np.ndarray:
    """(WINDOW,) the normalised 1D Gaussian kornia's ``get_gaussian_kernel1d(11, 1.5)`` gives, in ``dtype``."""
    offsets = np.arange(WINDOW, dtype=np.float64) - WINDOW // 2
    window = np.exp(-(offsets**2) / (2.0 * SIGMA**2))
    return (window / window.sum()).astype(dtype)


@numba.njit(inline="always")
def _reflect(index, size):
    """``index`` in [-size + 1, 2 size - 2] folded into [0, size) as torch's reflect padding folds it."""
    if index < 0:
        return -index
    if index >= size:
        return 2 * (size - 1) - index
    return index


@numba.njit(inline="always")
def _blur_line(line, window, channels, transposed, out):
    """``out`` (n C,) = the reflect-bordered blur of ``line`` (n C,: n places of C interleaved values) along its n
    places, or with ``transposed`` the blur's transpose (what each place was read by, given back to it: the window is
    symmetric, so the inside taps are the blur's own, and the reflected ones go back where they were read from). The
    inner loops run over contiguous memory without a branch (the window's taps that fall inside); the few places
    within the window's radius of an end then add the taps that reflect."""
    n, radius = line.shape[0] // channels, window.shape[0] // 2
    out[:] = 0.0
    for k in range(window.shape[0]):
        shift, g = (k - radius) * channels, window[k]
        lo, hi = max(0, -(k - radius)) * channels, min(n, n - (k - radius)) * channels  # the places tap k reads inside
        if transposed:
            for t in range(lo, hi):
                out[t + shift] += g * line[t]
        else:
            for t in range(lo, hi):
                out[t] += g * line[t + shift]
    for j in range(min(radius, n)):
        for side in range(2):
            place = j if side == 0 else n - 1 - j
            if side == 1 and place < radius:
                break
            for k in range(window.shape[0]):
                source = place + k - radius
                if 0 <= source < n:
                    continue
                source = _reflect(source, n)
                to, read = (source, place) if transposed else (place, source)
                for c in range(channels):
                    out[to * channels + c] += window[k] * line[read * channels + c]


@numba.njit(cache=True, parallel=True)
def loss_forward(x, y, channels, mask, masked, ssim_weight, window, partials, signs, row_sums):
    """x, y (H, W C) (a row's pixels' C values interleaved), ``channels`` C; mask (H, W) bool, read where ``masked`` -> fills
    ``partials`` (H, 3, W C): the pixels' share-weighted dS/dmx, dS/dEx2, dS/dExy; ``signs`` (H, W C): the
    share-weighted sign of x - y; ``row_sums`` (H, 3): each row's weighted L1 and SSIM sums and its squared error."""
    height, line = x.shape
    width = line // channels
    radius = window.shape[0] // 2
    count = 0
    if masked:
        for i in range(height):
            for j in range(width):
                count += mask[i, j]
    share = 1.0 / (max(count, 1) if masked else height * width) / channels
    along_rows = np.empty((height, 5, line), x.dtype)
    for i in numba.prange(height):  # the five moments blurred along each row
        products = np.empty((3, line), x.dtype)
        for t in range(line):
            a, b = x[i, t], y[i, t]
            products[0, t], products[1, t], products[2, t] = a * a, b * b, a * b
        _blur_line(x[i], window, channels, False, along_rows[i, 0])
        _blur_line(y[i], window, channels, False, along_rows[i, 1])
        for m in range(3):
            _blur_line(products[m], window, channels, False, along_rows[i, 2 + m])
    for i in numba.prange(height):  # then along the columns, a row of output at a time, and the SSIM formula
        blurred = np.zeros((5, line), x.dtype)
        for k in range(window.shape[0]):
            source, g = _reflect(i + k - radius, height), window[k]
            for m in range(5):
                for t in range(line):
                    blurred[m, t] += g * along_rows[source, m, t]
        l1_sum = ssim_sum = squared = 0.0
        for t in range(line):
            weight = share if not masked else (share if mask[i, t // channels] else 0.0)
            mx, my, exx, eyy, exy = blurred[0, t], blurred[1, t], blurred[2, t], blurred[3, t], blurred[4, t]
            a1 = 2.0 * mx * my + C1
            a2 = 2.0 * (exy - mx * my) + C2
            b1 = mx * mx + my * my + C1
            b2 = (exx - mx * mx) + (eyy - my * my) + C2
            denominator = b1 * b2 + 1e-12
            s = a1 * a2 / denominator
            d_mx = (2.0 * my * a2 - 2.0 * my * a1) / denominator - s / denominator * (2.0 * mx * b2 - 2.0 * mx * b1)
            partials[i, 0, t] = weight * d_mx
            partials[i, 1, t] = weight * (-s / denominator * b1)
            partials[i, 2, t] = weight * (2.0 * a1 / denominator)
            difference = x[i, t] - y[i, t]
            signs[i, t] = weight * ((difference > 0) - (difference < 0))
            l1_sum += weight * abs(difference)
            ssim_sum += weight * s
            squared += difference * difference
        row_sums[i, 0], row_sums[i, 1], row_sums[i, 2] = l1_sum, ssim_sum, squared


@numba.njit(cache=True, parallel=True)
def loss_backward(x, y, partials, signs, ssim_weight, window, channels, scale, grad):
    """The gradient of the loss, times ``scale`` (the upstream gradient), into ``grad`` (H, W C) from what
    :func:`loss_forward` kept: the partials blurred by the blur's transpose (columns, then rows), then the chain rule
    through the moments x, x^2 and xy."""
    height, line = x.shape
    radius = window.shape[0] // 2
    for q in numba.prange(height):  # each output row gathers the partials' rows that read it
        down = np.zeros((3, line), x.dtype)
        for k in range(window.shape[0]):
            # the rows i whose tap k read row q: directly, or through the reflection at the top or the bottom
            for case in range(3):
                if case == 0:
                    i = q - k + radius
                elif case == 1:  # i + k - radius = -q < 0
                    i = -q - k + radius
                    if q == 0:
                        continue
                else:  # i + k - radius = 2 (height - 1) - q >= height
                    i = 2 * (height - 1) - q - k + radius
                    if q > height - 2:
                        continue
                if i < 0 or i >= height:
                    continue
                g = window[k]
                for m in range(3):
                    for t in range(line):
                        down[m, t] += g * partials[i, m, t]
        across = np.empty((3, line), x.dtype)
        for m in range(3):
            _blur_line(down[m], window, channels, True, across[m])
        for t in range(line):
            d_ssim = across[0, t] + 2.0 * x[q, t] * across[1, t] + y[q, t] * across[2, t]
            grad[q, t] = scale * ((1.0 - ssim_weight) * signs[q, t] - ssim_weight * d_ssim)


class FusedPhotometricLoss(torch.autograd.Function):
    """rgb (H, W, C), image (H, W, C), mask (H, W) bool or None, ssim_weight -> the loss () and the mean squared
    error over the whole image (a float, for the logged PSNR); differentiable in rgb."""

    @staticmethod
    def forward(ctx, rgb, image, mask, ssim_weight: float):
        x = rgb.detach().contiguous().numpy()
        y = image.detach().to(rgb.dtype).contiguous().numpy()
        masked = mask is not None
        mask_array = mask.detach().contiguous().numpy() if masked else np.ones((1, 1), np.bool_)
        height, width, channels = x.shape
        x, y = x.reshape(height, width * channels), y.reshape(height, width * channels)  # views: a row's values in a line
        window = gaussian_window(x.dtype)
        partials = torch.empty((height, 3, width * channels), dtype=rgb.dtype).numpy()
        signs = torch.empty((height, width * channels), dtype=rgb.dtype).numpy()
        row_sums = np.empty((height, 3), np.float64)
        loss_forward(x, y, channels, mask_array, masked, ssim_weight, window, partials, signs, row_sums)
        l1, ssim, squared = row_sums.sum(axis=0)  # in row order: the same sum every time
        ctx.save_for_backward(rgb, image)  # autograd's check that neither is changed in place before the backward
        ctx.saved = (x, y, partials, signs, ssim_weight, window, channels)
        loss = (1.0 - ssim_weight) * l1 + ssim_weight * (1.0 - ssim)
        return torch.from_numpy(np.asarray(loss, dtype=x.dtype)), float(squared / x.size)

    @staticmethod
    def backward(ctx, grad_loss, _mse):
        ctx.saved_tensors  # raises where rgb or the image was changed in place since the forward pass
        x, y, partials, signs, ssim_weight, window, channels = ctx.saved
        grad = torch.empty(x.shape, dtype=grad_loss.dtype)
        loss_backward(x, y, partials, signs, ssim_weight, window, channels, grad_loss.detach().numpy().item(), grad.numpy())
        return grad.reshape(x.shape[0], -1, channels), None, None, None


def photometric_loss_fast(rgb: torch.Tensor, image: torch.Tensor, ssim_weight: float,
                          mask: torch.Tensor | None = None) -> tuple[torch.Tensor, float]:
    """:func:`~nerf_lightning.splats.loss.photometric_loss` of CPU rgb (H, W, C) against image (H, W, C) (mask
    (H, W) bool or None), in one numba pass, and the mean squared error of rgb against image over every pixel (for
    the logged PSNR). H and W must exceed the window's radius (5), as the reference's reflect padding needs."""
    if rgb.shape != image.shape or rgb.ndim != 3:
        raise ValueError(f"photometric_loss_fast expects (H, W, C) rgb and image of one shape, got {tuple(rgb.shape)} "
                         f"and {tuple(image.shape)}")
    if min(rgb.shape[:2]) <= WINDOW // 2:
        raise ValueError(f"photometric_loss_fast needs views larger than {WINDOW // 2} pixels a side (SSIM's reflect "
                         f"padding), got {tuple(rgb.shape[:2])}")
    if mask is not None and (mask.shape != rgb.shape[:2] or mask.dtype != torch.bool):
        raise ValueError(f"photometric_loss_fast's mask must be (H, W) = {tuple(rgb.shape[:2])} bool, got "
                         f"{tuple(mask.shape)} {mask.dtype}")
    return FusedPhotometricLoss.apply(rgb, image, mask, float(ssim_weight))
