"""The hash-grid encoding's fast paths (nerf_lightning.fields.hash_grid_fast) against its reference, and the chooser."""

import shutil
import warnings

import pytest
import torch

from nerf_lightning.compiling import CompiledOrEager
from nerf_lightning.fields import HashGridEncoding, hash_grid_fast
from nerf_lightning.fields.hash_grid import encode_reference
from nerf_lightning.fields.hash_grid_fast import (COMPILED, COMPLEX_GATHER, COMPLEX_SUM, GATHER, PATHS, choose_path, encode,
                                                 gather_rows)
from tests.fields.test_hash_grid import reference_encoding, small_encoding


def has_cxx_compiler() -> bool:
    return any(shutil.which(name) for name in ("g++", "clang++", "c++"))


def random_points(n: int, seed: int, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    points = torch.rand(n, 3, generator=torch.Generator().manual_seed(seed), dtype=dtype)
    points[0], points[1] = torch.tensor([1.0, 1.0, 1.0]), torch.tensor([0.0, 0.0, 0.0])  # the far and the near corner
    return points


ENCODINGS = {
    # levels of 4, 10 (dense), 25, 64 (hashed) cells, rows in int32
    "F=2": lambda: small_encoding(features_per_level=2),
    "F=3": lambda: small_encoding(features_per_level=3),
    "F=1": lambda: small_encoding(features_per_level=1),
    # 16 (dense) and 2048 (hashed) cells in tables of 2^21 rows: rows in int64
    "F=2, int64 rows": lambda: small_encoding(n_levels=2, log2_table_size=21, base_resolution=16, max_resolution=2048),
}


@pytest.mark.parametrize("name", ENCODINGS)
def test_every_path_gives_the_reference_values_and_table_gradients(name):
    """float32 on random points, dense and hashed levels: each path that applies to the rows' width (the complex ones
    to rows of two) gives encode_reference's features, and its gradient with respect to the table."""
    encoding = ENCODINGS[name]()
    assert encoding.hashed.any() and not encoding.hashed.all()
    assert encoding.index_dtype == (torch.long if "int64" in name else torch.int32)
    points = random_points(500, seed=7)
    upstream = torch.randn(500, encoding.out_dim, generator=torch.Generator().manual_seed(8))
    expected = encode_reference(points, *encoding.reference_inputs())
    (expected_grad,) = torch.autograd.grad((expected * upstream).sum(), encoding.table)
    paths = PATHS if encoding.features_per_level == 2 else (COMPILED, GATHER)
    for path in paths:
        with torch.no_grad():  # as the compiled path runs
            torch.testing.assert_close(encode(path, encoding, points), expected.detach(), msg=path)
        if path != COMPILED:
            got = encode(path, encoding, points)
            torch.testing.assert_close(got, expected, msg=path)
            (grad,) = torch.autograd.grad((got * upstream).sum(), encoding.table)
            torch.testing.assert_close(grad, expected_grad, msg=path)


@pytest.mark.parametrize(("arguments", "path"), [
    (("cpu", True, 2, torch.float32), COMPLEX_SUM),  # training on a CPU
    (("cpu", True, 2, torch.float64), COMPLEX_SUM),
    (("cpu", False, 2, torch.float32, True, 100), COMPILED),  # evaluation on a CPU
    (("cpu", False, 3, torch.float32, True, 100), COMPILED),
    (("cpu", False, 2, torch.float32, False, 100), COMPLEX_GATHER),  # compile_evaluation=False
    (("cpu", False, 2, torch.float32, True, 1), COMPLEX_GATHER),  # sizes 0 and 1 are not compiled
    (("cpu", False, 2, torch.float32, True, 0), COMPLEX_GATHER),
    (("cpu", False, 3, torch.float32, False, 100), GATHER),
    (("cpu", True, 3, torch.float32), GATHER),  # rows of three, or not of float32/64: real rows
    (("cpu", True, 1, torch.float32), GATHER),
    (("cpu", True, 2, torch.float16), GATHER),
    (("cpu", True, 2, torch.bfloat16), GATHER),
    (("cuda", True, 2, torch.float32), GATHER),  # a GPU, with gradients or without
    (("cuda", False, 2, torch.float32, True, 100), GATHER),
    (("mps", False, 2, torch.float32, True, 100), GATHER),
])
def test_the_chooser_picks_by_device_gradients_width_and_dtype(arguments, path):
    assert choose_path(*arguments) == path


def test_forward_runs_the_chosen_path(monkeypatch):
    """forward asks the chooser with its points' device, the grad mode, F, the table's dtype, compile_evaluation and
    the number of points, and runs what it picks."""
    chosen = []
    run = hash_grid_fast.encode

    def spy(path, encoding, points):
        chosen.append(path)
        return run(GATHER, encoding, points)  # eager: no compiling here

    monkeypatch.setattr(hash_grid_fast, "encode", spy)
    encoding, points = small_encoding(), torch.rand(2, 5, 3)
    encoding(points)
    with torch.no_grad():
        encoding(points)
        encoding(points[:1, :1])
        encoding.compile_evaluation = False
        encoding(points)
    small_encoding(features_per_level=3)(points)
    small_encoding().double()(points.double())
    assert chosen == [COMPLEX_SUM, COMPILED, COMPLEX_GATHER, COMPLEX_GATHER, GATHER, COMPLEX_SUM]
    with pytest.raises(ValueError, match="path must be one of"):
        run("complex", encoding, points[0])


def test_evaluation_runs_the_reference_compiled():
    """Without gradients on a CPU, forward is encode_reference through torch.compile: the paper's features, dense and
    hashed levels, the far corner included. Where this machine has a C++ compiler, it really ran compiled."""
    encoding = small_encoding().double().eval()
    points = random_points(40, seed=2, dtype=torch.float64)
    expected = torch.tensor([reference_encoding(encoding, p.tolist()) for p in points], dtype=torch.float64)
    with torch.no_grad():
        torch.testing.assert_close(encoding(points.reshape(4, 10, 3)), expected.reshape(4, 10, 8), rtol=1e-9, atol=1e-9)
    if has_cxx_compiler():
        assert hash_grid_fast.compiled_reference.failure is None and hash_grid_fast.compiled_reference.compiled is not None


def test_only_passes_without_gradients_on_the_cpu_go_through_the_compiled_reference(monkeypatch):
    """Gradients, ``compile_evaluation=False`` and sizes 0 and 1 take a gather path; a pass without gradients
    (evaluation, or a proposal network's pass on a step it does not learn) takes :func:`encode_reference` through
    ``compiled_reference`` (here a spy running it eagerly), the same features."""
    calls = []

    def spy(*args):
        calls.append(args[0].shape[0])
        return encode_reference(*args)

    monkeypatch.setattr(hash_grid_fast, "compiled_reference", spy)
    encoding = small_encoding()
    points = torch.rand(50, 3, generator=torch.Generator().manual_seed(3))
    batched = encoding(points).detach()  # gradients on
    encoding.eval()
    encoding(points)
    encoding.compile_evaluation = False
    with torch.no_grad():
        encoding(points)
    assert calls == []
    encoding.compile_evaluation = True
    with torch.no_grad():
        torch.testing.assert_close(encoding(points.reshape(5, 10, 3)), batched.reshape(5, 10, 8), atol=1e-6, rtol=1e-5)
        assert encoding(points[:1]).shape == (1, 8) and encoding(torch.zeros(0, 3)).shape == (0, 8)
        encoding.train()
        encoding(points[:20])
    assert calls == [50, 20]


def test_a_failing_compiler_leaves_plain_pytorch_with_one_warning(monkeypatch):
    """No C++ compiler (torch.compile raising at the first call): one warning naming what and why, then the function
    itself, call after call. An input the function itself refuses raises the function's error, compiling left on."""
    def broken_compile(function, **options):
        def compiled(*args):
            raise RuntimeError("InvalidCxxCompiler: no working C++ compiler found\nmore detail")
        return compiled
    monkeypatch.setattr(torch, "compile", broken_compile)

    def double(x: torch.Tensor) -> torch.Tensor:
        if x.ndim:
            raise ValueError("double expected a 0-d tensor")
        return 2 * x

    twice = CompiledOrEager(double, "doubling")
    with pytest.raises(ValueError, match="double expected a 0-d tensor"):
        twice(torch.ones(2))
    assert twice.failure is None
    with pytest.warns(UserWarning, match=r"doubling \(RuntimeError: InvalidCxxCompiler: no working C\+\+ compiler found\)"):
        assert twice(torch.tensor(3.0)) == 6.0
    assert twice.failure.startswith("RuntimeError")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert twice(torch.tensor(4.0)) == 8.0


def test_running_out_of_memory_raises_and_leaves_compiling_on(monkeypatch):
    """A compiled call that runs out of memory (a larger batch): the error is the caller's, and the next call compiles
    again (a plain retry that fit would otherwise have turned compiling off for the rest of the run)."""
    calls = []

    def out_of_memory(function, **options):
        def compiled(*args):
            calls.append(args[0].shape)
            if args[0].numel() > 2:
                raise torch.OutOfMemoryError("CUDA out of memory. Tried to allocate 2.00 GiB")
            return function(*args)
        return compiled
    monkeypatch.setattr(torch, "compile", out_of_memory)
    twice = CompiledOrEager(lambda x: 2 * x, "doubling")
    with pytest.raises(torch.OutOfMemoryError):
        twice(torch.ones(4))
    assert twice.failure is None
    torch.testing.assert_close(twice(torch.ones(2)), torch.full((2,), 2.0))
    assert calls == [(4,), (2,)]


def test_gathering_rows_in_parts_equals_index_select_and_its_gradient():
    """Rows of two as complex64/128 elements or as rows, and rows of three, in two parts as the encoding gathers them
    (the dense levels' rows from the table's first row, the hashed levels' from mid-table): the values and the table's
    gradient are index_select's, every part's gradient added into one buffer; a part whose features go unused adds
    nothing."""
    generator = torch.Generator().manual_seed(3)
    for width, dtype, complex_rows in ((2, torch.float32, True), (2, torch.float64, True), (2, torch.float32, False),
                                       (3, torch.float32, False)):
        table = torch.randn(50, width, generator=generator, dtype=dtype, requires_grad=True)
        starts = (0, 10)
        rows = [torch.randint(0, 40, (200,), generator=generator) for _ in starts]  # repeats: the backward must add them up
        upstream = [torch.randn(200, width, generator=generator, dtype=dtype) for _ in starts]
        gathered = gather_rows(table, rows, starts, complex_rows)
        expected = [torch.index_select(table[start:], 0, part) for start, part in zip(starts, rows)]
        assert all(found.dtype == dtype and torch.equal(found, wanted) for found, wanted in zip(gathered, expected))
        (grad,) = torch.autograd.grad(sum((found * up).sum() for found, up in zip(gathered, upstream)), table)
        (expected_grad,) = torch.autograd.grad(sum((wanted * up).sum() for wanted, up in zip(expected, upstream)), table)
        assert torch.allclose(grad, expected_grad, atol=1e-6)
        # only the second part used: its rows alone, counted from row 10, have a gradient
        (grad,) = torch.autograd.grad((gather_rows(table, rows, starts, complex_rows)[1] * upstream[1]).sum(), table)
        (expected_grad,) = torch.autograd.grad((torch.index_select(table[10:], 0, rows[1]) * upstream[1]).sum(), table)
        assert torch.allclose(grad, expected_grad, atol=1e-6) and bool((grad[:10] == 0).all())
    with pytest.raises(ValueError, match="a start for each part"):
        gather_rows(table, rows, (0,))


def test_the_encoding_is_the_reference_on_a_gpu_too():
    """Where a CUDA device is present: forward there (the gather path) against the reference on the CPU."""
    if not torch.cuda.is_available():
        pytest.skip("needs a CUDA device")
    encoding = small_encoding()
    points = random_points(300, seed=9)
    expected = encoding.forward_reference(points).detach()
    cuda = encoding.cuda()
    torch.testing.assert_close(cuda(points.cuda()).cpu(), expected)
    with torch.no_grad():
        torch.testing.assert_close(cuda(points.cuda()).cpu(), expected)
    assert isinstance(cuda, HashGridEncoding)


@pytest.mark.parametrize("precision", ["float16", "bfloat16"])
def test_a_table_read_in_half_precision_gives_the_float32_features_to_its_rounding(precision):
    """table_precision: every path (and the reference a compiled step runs) reads the table rounded to half
    precision; the features are those of the rounded table, and the gradient reaches the float32 parameter."""
    exact = small_encoding(features_per_level=2)
    exact.table.data.uniform_(-1.0, 1.0)  # values of order 1: the rounding is float16's or bfloat16's relative step
    half = small_encoding(features_per_level=2, table_precision=precision)
    half.load_state_dict(exact.state_dict())
    rounded = small_encoding(features_per_level=2)
    rounded.table.data.copy_(exact.table.data.to(getattr(torch, precision)).float())
    points = random_points(500, seed=3)
    with torch.no_grad():
        wanted = encode_reference(points, *rounded.reference_inputs())
    for path in (GATHER, COMPILED) if has_cxx_compiler() else (GATHER,):
        with torch.no_grad():
            got = encode(path, half, points)
        assert got.dtype == torch.float32
        torch.testing.assert_close(got, wanted, atol=1e-5, rtol=1e-5)
    features = half(points)  # with gradients: the gather path
    torch.testing.assert_close(features, wanted, atol=1e-5, rtol=1e-5)
    features.square().sum().backward()
    assert half.table.grad is not None and half.table.grad.dtype == torch.float32 and bool(half.table.grad.abs().sum() > 0)
    assert half.table.dtype == torch.float32  # what the optimiser steps
    with pytest.raises(ValueError, match="table_precision must be null, float16 or bfloat16"):
        small_encoding(table_precision="float8")
