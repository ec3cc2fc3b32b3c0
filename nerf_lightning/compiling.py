"""``torch.compile`` where this machine can run it, plain PyTorch where it cannot.

On a CPU, inductor turns a function into C++ that it builds with the system's compiler (g++ or clang) the first time
the function runs, and caches on disk. A machine without one (a fresh Windows or macOS install), or a platform
inductor does not support, raises at that first call: :class:`CompiledOrEager` then warns once and runs the
function as written from then on, so that nothing but speed depends on the compiler.
"""

from __future__ import annotations

import logging
import warnings
from collections.abc import Callable
from typing import Any

import torch

log = logging.getLogger(__name__)


class CompiledOrEager:
    """``function`` through ``torch.compile`` with ``options`` (by default ``dynamic=True``: shapes that change
    from call to call, packed samples), compiled at its first call; ``function`` itself for the rest of the process
    once compiling or running the compiled code has failed where ``function`` itself runs (one warning naming
    ``what`` and the error). Where ``function`` fails too, its own error is raised and compiling stays on. With
    ``fullgraph=True`` a graph break is such a failure.

    ``failure`` is None, or the error that turned compilation off."""

    def __init__(self, function: Callable[..., Any], what: str, **options: Any) -> None:
        self.function, self.what = function, what
        self.options = {"dynamic": True, **options}
        self.compiled: Callable[..., Any] | None = None
        self.failure: str | None = None

    def __call__(self, *args: Any) -> Any:
        if self.failure is None:
            try:
                if self.compiled is None:
                    log.info("compiling %s with torch.compile: the first call takes a while (seconds once cached on disk)", self.what)
                    self.compiled = torch.compile(self.function, **self.options)
                return self.compiled(*args)
            except torch.OutOfMemoryError:
                raise  # the input's size, not the compiler: a plain retry that fits would turn compiling off for good
            except Exception as error:  # noqa: BLE001 - the plain function decides whether it was the compiler's fault
                # an error of the input itself (a bad shape, out of memory) raises again here, as the function's own,
                # and leaves compiling on; only a call that runs plainly turns it off
                result = self.function(*args)
                lines = str(error).strip().splitlines()
                self.failure = f"{type(error).__name__}: {lines[0] if lines else ''}"
                warnings.warn(f"torch.compile failed for {self.what} ({self.failure}); running it in plain PyTorch from now "
                              f"on, slower (on a CPU inductor needs a working C++ compiler, g++ or clang, on the PATH)", stacklevel=2)
                return result
        return self.function(*args)
