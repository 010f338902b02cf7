"""Render folders as `rpod render`, `rpod eval_render` and a SPEED import write them: meta.json, the
image store (FOLDER/images.zarr, or the folder or fsspec URL that meta.json's `store` names: one zarr
array `images` (N, H, W, 3) uint8 RGB, checksummed) and poses.parquet (one row per image)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from pipeline.io.atomic import read_json
from pipeline.io.errors import DataError
from pipeline.io.store import open_zarr
from pipeline.io.tables import read_parquet

META, IMAGES, POSES = "meta.json", "images.zarr", "poses.parquet"


@dataclass(frozen=True)
class Renders:
    """A render folder: the zarr array of images (N, H, W, 3) uint8 (read lazily), the poses table
    (None when not read) and meta.json (frames, width, height, K, fingerprint, ...)."""

    images: Any
    poses: Any
    meta: dict[str, Any]


def render_identity(meta: dict[str, Any]) -> str:
    """What a label table records of the render it labels (`rpod label`; its readers compare it): meta.json's
    params fingerprint and, for a SPEED import, the first 16 hex digits of the sha256 of what it imported
    (label files, camera.json, images), so a re-import of an edited folder under the same params is another
    render."""
    source = meta.get("source") or {}
    return f"{meta.get('fingerprint')}:{source['sha256'][:16]}" if "sha256" in source else meta.get("fingerprint")


def read_renders(
    folder: Path | str,
    what: str,
    redo: str,
    *,
    poses: str | None = None,
    check: Callable[[dict[str, Any]], None] | None = None,
) -> Renders:
    """Open a render folder and verify it: meta.json, then `check(meta)` (the caller's own test, e.g. a
    params fingerprint), the image store against its checksum manifest (named `what` in messages) and against
    meta.json's render fingerprint (the one the store records), and with `poses` (its name in messages)
    poses.parquet. A DataError ending in `redo` (how to remake the
    folder) when it is incomplete or its counts of images, poses and meta's `frames` differ."""
    folder = Path(folder)
    meta = read_json(folder / META)
    if check is not None:
        check(meta)
    store = meta.get("store") or folder / IMAGES
    group = open_zarr(store, what)
    table = read_parquet(folder / POSES, poses) if poses is not None else None
    if not meta.get("complete") or "images" not in group:
        raise DataError(f"{folder} is incomplete; delete it and {redo}")
    held = group.attrs.get("render_fingerprint", meta.get("fingerprint"))  # older stores do not record it
    if held != meta.get("fingerprint"):
        raise DataError(
            f"{what} {store} holds the images of another render (fingerprint {held}; "
            f"{folder / META} says {meta.get('fingerprint')}); {redo}"
        )
    n = group["images"].shape[0]
    if n != meta["frames"] or (table is not None and n != len(table)):
        counts = f"{n} images" + (f", {len(table)} poses" if table is not None else "")
        raise DataError(f"{folder} is inconsistent ({counts}, meta says {meta['frames']}); delete it and {redo}")
    return Renders(group["images"], table, meta)
