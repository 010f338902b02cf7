"""File I/O shared by the stages: atomic writes, zarr stacks, checksums, clear errors."""
from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import tempfile
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterator

import numpy as np


class StageError(RuntimeError):
    """An error the user can act on; the CLI prints its message without a traceback."""


def atomic_write_text(path: Path | str, text: str) -> None:
    """Write text to path via a temporary file in the same folder and a rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_json(path: Path | str, obj: Any) -> None:
    atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=True, default=_json_default) + "\n")


def write_metrics(path: Path | str, metrics: dict[str, Any], params: dict[str, Any]) -> None:
    """Write a stage's metrics JSON stamped with the params profile it ran on and the UTC time."""
    stamp = {"profile": params.get("profile_name", "unknown"),
             "produced": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")}
    write_json(path, {**metrics, **stamp})


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o)}")


def save_torch(path: Path | str, obj: Any) -> None:
    """torch.save via a temporary file in the same folder and a rename (never a half-written file)."""
    import torch

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    try:
        torch.save(obj, tmp)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def load_torch(path: Path | str, fmt: str, stage: str) -> dict[str, Any]:
    """torch.load(weights_only=True) of an rpodguard checkpoint dict whose `format` is `fmt`;
    a missing, unreadable or foreign file is a StageError telling the user to re-run `rpod <stage>`."""
    import torch

    path = Path(path)
    if not path.exists():
        raise StageError(f"checkpoint {path} not found (run `rpod {stage}` first)")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        raise StageError(f"checkpoint {path} is unreadable ({type(e).__name__}: {e}); re-run `rpod {stage}`") from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != fmt:
        raise StageError(f"{path} is not an rpodguard checkpoint of format {fmt}; re-run `rpod {stage}`")
    return ckpt


def read_json(path: Path | str) -> Any:
    path = Path(path)
    if not path.exists():
        raise StageError(f"{path} not found (run the stage that writes it first)")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise StageError(f"{path} is not valid JSON: {e}") from None


@contextlib.contextmanager
def atomic_dir(path: Path | str) -> Iterator[Path]:
    """Yield a temporary sibling folder; on success it replaces `path` whole, on error it is removed.

    A later stage therefore never sees a half-written output folder.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp"))
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if path.exists():
        old = path.with_name(f".{path.name}.old")
        shutil.rmtree(old, ignore_errors=True)
        os.replace(path, old)
        os.replace(tmp, path)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp, path)


def save_figure(fig: Any, path: Path | str, dpi: int = 110) -> None:
    """Write a matplotlib Figure (pipeline/figures.py) as PNG atomically (temporary file + rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(tmp, dpi=dpi)
    tmp.replace(path)


def file_hash(path: Path | str, n: int = 16) -> str:
    """Short sha256 of a file (used to tie derived artifacts to a checkpoint)."""
    path = Path(path)
    if not path.exists():
        raise StageError(f"{path} not found")
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()[:n]


def open_zarr(path: Path | str, what: str = "zarr store"):
    """Open a zarr group read-only with a clear message when it is missing or corrupt."""
    import zarr

    path = Path(path)
    if not path.exists():
        raise StageError(f"{what} {path} not found (run the stage that writes it first)")
    try:
        return zarr.open_group(str(path), mode="r")
    except Exception as e:  # zarr raises several types for a damaged store
        raise StageError(f"{what} {path} is unreadable or corrupt ({type(e).__name__}: {e}); "
                         f"delete it and re-run the stage that writes it") from None


def read_parquet(path: Path | str, what: str = "table"):
    import pandas as pd

    path = Path(path)
    if not path.exists():
        raise StageError(f"{what} {path} not found (run the stage that writes it first)")
    try:
        return pd.read_parquet(path)
    except Exception as e:
        raise StageError(f"{what} {path} is unreadable ({type(e).__name__}: {e})") from None
