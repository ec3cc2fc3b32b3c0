"""SPZ: read back by gsply (a reader that is not the writer; an optional test dependency), every attribute within the
format's quantisation of what was written, turned from the PLY's RDF to SPZ's RUB; nerf-export writes it from the
same Gaussians as the PLY; the header and section sizes checked against the spec with gzip and struct alone."""

from __future__ import annotations

import gzip
import struct
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from nerf_lightning.outputs.export import export_model, formats_of
from nerf_lightning.splats.ply import read_splat_ply
from nerf_lightning.splats.spz import write_splat_spz

# the format's half steps: positions 1/4096 (12 fractional bits), alphas 1/255, DC colours 1/(0.15 255), log scales
# 1/16; SH coefficients of band 1 in buckets of 8/128, of bands 2 and 3 of 16/128 (plus the 8-bit rounding)
POSITION, ALPHA, COLOUR, LOG_SCALE = 0.5 / 4096, 0.5 / 255, 0.5 / (0.15 * 255), 0.5 / 16
SH_BAND_1, SH_BANDS_2_3 = 4.5 / 128, 8.5 / 128
# 180 degrees about x (RDF -> RUB) negates y and z; a real SH basis function changes sign with it where its polynomial
# is odd in (y, z) together: band 1 (y, z, x), band 2 (xy, yz, 3z^2 - 1, xz, x^2 - y^2),
# band 3 (y(3x^2 - y^2), xyz, y(5z^2 - 1), z(5z^2 - 3), x(5z^2 - 1), z(x^2 - y^2), x(x^2 - 3y^2))
FLIP = torch.tensor([1.0, -1.0, -1.0])
SH_FLIP = torch.tensor([-1, -1, 1, -1, 1, 1, -1, 1, -1, 1, -1, -1, 1, -1, 1], dtype=torch.float32)


def splats(n: int = 200, rest: int = 15, spread: float = 1.0, sh: float = 0.95) -> dict[str, torch.Tensor]:
    """Gaussians inside the ranges SPZ holds unclamped (DC colours within +-3.3, SH within [-1, 1), log scales
    within [-10, 5.9]); the higher SH within +-``sh``."""
    generator = torch.Generator().manual_seed(0)

    def uniform(*shape: int, low: float, high: float) -> torch.Tensor:
        return low + (high - low) * torch.rand(*shape, generator=generator)

    return {
        "means": spread * torch.randn(n, 3, generator=generator), "quats": torch.randn(n, 4, generator=generator),
        "log_scales": uniform(n, 3, low=-8, high=2), "opacity_logits": uniform(n, low=-5, high=5),
        "sh0": uniform(n, 1, 3, low=-3, high=3), "shN": uniform(n, rest, 3, low=-sh, high=sh),
    }


def rotation_matrices(quats: torch.Tensor) -> torch.Tensor:
    """(N, 4) w x y z -> (N, 3, 3)."""
    w, x, y, z = torch.nn.functional.normalize(quats.double(), dim=-1).unbind(-1)
    return torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], dim=-1).reshape(-1, 3, 3)


def read_with_gsply(path) -> dict[str, torch.Tensor]:
    gsply = pytest.importorskip("gsply")
    data = gsply.read_spz(path)
    n = len(data.means)
    shN = torch.from_numpy(np.asarray(data.shN)).reshape(n, -1, 3) if data.shN is not None else torch.zeros(n, 0, 3)
    return {"means": torch.from_numpy(np.asarray(data.means)), "quats": torch.from_numpy(np.asarray(data.quats)),
            "log_scales": torch.from_numpy(np.asarray(data.scales)), "opacity_logits": torch.from_numpy(np.asarray(data.opacities)),
            "sh0": torch.from_numpy(np.asarray(data.sh0)).reshape(n, 1, 3), "shN": shN}


def assert_within_quantisation(read: dict[str, torch.Tensor], rdf: dict[str, torch.Tensor],
                               sh_steps: tuple[float, float] = (SH_BAND_1, SH_BANDS_2_3)) -> None:
    """``read`` (RUB, from the SPZ) holds the Gaussians ``rdf`` (the PLY's coordinates) within the format's steps
    (``sh_steps``: the half steps of band 1's SH coefficients and of the others')."""
    torch.testing.assert_close(read["means"].double(), (rdf["means"] * FLIP).double(), rtol=0, atol=POSITION + 1e-6)
    torch.testing.assert_close(torch.sigmoid(read["opacity_logits"]).double(), torch.sigmoid(rdf["opacity_logits"]).double(),
                               rtol=0, atol=ALPHA + 1e-4)  # + the reader's float32 logit
    torch.testing.assert_close(read["sh0"], rdf["sh0"], rtol=0, atol=COLOUR + 1e-5)
    torch.testing.assert_close(read["log_scales"], rdf["log_scales"], rtol=0, atol=LOG_SCALE + 1e-5)
    # the same axes, each turned with the frame (its sign is the quaternion's choice: the same Gaussian either way)
    axes = rotation_matrices(read["quats"]).transpose(1, 2) @ (torch.diag(FLIP.double()) @ rotation_matrices(rdf["quats"]))
    torch.testing.assert_close(axes.abs(), torch.eye(3, dtype=torch.float64).expand_as(axes), rtol=0, atol=5e-3)
    rest = rdf["shN"].shape[1]
    expected = rdf["shN"] * SH_FLIP[:rest, None]
    step = torch.tensor([sh_steps[0]] * 3 + [sh_steps[1]] * 12)[:rest, None]
    assert ((read["shN"] - expected).abs() <= step + 1e-6).all()


