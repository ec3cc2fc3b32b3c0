"""How the commands fail: one clear line naming the file or key and what was expected, and exit status 2.

Errors in what a user gave (a path, a file's contents, a config value, a checkpoint) are raised where the input
enters as ``FileNotFoundError``, ``NotADirectoryError``, ``PermissionError`` or ``ValueError`` with a message that
names it. :func:`report_errors` wraps each command's Hydra task so that such an error prints as
``nerf-train: error: <message>`` on stderr, without a traceback, and the command exits 2. Anything else is a bug
and keeps its traceback; ``NERF_LIGHTNING_TRACEBACK=1`` shows the traceback of input errors too. Hydra itself
reports an unknown config key or group option before the task starts (its message names the key and lists the
options) and exits 1.
"""

from __future__ import annotations

import functools
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, NoReturn

from hydra.errors import InstantiationException
from omegaconf.errors import MissingMandatoryValue

INPUT_ERRORS = (FileNotFoundError, NotADirectoryError, PermissionError, ValueError)


class NonFiniteLossError(RuntimeError):
    """Training produced a NaN or infinite loss; the run stops and its last checkpoint is kept as it was."""


class MissingExtraError(ImportError):
    """An optional dependency the command needs is not installed; the message names the extra and how to install it."""


def input_error(error: BaseException) -> BaseException | None:
    """The user-input error behind ``error`` (unwrapping Hydra's InstantiationException), or None for a bug."""
    while isinstance(error, InstantiationException) and error.__cause__ is not None:
        error = error.__cause__
    if isinstance(error, MissingMandatoryValue):  # a ??? key left unset (data.root of a format without a default)
        key = getattr(error, "full_key", None) or "a required key"
        return ValueError(f"{key} has no value and needs one: give it on the command line, {key}=...")
    return error if isinstance(error, (*INPUT_ERRORS, NonFiniteLossError, MissingExtraError)) else None


def fail(command: str, message: str) -> NoReturn:
    """Print ``<command>: error: <message>`` on stderr and exit with status 2."""
    print(f"{command}: error: {message}", file=sys.stderr)
    sys.exit(2)


def report_errors(command: str) -> Callable[[Callable[..., Any]], Callable[..., Any]]:
    """Wrap the Hydra task function of ``command``: input errors print one line on stderr and exit 2 (see the
    module's docstring)."""

    def decorate(task: Callable[..., Any]) -> Callable[..., Any]:
        @functools.wraps(task)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            try:
                return task(*args, **kwargs)
            except Exception as error:
                cause = input_error(error)
                if cause is None or os.environ.get("NERF_LIGHTNING_TRACEBACK"):
                    raise
                fail(command, str(cause))

        return wrapper

    return decorate


def ensure_writable(folder: str | Path, key: str) -> Path:
    """Create ``folder`` and check a file can be written there; PermissionError naming ``key`` otherwise."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe = folder / ".write_test"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as error:
        raise PermissionError(f"cannot write to the folder {folder} ({error.strerror or error}); choose another with {key}=...") from error
    return folder
