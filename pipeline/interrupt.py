"""Stopping on a signal: SIGINT (Ctrl-C) and SIGTERM set one stop flag of the process and raise `Interrupted`.

The command line installs the handler (`install`, stages/cli.py). A signal then raises `Interrupted` in the main
thread at its next Python instruction, so `finally` blocks remove temporaries and locks on the way out. Where the
signal lands inside a library that swallows exceptions (Blender's Cycles runs its render engine in Python and
catches whatever that raises: a plain Ctrl-C there was lost and the stage ran to the end), the code runs `deferred`:
the signal only sets the flag, and `check` raises once control is back, between two frames. A second signal while
the first one's clean-up runs is recorded, not raised, so the clean-up finishes.

`Interrupted` derives from BaseException, as KeyboardInterrupt does: no `except Exception` stops it.
"""

from __future__ import annotations

import contextlib
import signal
from typing import Any, Iterator

SIGNALS = (signal.SIGINT, signal.SIGTERM)
EXIT_STATUS = 130  # the status a command stopped by a signal exits with (the shell's 128 + SIGINT)

_state: dict[str, Any] = {"signal": None, "deferred": 0, "raised": False}


class Interrupted(BaseException):
    """The process was asked to stop by a signal (`signum`); raised once, by the handler or by `check`."""

    def __init__(self, signum: int) -> None:
        self.signum = signum
        super().__init__(signal.Signals(signum).name)


def _handler(signum: int, frame: Any) -> None:
    """Set the stop flag; raise `Interrupted` unless deferred or already raised."""
    _state["signal"] = _state["signal"] or signum
    if not _state["deferred"] and not _state["raised"]:
        _state["raised"] = True
        raise Interrupted(signum)


def install() -> None:
    """Handle SIGINT and SIGTERM in this process (main thread only) with the stop flag (see the module docstring)."""
    for sig in SIGNALS:
        signal.signal(sig, _handler)


def requested() -> int | None:
    """The signal that asked this process to stop, or None."""
    return _state["signal"]


def check() -> None:
    """Raise `Interrupted` when a signal asked this process to stop (once): between the frames of a loop."""
    if _state["signal"] is not None and not _state["raised"]:
        _state["raised"] = True
        raise Interrupted(_state["signal"])


@contextlib.contextmanager
def deferred() -> Iterator[None]:
    """Within the block a signal only sets the stop flag (code that would swallow the exception runs here); the
    block's end checks it (`check`)."""
    _state["deferred"] += 1
    try:
        yield
    finally:
        _state["deferred"] -= 1
    check()
