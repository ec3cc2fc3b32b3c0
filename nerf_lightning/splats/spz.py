"""Niantic's SPZ, the compressed splat format (github.com/nianticlabs/spz, ``src/cc/load-spz.cc``), version 3: one
gzip stream of a 16-byte little-endian header

    magic 0x5053474e ("NGSP", uint32)  version 3 (uint32)  N (uint32)  sh degree, fractional bits, flags, 0 (uint8 each)

then the Gaussians attribute by attribute, each byte rounded and clamped to 0..255:

    positions  N x 3 x 3 bytes  24-bit signed fixed point (two's complement), ``fractional bits`` after the point
    alphas     N bytes          sigmoid(opacity logit) 255
    colours    N x 3 bytes      sh0 (0.15 255) + 127.5 (the DC coefficient, not clamped to [0, 1] colour first)
    scales     N x 3 bytes      (log scale + 10) 16
    rotations  N x 4 bytes      "smallest three": the unit quaternion (x y z w) with its largest component made
                                positive; that component's index in the top 2 bits, then each other component, in
                                index order, as a sign bit and 9 bits of |value| / sqrt(1/2)
    sh         N x (K - 1) x 3  coefficient by coefficient, the channel inner: round(128 sh) + 128, its low bits
                                rounded away to keep ``sh1_bits`` (band 1) and ``sh_rest_bits`` (bands 2 and 3): 5 and
                                4 by default, as Niantic's writer packs them (zeros compress; a reader needs no word
                                of it)

Version 3, not 4 (each attribute its own zstd stream, newer): 3 is what every SPZ reader reads (PlayCanvas's
splat-transform, Spark, gsply, Niantic's loader). The format stores RUB coordinates (x right, y up, z back: three.js's);
the 3DGS PLY is taken to be RDF (y down, z forward: COLMAP's), so the Gaussians are turned 180 degrees about x on the
way in (y and z negated, rotations and SH bands turned with them), as Niantic's ``PackOptions.from = RDF`` does: a
viewer that follows each format's convention shows the SPZ as it shows the PLY.
"""

from __future__ import annotations

import gzip
import math
import struct
from pathlib import Path

import numpy as np
import torch

from nerf_lightning.io import write_atomic
from nerf_lightning.splats.gaussians import transform_gaussians

MAGIC = 0x5053474E
VERSION = 3
FLAG_ANTIALIASED = 0x1
COLOUR_SCALE = 0.15
# 12 bits after the point (1/4096, a quarter of a millimetre in metres), Niantic's choice; fewer where the positions
# reach beyond the 24 bits' +-2048 (a reader takes the count from the header)
FRACTIONAL_BITS = 12
SH1_BITS, SH_REST_BITS = 5, 4  # bits kept of an SH coefficient of band 1 and of bands 2 and 3: Niantic's defaults
# the PLY's RDF to SPZ's RUB: 180 degrees about x, a rotation (so the SH bands turn with it, no mirror)
RUB_FROM_RDF = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))


def to_bytes(values: np.ndarray) -> np.ndarray:
    """Rounded half away from zero (C's ``round``, as Niantic's writer does) and clamped to 0..255, as uint8."""
    return np.clip(np.sign(values) * np.floor(np.abs(values) + 0.5), 0, 255).astype(np.uint8)


def fractional_bits_for(means: np.ndarray) -> int:
    """The most bits after the point (up to 12) with which every coordinate of ``means`` (N, 3) fits 24 signed bits."""
    reach = float(np.abs(means).max(initial=0.0))
    bits = FRACTIONAL_BITS
    while bits > 0 and reach * 2**bits > 2**23 - 1:
        bits -= 1
    if reach * 2**bits > 2**23 - 1:
        raise ValueError(f"SPZ positions are 24-bit fixed point: a coordinate of {reach:g} is beyond its reach (2^23)")
    return bits


def pack_positions(means: np.ndarray, bits: int) -> np.ndarray:
    """(N, 3) -> (N, 9) bytes: each coordinate as a 24-bit little-endian two's-complement integer of ``bits``
    fractional bits."""
    fixed = (np.sign(means) * np.floor(np.abs(means) * 2**bits + 0.5)).astype(np.int64) & 0xFFFFFF
    return np.stack([fixed & 0xFF, (fixed >> 8) & 0xFF, fixed >> 16], axis=-1).astype(np.uint8).reshape(len(means), 9)


def pack_rotations(quats_xyzw: np.ndarray) -> np.ndarray:
    """(N, 4) unit quaternions x y z w -> (N, 4) bytes, smallest three (see the module's docstring)."""
    n = len(quats_xyzw)
    largest = np.abs(quats_xyzw).argmax(axis=1)
    q = quats_xyzw * np.where(quats_xyzw[np.arange(n), largest] < 0, -1.0, 1.0)[:, None]  # -q is the same rotation
    packed = largest.astype(np.uint32)
    for axis in range(4):
        magnitude = np.minimum(np.floor(511 * np.abs(q[:, axis]) / math.sqrt(0.5) + 0.5), 511).astype(np.uint32)
        component = ((q[:, axis] < 0).astype(np.uint32) << 9) | magnitude
        packed = np.where(largest == axis, packed, (packed << 10) | component)
    return packed.astype("<u4").view(np.uint8).reshape(n, 4)


