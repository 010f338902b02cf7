"""File I/O shared by the stages: atomic writes, zarr stacks, checksums, clear errors."""
from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import os
import shutil
import tempfile
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from stages.artifacts.paths import DVC_YAML


class StageError(RuntimeError):
    """An error the user can act on; the CLI prints its message without a traceback."""




@functools.cache
def dvc_stages() -> dict[str, dict[str, Any]]:
    """dvc.yaml's stages (name -> its entry: cmd, deps, params, outs, ...); empty without dvc.yaml."""
    import yaml

    if not DVC_YAML.is_file():
        return {}
    return yaml.safe_load(DVC_YAML.read_text()).get("stages", {})


def _outputs(stage: dict[str, Any]) -> list[Path]:
    """A dvc.yaml stage's outputs: its outs, metrics and plots."""
    return [Path(next(iter(o)) if isinstance(o, dict) else o) for kind in ("outs", "metrics", "plots")
            for o in stage.get(kind, [])]


def producer(path: Path | str) -> str | None:
    """The dvc.yaml stage whose output is `path` (or a folder holding it), or None."""
    path = Path(path)
    if path.is_absolute():
        path = Path(os.path.relpath(path, DVC_YAML.parent if path.is_relative_to(DVC_YAML.parent) else Path.cwd()))
    return next((name for name, st in dvc_stages().items()
                 if any(path == out or out in path.parents for out in _outputs(st))), None)


def make_hint(path: Path | str) -> str:
    """How to make `path`: "run `dvc repro STAGE` (or `rpod ...`)" for the stage that writes it."""
    stage = producer(path)
    if stage is None:
        return "run the stage that writes it first"
    return f"run `dvc repro {stage}` (or `{dvc_stages()[stage]['cmd']}`)"


def not_found(path: Path | str, what: str = "") -> StageError:
    """The one-line error for a missing input, naming the stage that writes it."""
    return StageError(f"{what + ' ' if what else ''}{path} not found: {make_hint(path)}")


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


def write_metrics(path: Path | str, metrics: dict[str, Any], profile: str) -> None:
    """Write a stage's metrics JSON stamped with the params profile it ran on (`profile_name`) and the UTC time."""
    stamp = {"profile": profile,
             "produced": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")}
    write_json(path, {**metrics, **stamp})


def _json_default(o: Any) -> Any:
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o)}")


def save_torch(path: Path | str, obj: Any) -> None:
    """torch.save via a temporary file in the same folder and a rename (never a half-written file).
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
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def load_torch(path: Path | str, fmt: str, stage: str) -> dict[str, Any]:
    """torch.load(weights_only=True) of an rpodguard checkpoint dict whose `format` is `fmt`;
    a missing, unreadable or foreign file is a StageError telling the user to re-run `rpod <stage>`."""
    import torch

    path = Path(path)
    if not path.exists():
        raise not_found(path, "checkpoint")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:
        raise StageError(f"checkpoint {path} is unreadable ({type(e).__name__}: {e}); re-run `rpod {stage}`") from None
    if not isinstance(ckpt, dict) or ckpt.get("format") != fmt:
        raise StageError(f"{path} is not an rpodguard checkpoint of format {fmt}; re-run `rpod {stage}`")
    bad = _nonfinite_tensors(ckpt)
    if bad:
        raise StageError(f"checkpoint {path} holds non-finite weights ({', '.join(bad[:3])}); re-run `rpod {stage}`")
    return ckpt


def _nonfinite_tensors(obj: Any, prefix: str = "") -> list[str]:
    """Names of the floating-point tensors (nested in dicts) with a NaN or inf."""
    import torch

    if isinstance(obj, dict):
        return [n for k, v in obj.items() for n in _nonfinite_tensors(v, f"{prefix}{k}.")]
    if isinstance(obj, torch.Tensor) and obj.is_floating_point() and not bool(torch.isfinite(obj).all()):
        return [prefix.rstrip(".")]
    return []


def read_json(path: Path | str) -> Any:
    path = Path(path)
    if not path.exists():
        raise not_found(path)
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise StageError(f"{path} is not valid JSON: {e}") from None


@contextlib.contextmanager
def atomic_dir(path: Path | str) -> Iterator[Path]:
    """Yield a temporary sibling folder; on success it replaces `path` whole, on error it is removed.

    A later stage therefore never sees a half-written output folder. Every zarr store in it (the folder
    itself, or any `*.zarr` below it) is sealed with its manifest (`seal_zarr`), unless its writer
    sealed it, before the rename. The temporary name carries the process id, so `remove_stale_temps`
    never deletes a live run's folder.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.{os.getpid()}.", suffix=".tmp"))
    try:
        yield tmp
        for store in [tmp, *sorted(tmp.rglob("*.zarr"))]:
            if (store / "zarr.json").is_file() and not is_sealed(store):
                seal_zarr(store)
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


