"""Atomic file writes (temporary file or folder + rename: a reader never sees half a file) and JSON,
figure and hash helpers."""

from __future__ import annotations

import contextlib
import glob
import hashlib
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from pipeline.io.errors import DataError
from pipeline.io.files import open_regular, read_bytes
from pipeline.io.store import is_sealed, seal_zarr


def atomic_write_text(path: Path | str, text: str) -> None:
    """Write text to path via a temporary file in the same folder and a rename."""
    _atomic_write(path, "w", text)


def atomic_write_bytes(path: Path | str, data: bytes) -> None:
    """Write bytes to path via a temporary file in the same folder and a rename."""
    _atomic_write(path, "wb", data)


def _atomic_write(path: Path | str, mode: str, payload: str | bytes) -> None:
    """`payload` to path in `mode` ("w" or "wb") through a temporary file in the same folder and a rename: a kill
    leaves the previous file or none, never half of one."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, mode) as f:
            f.write(payload)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def check_writable(*folders: Path | str) -> None:
    """A DataError naming the first of `folders` (created when missing) where no file can be created (read-only,
    not a folder, no permission): for a stage to find out before its expensive work, not after it."""
    for folder in map(Path, folders):
        try:
            folder.mkdir(parents=True, exist_ok=True)
            with tempfile.TemporaryFile(dir=folder):
                pass
        except OSError as e:
            raise DataError(f"{folder} is not writable ({e.strerror or e}); the outputs go there") from None


def write_json(path: Path | str, obj: Any) -> None:
    """`obj` as indented JSON with sorted keys (numpy scalars and arrays as numbers and lists), atomically."""
    atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=True, default=_json_default) + "\n")


def _json_default(o: Any) -> Any:
    """numpy scalars and arrays as plain JSON values."""
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o)}")


def read_json(path: Path | str) -> Any:
    """A JSON file; a DataError when it is missing (naming how to make it), not a regular file (a FIFO:
    `pipeline.io.files.open_regular`, never blocking) or not valid JSON."""
    path = Path(path)
    try:
        return json.loads(read_bytes(path))
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise DataError(f"{path} is not valid JSON: {e}") from None


OWNER = ".rpodguard-owner"  # inside every temporary folder `owned_temp` makes: the folder's own name (its token)
OLD = "previous"  # inside an `owned_temp`: the output being replaced, while atomic_dir swaps it


def owned_temp(path: Path | str) -> Path:
    """A new temporary folder beside `path`, `.NAME.PID.RANDOM.tmp`, holding the file OWNER with its own name: the
    token `remove_stale_temps` checks before it deletes anything (a folder of the user's with a similar name
    lacks it and is never touched)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.{os.getpid()}.", suffix=".tmp"))
    (tmp / OWNER).write_text(tmp.name)
    return tmp


def _owned(folder: Path) -> bool:
    """Whether `folder` is a real folder holding the token `owned_temp` wrote into it."""
    token = folder / OWNER
    try:
        return (
            not folder.is_symlink()
            and folder.is_dir()
            and not token.is_symlink()
            and token.is_file()
            and token.read_text() == folder.name
        )
    except OSError:
        return False


def followed(path: Path | str) -> Path:
    """`path`, or the path a symbolic link there points to (so a linked output folder is written, not replaced)."""
    path = Path(path)
    return Path(os.path.realpath(path)) if path.is_symlink() else path


@contextlib.contextmanager
def atomic_dir(path: Path | str) -> Iterator[Path]:
    """Yield a temporary folder; on success it replaces `path` whole, on error it is removed.

    A later stage therefore never sees a half-written output folder. Every zarr store in it (the folder
    itself, or any `*.zarr` below it) is sealed with its manifest (`seal_zarr`), unless its writer
    sealed it, before the rename. The folder yielded lies inside an `owned_temp` beside `path` (a symbolic
    link at `path` is followed: its target is replaced), which also holds the previous `path` while the two
    are swapped: nothing outside it is ever deleted, and `remove_stale_temps` removes it once its run is gone.
    """
    path = followed(path)
    owner = owned_temp(path)
    tmp = owner / path.name
    tmp.mkdir()
    try:
        yield tmp
        for store in [tmp, *sorted(tmp.rglob("*.zarr"))]:
            if (store / "zarr.json").is_file() and not is_sealed(store):
                seal_zarr(store)
        if path.exists():
            os.replace(path, owner / OLD)
        try:
            os.replace(tmp, path)
        except BaseException:
            if (owner / OLD).exists():
                os.replace(owner / OLD, path)
            raise
    finally:
        shutil.rmtree(owner, ignore_errors=True)


