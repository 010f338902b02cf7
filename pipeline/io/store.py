"""The checksummed zarr store: every chunk compressed with zstd and followed by its crc32c, and a
manifest (written last, in the root group's attributes) listing per array its shape, chunks, the crc32c
of its metadata document (its zarr.json: dtype, codecs, fill value) and of every chunk object, and the
crc32c of the root group's other attributes; `open_zarr` refuses a store that does not match it. Stores
are local paths or fsspec URLs."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from pipeline.io.errors import DataError, not_found

MANIFEST = "rpodguard_manifest"  # key in the root group's attributes (zarr.json)
MANIFEST_FORMAT = "rpodguard-zarr-manifest/3"  # /1 summed the codec's own crc32c too; /2 left zarr.json out


def create_array(group: Any, name: str, **kwargs: Any) -> Any:
    """`group.create_array` with the project's codecs: zstd, then a crc32c checksum of every chunk,
    and every chunk written (also all-zero ones) so a missing chunk file is always an error."""
    from zarr.codecs import Crc32cCodec, ZstdCodec

    return group.create_array(
        name, compressors=[ZstdCodec(level=0), Crc32cCodec()], config={"write_empty_chunks": True}, **kwargs
    )


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


def cat(fs: Any, path: str) -> bytes:
    """The bytes of one stored object: `fs.cat_file`, or for a local store `pipeline.io.files.read_bytes`, which
    refuses a FIFO or other special file (with one DataError naming it) instead of blocking on it."""
    from pipeline.io.files import read_bytes

    protocols = fs.protocol if isinstance(fs.protocol, tuple) else (fs.protocol,)
    if "file" in protocols or "local" in protocols:
        try:
            return read_bytes(path)
        except DataError as e:
            if not Path(path).exists():
                raise FileNotFoundError(path) from None  # what the callers (as fs.cat_file) expect
            raise DataError(f"zarr store object {e}; delete the store and re-run the stage that writes it") from None
    return fs.cat_file(path)


def chunk_crc32c(fs: Any, path: str) -> str:
    """crc32c (8 hex digits) of one stored chunk object's payload, as the manifest lists it: the bytes
    before the 4-byte crc32c the codec appends (the crc32c of data followed by its own crc32c is the
    same constant for every chunk, so it could not tell one chunk from another).
    A chunk whose own trailer does not match its payload gives "damaged", which no manifest lists.
    """
    import google_crc32c

    data = cat(fs, path)
    crc = google_crc32c.value(data[:-4])
    return f"{crc:08x}" if data[-4:] == crc.to_bytes(4, "little") else "damaged"


def _json_crc32c(fs: Any, root: str, name: str | None) -> str:
    """crc32c (8 hex digits) of what the manifest pins of a zarr.json: an array's whole document (`name`), or
    the root group's attributes other than the manifest itself (`name` None), as canonical JSON."""
    import google_crc32c

    raw = cat(fs, f"{root}/{name}/zarr.json" if name else f"{root}/zarr.json")
    if name is None:
        attrs = json.loads(raw).get("attributes", {})
        raw = json.dumps({k: v for k, v in attrs.items() if k != MANIFEST}, sort_keys=True).encode()
    return f"{google_crc32c.value(raw):08x}"


def _chunk_files(fs: Any, root: str, name: str) -> set[str]:
    """Keys (c/i/j/...) of the chunk objects stored under array `name`."""
    base = f"{root.rstrip('/')}/{name}/"
    return {f[len(base) :] for f in fs.find(base) if f.startswith(base) and f[len(base) :].startswith("c/")}


def seal_zarr(path: Path | str, crc32c: dict[str, dict[str, str]] | None = None) -> None:
    """Write the store's manifest last, into the root group's attributes: per array its shape, chunks and
    the crc32c of its zarr.json and of every chunk object, and the crc32c of the root's other attributes.
    `crc32c` ({array: {chunk key: crc}}, from the workers that wrote the chunks) is used where given; other
    arrays are read back and checksummed here.

    Refuses (RuntimeError: a bug in the writer) an array without the crc32c codec or with a chunk of
    its grid never written (or not checksummed).
    """
    import zarr

    fs, root = store_fs(path)
    group = zarr.open_group(str(path), mode="r")
    arrays: dict[str, Any] = {}
    for name, arr in sorted(group.arrays()):
        if not any(type(c).__name__ == "Crc32cCodec" for c in arr.compressors):
            raise RuntimeError(
                f"{path}/{name} was written without the crc32c codec (use pipeline.io.store.create_array)"
            )
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
        arrays[name] = {
            "shape": list(arr.shape),
            "chunks": list(arr.chunks),
            "zarr_json": _json_crc32c(fs, root, name),
            "crc32c": crcs,
        }
    zarr.open_group(str(path), mode="r+").attrs[MANIFEST] = {
        "format": MANIFEST_FORMAT,
        "arrays": arrays,
        "attributes": _json_crc32c(fs, root, None),
    }