def remove_stale_temps(path: Path | str) -> list[Path]:
    """Delete the temporary folders `atomic_dir` left next to `path` in runs that were killed (their
    process is gone); a concurrent live run's folder is kept. Returns the folders removed."""
    path = Path(path)
    removed = []
    for d in path.parent.glob(f".{path.name}.*.tmp"):
        pid = d.name[len(path.name) + 2:].split(".", 1)[0]
        if pid.isdigit() and _alive(int(pid)):
            continue
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
        for t in tmps[len(files):]:
            shutil.rmtree(t, ignore_errors=True)
            t.mkdir()
        yield tmps
        missing = [str(p) for p, t in zip(files, tmps) if not t.exists()]
        if missing:
            raise RuntimeError(f"atomic_outputs: {missing} were not written")
    except BaseException:
        for t in tmps:
            if t.is_dir():
                shutil.rmtree(t, ignore_errors=True)
            else:
                t.unlink(missing_ok=True)
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
    path = Path(path)
    if not path.exists():
        raise not_found(path)
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()[:n]


MANIFEST = "rpodguard_manifest"  # key in the root group's attributes (zarr.json)
MANIFEST_FORMAT = "rpodguard-zarr-manifest/2"  # /1 summed the codec's own crc32c too: a constant


def create_array(group: Any, name: str, **kwargs: Any) -> Any:
    """`group.create_array` with the project's codecs: zstd, then a crc32c checksum of every chunk,
    and every chunk written (also all-zero ones) so a missing chunk file is always an error."""
    from zarr.codecs import Crc32cCodec, ZstdCodec

    return group.create_array(name, compressors=[ZstdCodec(level=0), Crc32cCodec()],
                              config={"write_empty_chunks": True}, **kwargs)


def reopen_array(path: Path | str, name: str) -> Any:
    """An array that `create_array` made, reopened for writing (path or fsspec URL of its store) with the
    same rule: every chunk written, also all-zero ones (zarr keeps that setting only per open array)."""
    import zarr

    with zarr.config.set({"array.write_empty_chunks": True}):
        return zarr.open_array(str(path), path=name, mode="r+")


