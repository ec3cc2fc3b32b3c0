"""What is the GPU tile rasteriser's (Triton) own: its gradients the same bit for bit on the device, float64 and bf16
footprints, and its kernels compiled for a GPU without one. Its equality with the dense reference is tested beside the
CPU's tile rasteriser (tests/splats/test_rasterize_tiles.py). On a GPU where there is one, else in Triton's
interpreter on the CPU; skipped where Triton is not installed."""

from __future__ import annotations

import pytest
import torch

triton = pytest.importorskip("triton")

from nerf_lightning.splats.projection import Projection, project  # noqa: E402
from nerf_lightning.splats.rasterize_reference import rasterize_reference  # noqa: E402
from nerf_lightning.splats.rasterize_triton import rasterize_triton  # noqa: E402
from tests.splats.test_rasterize_pairs import camera, gaussians  # noqa: E402
from tests.splats.test_rasterize_tiles import BACKGROUND, TRITON_DEVICE as DEVICE, rasterize_triton_here  # noqa: E402


def test_the_same_input_gives_the_same_gradients_bit_for_bit():
    # the footprints' tensors are the leaves, on the device: the rasteriser's own determinism, not that of the
    # projection's gathers (index_add adds atomically on CUDA) or of autograd adding up a CPU leaf's gradients as
    # they come back from another device
    g = gaussians(n=300 if DEVICE == "cuda" else 100, seed=8)  # fewer in the interpreter, which is slow
    K, c2w = camera(40, 48)
    with torch.no_grad():
        projection = project(g["means"], g["quats"], g["log_scales"], torch.sigmoid(g["opacity_logits"]), K, c2w, 40, 48)
    leaves = [value.to(DEVICE).requires_grad_() for value in (projection.means2d, projection.conics, projection.opacities,
                                                              projection.depths)]
    colours = g["colours"].detach()[projection.ids].to(DEVICE).requires_grad_()
    on_gpu = Projection(projection.ids.to(DEVICE), *leaves[:3], leaves[3], projection.extents.to(DEVICE))
    grads = []
    for _ in range(2):
        out = rasterize_triton(on_gpu, colours, 40, 48, BACKGROUND.to(DEVICE))
        grads.append(torch.autograd.grad(out["rgb"].square().sum() + out["depth"].sum(), [*leaves, colours]))
    for a, b in zip(*grads):
        assert torch.isfinite(a).all() and torch.equal(a, b)


def test_a_bfloat16_projection_is_drawn_in_float32_with_gradients_in_its_own_dtype():
    # autocast's bf16 matrix products make the projection bf16 on a GPU: drawn in float32, as float32 footprints are
    g = gaussians(n=60, seed=12)
    K, c2w = camera(20, 24)
    with torch.no_grad():
        projection = project(g["means"], g["quats"], g["log_scales"], torch.sigmoid(g["opacity_logits"]), K, c2w, 20, 24)
    half = Projection(projection.ids, *(value.bfloat16().requires_grad_() for value in projection[1:5]), projection.extents)
    colours = g["colours"].detach()[projection.ids]
    out = rasterize_triton_here(half, colours, 20, 24, BACKGROUND)
    assert out["rgb"].dtype == torch.float32
    exact = rasterize_triton_here(Projection(projection.ids, *(value.bfloat16().float() for value in projection[1:5]), projection.extents),
                      colours, 20, 24, BACKGROUND)
    torch.testing.assert_close(out["rgb"], exact["rgb"])
    out["rgb"].sum().backward()
    assert half.means2d.grad.dtype == torch.bfloat16 and torch.isfinite(half.means2d.grad.float()).all()


def test_float64_inputs_are_drawn_in_float64():
    g = {key: value.detach().double().requires_grad_() for key, value in gaussians(seed=9).items()}
    K, c2w = camera()
    projection = project(g["means"], g["quats"], g["log_scales"], torch.sigmoid(g["opacity_logits"]), K.double(),
                         c2w.double(), 20, 24)
    out = rasterize_triton_here(projection, g["colours"][projection.ids], 20, 24, BACKGROUND.double())
    assert out["rgb"].dtype == torch.float64
    reference = rasterize_reference(projection, g["colours"][projection.ids], 20, 24, BACKGROUND.double())
    torch.testing.assert_close(out["rgb"], reference["rgb"], atol=1e-10, rtol=1e-10)


def compile_kernels(dtype: str) -> None:
    """Each kernel compiled to a Hopper cubin for ``dtype`` ("fp32" or "fp64") footprints, as a GPU would, with no GPU."""
    import nerf_lightning.splats.rasterize_triton as kernels
    from nerf_lightning.splats.projection import MAX_ALPHA, MIN_ALPHA, MIN_TRANSMITTANCE
    from triton.backends.compiler import GPUTarget
    from triton.compiler import ASTSource

    f = f"*{dtype}"
    limits = {"MAX_ALPHA": MAX_ALPHA, "MIN_ALPHA": MIN_ALPHA}
    jobs = [
        (kernels._composite, {"packed": f, "offsets": "*i64", "entries": "*i32", "height": "i32", "width": "i32",
                              "tiles_x": "i32", "shaded": f, "accumulation": f, "transmittance": "*fp64", "stop": "*i64"},
         {"TILE": kernels.TILE, "PACKED": kernels.PACKED, **limits, "MIN_TRANSMITTANCE": MIN_TRANSMITTANCE}),
        (kernels._composite_backward, {"packed": f, "offsets": "*i64", "entries": "*i32", "slot_of": "*i64", "height": "i32",
                                       "width": "i32", "tiles_x": "i32", "transmittance": "*fp64", "stop": "*i64",
                                       "grad_shaded": f, "grad_accumulation": f, "slot_grads": f},
         {"TILE": kernels.TILE, "PACKED": kernels.PACKED, "GRADIENTS": kernels.GRADIENTS, **limits}),
        (kernels._sum_slots, {"slot_grads": f, "first_slot": "*i64", "n_slots": "*i64", "out": f, "n_footprints": "i32"},
         {"BLOCK": kernels.SUM_BLOCK, "GRADIENTS": kernels.GRADIENTS}),
    ]
    for kernel, signature, constants in jobs:
        source = ASTSource(fn=kernel, signature={**signature, **{name: "constexpr" for name in constants}},
                           constexprs={(kernel.arg_names.index(name),): value for name, value in constants.items()})
        compiled = triton.compile(source, target=GPUTarget("cuda", 90, 32), options={"num_warps": 8})
        assert "cubin" in compiled.asm, kernel.fn.__name__


@pytest.mark.skipif(DEVICE == "cuda", reason="on a GPU the other tests compile and run the kernels")
@pytest.mark.parametrize("dtype", ["fp32", "fp64"])
def test_the_kernels_compile_for_a_gpu_without_one(dtype):
    """The interpreter runs what Triton's compiler may still refuse (a global, a branch that changes a variable's
    type): compiled in a process of its own, since this one runs Triton's language in the interpreter."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    result = subprocess.run([sys.executable, "-c", f"from tests.splats.test_rasterize_triton import compile_kernels; "
                             f"compile_kernels({dtype!r})"], cwd=root, capture_output=True, text=True, timeout=300,
                            env={**os.environ, "TRITON_INTERPRET": "0", "TRITON_DEFAULT_FP_FUSION": "1"})
    assert result.returncode == 0, result.stderr[-3000:]