def is_sealed(path: Path | str) -> bool:
    """Whether the store at `path` already carries its manifest."""
    fs, root = store_fs(path)
    try:
        return MANIFEST in json.loads(cat(fs, f"{root}/zarr.json")).get("attributes", {})
    except (FileNotFoundError, ValueError, AttributeError):
        return False


def _manifest(path: Path | str, what: str) -> dict[str, Any]:
    """The manifest from the root zarr.json (format, arrays, attributes), or a DataError."""
    redo = "delete it and re-run the stage that writes it"
    fs, root = store_fs(path)
    try:
        meta = json.loads(cat(fs, f"{root}/zarr.json"))
    except FileNotFoundError:
        raise DataError(f"{what} {path} is not a zarr store (no zarr.json); {redo}") from None
    except (json.JSONDecodeError, UnicodeDecodeError):
        raise DataError(f"{what} {path}/zarr.json is damaged; {redo}") from None
    manifest = meta.get("attributes", {}).get(MANIFEST) if isinstance(meta, dict) else None
    if manifest is None:
        raise DataError(f"{what} {path} has no checksum manifest (an interrupted write or an older rpodguard); {redo}")
    fmt = manifest.get("format") if isinstance(manifest, dict) else None
    if isinstance(fmt, str) and fmt.startswith("rpodguard-zarr-manifest/") and fmt != MANIFEST_FORMAT:
        raise DataError(f"{what} {path} was written by an older rpodguard (checksum manifest {fmt}); {redo}")
    arrays = manifest.get("arrays") if fmt == MANIFEST_FORMAT else None
    if not isinstance(arrays, dict):
        raise DataError(f"{what} {path}: the checksum manifest is damaged; {redo}")
    return manifest


def verify_zarr(path: Path | str, what: str = "zarr store") -> None:
    """Check a store (local path or fsspec URL) against its manifest: every array and chunk object
    present, every crc32c equal (chunks, each array's zarr.json, the root's attributes). One DataError naming
    the store and the first bad file; costs one read of the compressed bytes.
    """
    redo = "delete it and re-run the stage that writes it"
    manifest = _manifest(path, what)
    fs, root = store_fs(path)
    if _json_crc32c(fs, root, None) != manifest.get("attributes"):
        raise DataError(f"{what} {path}: the root group's attributes (zarr.json) changed since it was sealed; {redo}")
    for name, entry in manifest["arrays"].items():
        try:
            changed = _json_crc32c(fs, root, name) != entry.get("zarr_json")
        except FileNotFoundError:
            raise DataError(f"{what} {path} is missing {name}/zarr.json; {redo}") from None
        if changed:
            raise DataError(
                f"{what} {path}: {name}/zarr.json (dtype, codecs, shape) changed since it was sealed; {redo}"
            )
        stored = _chunk_files(fs, root, name)
        for key, crc in entry["crc32c"].items():
            if key not in stored:
                raise DataError(f"{what} {path} is missing chunk {name}/{key}; {redo}")
            if chunk_crc32c(fs, f"{root}/{name}/{key}") != crc:
                raise DataError(f"{what} {path}: chunk {name}/{key} fails its crc32c checksum (corrupt); {redo}")


def open_zarr(path: Path | str, what: str = "zarr store") -> Any:
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
        listed = _manifest(path, what)["arrays"]
        stored = {name: arr for name, arr in group.arrays()}
    except Exception as e:  # zarr raises several types for a damaged store
        raise DataError(
            f"{what} {path} is unreadable or corrupt ({type(e).__name__}: {e}); "
            f"delete it and re-run the stage that writes it"
        ) from None
    changed = sorted(set(stored) ^ set(listed)) or [
        n for n, a in stored.items() if [list(a.shape), list(a.chunks)] != [listed[n]["shape"], listed[n]["chunks"]]
    ]
    if changed:
        raise DataError(
            f"{what} {path}: arrays {changed} differ from its checksum manifest; "
            f"delete it and re-run the stage that writes it"
        )
    return group


IO_THREAD_JOIN_S = 30.0  # seconds `release_zarr` waits for zarr's I/O thread to stop


def release_zarr() -> None:
    """Stop zarr's I/O event loop and its thread, waiting for the thread, before the interpreter exits. zarr's own
    exit hook (zarr.core.sync.cleanup_resources) waits 0.2 s for the thread and then closes the loop anyway: on a busy
    machine the thread is still running it and the hook prints a traceback ("RuntimeError: Cannot close a running
    event loop") after a command that succeeded. With the loop gone the hook has nothing left to do. Nothing when
    zarr was never imported."""
    import sys

    sync = sys.modules.get("zarr.core.sync")
    if sync is None:
        return
    if sync._executor is not None:  # zarr's module state (zarr 3.1: loop, iothread, _executor)
        sync._executor.shutdown(wait=True, cancel_futures=True)
        sync._executor = None
    loop, thread = sync.loop[0], sync.iothread[0]
    if loop is None:
        return
    loop.call_soon_threadsafe(loop.stop)
    if thread is not None:
        thread.join(IO_THREAD_JOIN_S)
        if thread.is_alive():
            return  # still busy: leave it to zarr's hook
    loop.close()
    sync.loop[0], sync.iothread[0] = None, None
