"""`StageError`: an error in how a stage is run (params, a refused run, the Ray engine) that the user can act on."""

from __future__ import annotations

from pipeline.io.errors import DataError


class StageError(DataError):
    """An error the user can act on; the CLI prints its message without a traceback (as for any DataError)."""