@pytest.mark.parametrize("rest", [15, 8, 3, 0])
def test_gsply_reads_back_every_attribute_within_the_formats_quantisation(tmp_path, rest):
    written = splats(rest=rest)
    path = write_splat_spz(tmp_path / "splats.spz", **written)
    read = read_with_gsply(path)
    assert len(read["means"]) == 200 and read["shN"].shape[1] == rest
    assert_within_quantisation(read, written)


def test_every_bit_of_the_sh_can_be_kept(tmp_path):
    """sh1_bits=8 and sh_rest_bits=8: the SH within half of 1/128, the 8 bits' own step."""
    written = splats()
    read = read_with_gsply(write_splat_spz(tmp_path / "all.spz", **written, sh1_bits=8, sh_rest_bits=8))
    assert_within_quantisation(read, written, sh_steps=(0.5 / 128, 0.5 / 128))
    with pytest.raises(ValueError, match="sh1_bits and sh_rest_bits must be from 1 to 8, got 9 and 4"):
        write_splat_spz(tmp_path / "nine.spz", **written, sh1_bits=9)


def test_the_header_and_sections_are_the_specs(tmp_path):
    """Read with gzip and struct: "NGSP", version 3, N, the SH degree, 12 fractional bits (fewer for a far scene,
    which then still reads back), the antialiasing flag; then 9 + 1 + 3 + 3 + 4 + 3 (K - 1) bytes a Gaussian."""
    written = splats(rest=8)
    raw = gzip.decompress(write_splat_spz(tmp_path / "a.spz", **written, antialiased=True).read_bytes())
    assert struct.unpack("<IIIBBBB", raw[:16]) == (0x5053474E, 3, 200, 2, 12, 1, 0) and raw[:4] == b"NGSP"
    assert len(raw) == 16 + 200 * (9 + 1 + 3 + 3 + 4 + 3 * 8)
    far = splats(rest=0, spread=1000.0)  # beyond +-2048 needs fewer bits after the point
    raw = gzip.decompress(write_splat_spz(tmp_path / "far.spz", **far).read_bytes())
    bits = raw[13]
    assert bits < 12 and float(far["means"].abs().max()) * 2**bits < 2**23
    fixed = np.frombuffer(raw, np.uint8, 200 * 9, 16).reshape(200, 3, 3).astype(np.int32) @ np.array([1, 1 << 8, 1 << 16])
    means = np.where(fixed >= 1 << 23, fixed - (1 << 24), fixed) / 2**bits  # 24-bit two's complement, little-endian
    np.testing.assert_allclose(means, (far["means"] * FLIP).numpy(), rtol=0, atol=0.5 / 2**bits + 1e-3)


def test_non_finite_gaussians_are_left_out_none_is_an_empty_file_and_a_fourth_band_refused(tmp_path):
    written = splats(n=7, rest=3)
    written["log_scales"][2, 0] = float("inf")
    raw = gzip.decompress(write_splat_spz(tmp_path / "s.spz", **written).read_bytes())
    assert struct.unpack("<I", raw[8:12])[0] == 6
    nothing = {name: value[:0] for name, value in written.items()}  # a model with no Gaussians left: a valid empty file
    assert gzip.decompress(write_splat_spz(tmp_path / "none.spz", **nothing).read_bytes())[8:12] == b"\0\0\0\0"
    with pytest.raises(ValueError, match="SPZ holds SH degrees 0 to 3 .* got 24"):
        write_splat_spz(tmp_path / "four.spz", **splats(n=3, rest=24))


class Splats(torch.nn.Module):
    """A model of Gaussians as nerf-export sees one (HasGaussians), its scene a similarity away from the capture."""

    def __init__(self, parameters: dict[str, torch.Tensor], world_from_capture: torch.Tensor) -> None:
        super().__init__()
        self.parameters_, self.space = parameters, SimpleNamespace(world_from_capture=world_from_capture)
        self.rasterizer = SimpleNamespace(antialiased=True)

    def gaussian_parameters(self) -> dict[str, torch.Tensor]:
        return self.parameters_


def test_nerf_export_writes_the_plys_gaussians_as_spz_smaller(tmp_path):
    turn = torch.linalg.matrix_exp(torch.tensor([[0.0, -0.3, 0.2], [0.3, 0.0, -0.5], [-0.2, 0.5, 0.0]]))
    world_from_capture = torch.eye(4)
    world_from_capture[:3, :3], world_from_capture[:3, 3] = 0.5 * turn, torch.tensor([0.1, -0.2, 0.3])
    model = Splats(splats(n=2000, sh=0.3), world_from_capture)  # turned, a band's coefficients stay within [-1, 1)
    assert formats_of(model) == ["ply", "spz"]
    ply = export_model(model, "ply", tmp_path, {"frame": "capture"})
    spz = export_model(model, "spz", tmp_path, {"frame": "capture", "sh1_bits": 5, "sh_rest_bits": 4})
    assert spz.name == "splats.spz" and spz.stat().st_size < ply.stat().st_size / 4
    assert gzip.decompress(spz.read_bytes())[14] == 1  # drawn antialiased, flagged so
    in_capture = read_splat_ply(ply)
    assert not torch.allclose(in_capture["means"], model.gaussian_parameters()["means"])  # the similarity was undone
    assert_within_quantisation(read_with_gsply(spz), in_capture)
    with pytest.raises(ValueError, match=r"format=spz needs Gaussians \(a splat SPZ\); .*it has nothing nerf-export writes"):
        export_model(torch.nn.Linear(1, 1), "spz", tmp_path, {})