def _chunk_keys(shape: tuple[int, ...], chunks: tuple[int, ...]) -> list[str]:
    """Chunk file names of a zarr v3 array (default encoding "c/i/j/...") over its whole grid."""
    import itertools

    grid = [range(-(-n // c)) for n, c in zip(shape, chunks)]
    return ["/".join(["c", *map(str, ix)]) for ix in itertools.product(*grid)]


def store_fs(path: Path | str) -> tuple[Any, str]:
    """(fsspec filesystem, root path on it) of a zarr store given as a local path or an fsspec URL."""
    from fsspec.core import url_to_fs

    return url_to_fs(str(path))


def chunk_crc32c(fs: Any, path: str) -> str:
    """crc32c (8 hex digits) of one stored chunk object's payload, as the manifest lists it: the bytes
    before the 4-byte crc32c the codec appends (the crc32c of data followed by its own crc32c is the
    same constant for every chunk, so it could not tell one chunk from another).
    A chunk whose own trailer does not match its payload gives "damaged", which no manifest lists.
    """
    import google_crc32c

    data = fs.cat_file(path)
    crc = google_crc32c.value(data[:-4])
    return f"{crc:08x}" if data[-4:] == crc.to_bytes(4, "little") else "damaged"


def _chunk_files(fs: Any, root: str, name: str) -> set[str]:
    """Keys (c/i/j/...) of the chunk objects stored under array `name`."""
    base = f"{root.rstrip('/')}/{name}/"
    return {f[len(base):] for f in fs.find(base) if f.startswith(base) and f[len(base):].startswith("c/")}


def seal_zarr(path: Path | str, crc32c: dict[str, dict[str, str]] | None = None) -> None:
    """Write the store's manifest last, into the root group's attributes: per array its shape, chunks
    and the crc32c of every chunk object. `crc32c` ({array: {chunk key: crc}}, from the workers that
    wrote the chunks) is used where given; other arrays are read back and checksummed here.

    Refuses (RuntimeError: a bug in the writer) an array without the crc32c codec or with a chunk of
    its grid never written (or not checksummed).
    """
    import zarr

    fs, root = store_fs(path)
    group = zarr.open_group(str(path), mode="r")
    arrays: dict[str, Any] = {}
    for name, arr in sorted(group.arrays()):
        if not any(type(c).__name__ == "Crc32cCodec" for c in arr.compressors):
            raise RuntimeError(f"{path}/{name} was written without the crc32c codec (use stages.io.create_array)")
        keys = _chunk_keys(arr.shape, arr.chunks)
        given = (crc32c or {}).get(name)
        missing = set(keys) - _chunk_files(fs, root, name)
        if given:
            missing |= set(keys) - set(given)
        unwritten = sorted(missing)
        if unwritten:
            raise RuntimeError(f"{path}/{name}: chunk {unwritten[0]} was never written ({len(unwritten)} in all)")
        crcs = {k: given[k] for k in keys} if given else {k: chunk_crc32c(fs, f"{root}/{name}/{k}") for k in keys}
        if "damaged" in crcs.values():
            raise RuntimeError(f"{path}/{name}: a chunk was damaged while it was written")
        arrays[name] = {"shape": list(arr.shape), "chunks": list(arr.chunks), "crc32c": crcs}
    zarr.open_group(str(path), mode="r+").attrs[MANIFEST] = {"format": MANIFEST_FORMAT, "arrays": arrays}


def is_sealed(path: Path | str) -> bool:
    """Whether the store at `path` already carries its manifest."""
    fs, root = store_fs(path)
    try:
        return MANIFEST in json.loads(fs.cat_file(f"{root}/zarr.json")).get("attributes", {})
    except (FileNotFoundError, ValueError, AttributeError):
        return False


def _manifest(path: Path | str, what: str) -> dict[str, Any]:
    """The manifest's arrays from the root zarr.json, or a StageError."""
    redo = "delete it and re-run the stage that writes it"
    fs, root = store_fs(path)
    try:
        meta = json.loads(fs.cat_file(f"{root}/zarr.json"))
    except FileNotFoundError:
        raise StageError(f"{what} {path} is not a zarr store (no zarr.json); {redo}") from None
    except (json.JSONDecodeError, UnicodeDecodeError):
        raise StageError(f"{what} {path}/zarr.json is damaged; {redo}") from None
    manifest = meta.get("attributes", {}).get(MANIFEST) if isinstance(meta, dict) else None
    if manifest is None:
        raise StageError(f"{what} {path} has no checksum manifest (an interrupted write or an older "
                         f"rpodguard); {redo}")
    fmt = manifest.get("format") if isinstance(manifest, dict) else None
    if isinstance(fmt, str) and fmt.startswith("rpodguard-zarr-manifest/") and fmt != MANIFEST_FORMAT:
        raise StageError(f"{what} {path} was written by an older rpodguard (checksum manifest {fmt}); {redo}")
    arrays = manifest.get("arrays") if fmt == MANIFEST_FORMAT else None
    if not isinstance(arrays, dict):
        raise StageError(f"{what} {path}: the checksum manifest is damaged; {redo}")
    return arrays


def verify_zarr(path: Path | str, what: str = "zarr store") -> None:
    """Check a store (local path or fsspec URL) against its manifest: every array and chunk object
    present, every crc32c equal. One StageError naming the store and the first bad chunk; costs one
    read of the compressed bytes.
    """
    redo = "delete it and re-run the stage that writes it"
    arrays = _manifest(path, what)
    fs, root = store_fs(path)
    for name, entry in arrays.items():
        stored = _chunk_files(fs, root, name)
        for key, crc in entry["crc32c"].items():
            if key not in stored:
                raise StageError(f"{what} {path} is missing chunk {name}/{key}; {redo}")
            if chunk_crc32c(fs, f"{root}/{name}/{key}") != crc:
                raise StageError(f"{what} {path}: chunk {name}/{key} fails its crc32c checksum (corrupt); {redo}")


def open_zarr(path: Path | str, what: str = "zarr store"):
    """Open a zarr group (local path or fsspec URL) read-only after `verify_zarr`, with a clear message
    when it is missing or corrupt. The group's arrays are only those in the manifest (an array added
    later is refused).
    """
    import zarr

    fs, root = store_fs(path)
    if not fs.exists(root):
        raise not_found(path, what)
    verify_zarr(path, what)
    try:
        group = zarr.open_group(str(path), mode="r")
        listed = _manifest(path, what)
        stored = {name: arr for name, arr in group.arrays()}
    except Exception as e:  # zarr raises several types for a damaged store
        raise StageError(f"{what} {path} is unreadable or corrupt ({type(e).__name__}: {e}); "
                         f"delete it and re-run the stage that writes it") from None
    changed = sorted(set(stored) ^ set(listed)) or [
        n for n, a in stored.items() if [list(a.shape), list(a.chunks)] != [listed[n]["shape"], listed[n]["chunks"]]]
    if changed:
        raise StageError(f"{what} {path}: arrays {changed} differ from its checksum manifest; "
                         f"delete it and re-run the stage that writes it")
    return group


def write_parquet(df: Any, path: Path | str) -> None:
    """DataFrame -> parquet with a CRC checksum on every page, via a temporary file and a rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    try:
        df.to_parquet(tmp, index=False, write_page_checksum=True)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def read_parquet(path: Path | str, what: str = "table"):
    """A parquet table, its page checksums verified (where written); a clear StageError otherwise."""
    import pandas as pd

    path = Path(path)
    if not path.exists():
        raise not_found(path, what)
    try:
        return pd.read_parquet(path, page_checksum_verification=True)
    except Exception as e:
        raise StageError(f"{what} {path} is unreadable ({type(e).__name__}: {e})") from None
