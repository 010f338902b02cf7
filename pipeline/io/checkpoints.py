"""torch checkpoints: written atomically with reproducible bytes, read safely (weights_only=True)."""

from __future__ import annotations

import math
import os
import tempfile
from pathlib import Path
from typing import Any

from pipeline.io.errors import DataError, not_found


def save_torch(path: Path | str, obj: Any) -> None:
    """torch.save via a temporary file in the same folder and a rename (never a half-written file; a full disk
    is a DataError naming `path`).
    Saved through a file object, so the zip's root folder is torch's fixed "archive", not the random
    temporary name: the same object gives the same bytes (and file hash) on every run."""
    import torch

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    try:
        with open(tmp, "wb") as f:
            torch.save(obj, f)
        os.replace(tmp, path)
    except BaseException as e:
        Path(tmp).unlink(missing_ok=True)
        cause = e if isinstance(e, OSError) else e.__context__  # torch reports a failed write as a RuntimeError
        if isinstance(cause, OSError):  # disk full, quota, read-only, ...
            raise DataError(f"could not write {path} ({cause.strerror or cause}); the file was left as it was") from e
        raise


def load_torch(path: Path | str, fmt: str, redo: str) -> dict[str, Any]:
    """torch.load(weights_only=True) of an rpodguard checkpoint dict whose `format` is `fmt`; a missing,
    unreadable, damaged (a record failing its CRC-32), foreign or non-finite file is a DataError ending in `redo`
    (how to remake it)."""
    import torch

    path = Path(path)
    if not path.exists():
        raise not_found(path, "checkpoint")
    if not path.is_file():  # a FIFO or device would block the read for ever
        raise DataError(f"checkpoint {path} is not a regular file; {redo}")
    damaged = _damaged_record(path)
    if damaged:
        raise DataError(f"checkpoint {path} {damaged}; {redo}")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        raise DataError(f"checkpoint {path} is unreadable ({type(e).__name__}: {e}); {redo}") from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != fmt:
        raise DataError(f"{path} is not an rpodguard checkpoint of format {fmt}; {redo}")
    bad = _nonfinite(ckpt)
    if bad:
        raise DataError(f"checkpoint {path} holds non-finite weights or values ({', '.join(bad[:3])}); {redo}")
    return ckpt


def _damaged_record(path: Path) -> str | None:
    """What is wrong with the zip archive torch.save writes, or None: every record (the pickled dict, each
    tensor's bytes) carries a CRC-32 there that torch.load never checks, so a flipped byte inside a weight would
    load as a wrong weight; zipfile checks them all (one read of the file)."""
    import zipfile

    try:
        with zipfile.ZipFile(path) as archive:
            bad = archive.testzip()
    except (zipfile.BadZipFile, OSError, EOFError, ValueError) as e:
        return f"is unreadable (not the zip archive torch.save writes: {e})"
    return None if bad is None else f"is damaged: record {bad} fails its CRC-32 (changed since it was written)"


def _nonfinite(obj: Any, prefix: str = "") -> list[str]:
    """Names of the floating-point tensors and numbers (nested in dicts and lists; e.g. a detector's
    threshold) with a NaN or inf."""
    import torch

    if isinstance(obj, dict):
        return [n for k, v in obj.items() for n in _nonfinite(v, f"{prefix}{k}.")]
    if isinstance(obj, (list, tuple)):
        return [n for i, v in enumerate(obj) for n in _nonfinite(v, f"{prefix}{i}.")]
    if isinstance(obj, torch.Tensor) and obj.is_floating_point() and not bool(torch.isfinite(obj).all()):
        return [prefix.rstrip(".")]
    if isinstance(obj, float) and not math.isfinite(obj):
        return [prefix.rstrip(".")]
    return []