@contextlib.contextmanager
def exclusive(lock: Path | str, what: str) -> Iterator[None]:
    """Hold an exclusive lock on the file `lock` (created if missing) while the block runs: fcntl.flock, which
    the system releases when the holder ends, also when it is killed. A DataError naming `what` and the
    holder's process id when another process holds it (no waiting). The lock file is removed when the block
    ends (a killed holder's file stays, unlocked: the next run takes it over)."""
    import fcntl

    lock = Path(lock)
    lock.parent.mkdir(parents=True, exist_ok=True)
    while True:
        f = open(lock, "a+")
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            f.seek(0)
            holder = f.read().strip() or "?"
            f.close()
            raise DataError(
                f"{what} is being written by another process (pid {holder}, lock {lock}); wait for it to finish"
            ) from None
        try:  # the file locked is still the one at `lock` (its last holder did not remove it in between)
            if os.stat(lock).st_ino == os.fstat(f.fileno()).st_ino:
                break
        except FileNotFoundError:
            pass
        f.close()
    with f:
        f.truncate(0)
        f.write(str(os.getpid()))
        f.flush()
        try:
            yield
        finally:
            lock.unlink(missing_ok=True)  # while still held: a process that opened it meanwhile tries again
            fcntl.flock(f, fcntl.LOCK_UN)


def remove_stale_temps(path: Path | str) -> list[Path]:
    """Delete the temporary folders (`owned_temp`) that runs killed since (their process is gone) left next to
    `path`, putting back a previous output one of them held when `path` is missing; a concurrent live run's
    folder, and any folder without the token, are kept. Returns the folders removed."""
    path = followed(path)
    removed = []
    for d in sorted(path.parent.glob(f".{glob.escape(path.name)}.*.tmp")):
        pid = d.name[len(path.name) + 2 :].split(".", 1)[0]
        if not _owned(d) or (pid.isdigit() and _alive(int(pid))):
            continue
        if (d / OLD).is_dir() and not os.path.lexists(path):
            os.replace(d / OLD, path)
        shutil.rmtree(d, ignore_errors=True)
        removed.append(d)
    return removed


def _alive(pid: int) -> bool:
    """Whether a process with this id exists on this machine."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


@contextlib.contextmanager
def atomic_outputs(*paths: Path | str, dirs: tuple[Path | str, ...] = ()) -> Iterator[list[Path]]:
    """Yield temporary stand-ins for the files `paths` and the folders `dirs` (in that order; the folders
    are created empty). On success all are renamed into place one right after another, once every one
    was written; on error none is, so a stage's model, metrics and curves never come from different runs."""
    files, folders = [Path(p) for p in paths], [Path(d) for d in dirs]
    tmps = []
    for p in files + folders:
        p.parent.mkdir(parents=True, exist_ok=True)
        tmps.append(p.with_name(f".{p.name}.{os.getpid()}.tmp"))
    try:
        for t in tmps[len(files) :]:
            shutil.rmtree(t, ignore_errors=True)
            t.mkdir()
        yield tmps
        missing = [str(p) for p, t in zip(files, tmps) if not t.exists()]
        if missing:
            raise RuntimeError(f"atomic_outputs: {missing} were not written")
    except BaseException as e:
        for t in tmps:
            if t.is_dir():
                shutil.rmtree(t, ignore_errors=True)
            else:
                t.unlink(missing_ok=True)
        if isinstance(e, DataError):  # "could not write .pose.pt.PID.tmp": name the output, not its stand-in
            message = str(e)
            for p, t in zip(files + folders, tmps):
                message = message.replace(str(t), str(p))
            raise DataError(message) from e
        raise
    for p, t in zip(files + folders, tmps):
        if t.is_dir() and p.exists():
            old = p.with_name(f".{p.name}.{os.getpid()}.old")
            os.replace(p, old)
            os.replace(t, p)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(t, p)


def save_figure(fig: Any, path: Path | str, dpi: int = 110) -> None:
    """Write a matplotlib Figure (pipeline/report/figures.py) as PNG atomically (temporary file + rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(tmp, dpi=dpi)
    tmp.replace(path)


def file_hash(path: Path | str, n: int = 16) -> str:
    """Short sha256 of a file (used to tie derived artifacts to a checkpoint)."""
    h = hashlib.sha256()
    with open_regular(path) as f:  # a FIFO or device would block the read for ever
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()[:n]