def pack_sh(shN: np.ndarray, sh1_bits: int = SH1_BITS, sh_rest_bits: int = SH_REST_BITS) -> np.ndarray:
    """(N, K - 1, 3) higher SH coefficients -> (N, 3 (K - 1)) bytes, ``sh1_bits`` kept of band 1's, ``sh_rest_bits``
    of the others' (1 to 8)."""
    n, rest = shN.shape[:2]
    quantised = np.floor(np.abs(shN) * 128 + 0.5) * np.sign(shN) + 128
    band = np.floor(np.sqrt(np.arange(rest) + 1)).astype(int)  # coefficient k (after the DC) is in band floor(sqrt(k + 1))
    bucket = np.array([1 << (8 - (sh1_bits if b == 1 else sh_rest_bits)) for b in band], dtype=np.float64)[None, :, None]
    quantised = np.floor((quantised + bucket // 2) / bucket) * bucket
    return np.clip(quantised, 0, 255).astype(np.uint8).reshape(n, 3 * rest)


def write_splat_spz(path: str | Path, means: torch.Tensor, quats: torch.Tensor, log_scales: torch.Tensor, opacity_logits: torch.Tensor,
                    sh0: torch.Tensor, shN: torch.Tensor, antialiased: bool = False, sh1_bits: int = SH1_BITS,
                    sh_rest_bits: int = SH_REST_BITS) -> Path:
    """Write N Gaussians, given in the PLY's RDF coordinates, as SPZ version 3 (RUB): means (N, 3), quats (N, 4)
    w x y z, log_scales (N, 3), opacity_logits (N,), sh0 (N, 1, 3), shN (N, K - 1, 3) with K - 1 in 0, 3, 8, 15;
    ``antialiased`` sets the header's flag (viewers then compensate the low-pass filter's opacity, as Mip-Splatting);
    ``sh1_bits`` and ``sh_rest_bits`` (1 to 8) the bits kept of the higher SH coefficients.
    Gaussians with a non-finite value are left out, as in the PLY."""
    rest = shN.shape[1]
    if rest not in (0, 3, 8, 15):
        raise ValueError(f"SPZ holds SH degrees 0 to 3 ((degree + 1)^2 - 1 = 0, 3, 8 or 15 higher coefficients), got {rest}")
    if not (1 <= sh1_bits <= 8 and 1 <= sh_rest_bits <= 8):
        raise ValueError(f"sh1_bits and sh_rest_bits must be from 1 to 8, got {sh1_bits} and {sh_rest_bits}")
    columns = [means, quats, log_scales, opacity_logits[:, None], sh0.reshape(len(sh0), 3), shN.reshape(len(shN), 3 * rest)]
    finite = torch.cat([column.detach().float().cpu() for column in columns], dim=1).isfinite().all(dim=1)
    parameters = {"means": means, "quats": quats, "log_scales": log_scales, "opacity_logits": opacity_logits, "sh0": sh0, "shN": shN}
    g = {name: value.detach().cpu()[finite] for name, value in parameters.items()}
    turned = transform_gaussians(g, RUB_FROM_RDF)
    # the rotation R in the new frame as F R F (F = RUB_FROM_RDF: x, y, z's signs flipped as Niantic's writer flips them,
    # so its bytes are the ones it writes) rather than transform_gaussians's F R: the same Gaussian, its axes' signs aside
    turned["quats"] = torch.nn.functional.normalize(g["quats"].double(), dim=-1) * torch.tensor([1.0, 1.0, -1.0, -1.0], dtype=torch.float64)
    g = {name: value.double().numpy() for name, value in turned.items()}
    n = len(g["means"])
    bits = fractional_bits_for(g["means"])
    quats_xyzw = g["quats"][:, [1, 2, 3, 0]]
    header = struct.pack("<IIIBBBB", MAGIC, VERSION, n, round(math.sqrt(rest + 1)) - 1, bits, FLAG_ANTIALIASED if antialiased else 0, 0)
    sections = [pack_positions(g["means"], bits), to_bytes(255 / (1 + np.exp(-np.clip(g["opacity_logits"], -60, 60)))),
                to_bytes(g["sh0"].reshape(n, 3) * (COLOUR_SCALE * 255) + 127.5), to_bytes((g["log_scales"] + 10) * 16),
                pack_rotations(quats_xyzw), pack_sh(g["shN"], sh1_bits, sh_rest_bits)]
    payload = header + b"".join(np.ascontiguousarray(section).tobytes() for section in sections)
    return write_atomic(path, gzip.compress(payload, compresslevel=6, mtime=0))  # mtime 0: the same Gaussians, the same bytes
