"""`DataError`: a problem with an input file that the user can fix; the message names the file."""

from __future__ import annotations

from pathlib import Path
from typing import Callable


class DataError(RuntimeError):
    """A missing, unreadable, corrupt or inconsistent input file; applications print the message alone
    (no traceback), so it names the file and says what to do."""


GENERIC_HINT = "run the stage that writes it first"  # when the application names no way to make the file
_HINT: list[Callable[[Path], str]] = [lambda path: GENERIC_HINT]


def set_missing_hint(hint: Callable[[Path], str]) -> None:
    """Let the application say how a missing input is made (`rpod` names the dvc.yaml stage that writes it)."""
    _HINT[0] = hint


def not_found(path: Path | str, what: str = "") -> DataError:
    """The one-line error for a missing input: "[what ]PATH not found: HINT" (HINT: `set_missing_hint`)."""
    return DataError(f"{what + ' ' if what else ''}{path} not found: {_HINT[0](Path(path))}")
