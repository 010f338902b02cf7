"""Chunk-aligned render jobs written straight into one zarr store, fanned out by stages/engine.py.

The driver creates the store (array `images`, uint8 (N, H, W, 3), chunked by frames); each worker
holds one Blender scene, renders whole chunks, writes them into the store itself (a local path or an
fsspec URL every worker can reach) and returns each chunk's crc32c; the driver writes the manifest
last (`stages.io.seal_zarr`). No merge step: the store is complete when the manifest is there.
"""
from __future__ import annotations

import dataclasses
import socket
import time
from pathlib import Path
from typing import Any

import numpy as np

from stages import engine
from stages.io import StageError, chunk_crc32c, create_array, reopen_array, seal_zarr, store_fs


def store_url(path: Path | str) -> str:
    """An absolute location every worker can open: a local path made absolute, a URL as given."""
    return str(path) if "://" in str(path) else str(Path(path).resolve())


def create_store(url: str, n: int, height: int, width: int, chunk: int) -> None:
    """An empty store at `url` (replacing one there) with the array `images` (n, height, width, 3) uint8."""
    import zarr

    try:
        group = zarr.open_group(url, mode="w")
        create_array(group, "images", shape=(n, height, width, 3), chunks=(chunk, height, width, 3), dtype="uint8")
    except Exception as e:  # fsspec and zarr raise many types for a bad URL or a read-only place
        raise StageError(f"image store {url} cannot be written ({type(e).__name__}: {e}); "
                         f"set engine.store to a writable folder or fsspec URL") from None


class RenderWorker:
    """One Blender scene: `run(lo, hi)` renders the poses R[lo:hi], t[lo:hi] (camera frame, metres),
    exactly one chunk, into the store's `images` and returns {chunk key: crc32c}."""

    def __init__(self, K: Any, scene: Any, R: np.ndarray, t: np.ndarray, url: str, empty_hint: str | None) -> None:
        from pipeline.scene import Renderer

        fs, root = store_fs(url)
        if not fs.exists(f"{root}/zarr.json"):
            raise StageError(f"image store {url} is not visible on worker host {socket.gethostname()}; on a "
                             f"cluster of several machines set engine.store to a shared folder or fsspec URL")
        self.images = reopen_array(url, "images")
        self.fs, self.root, self.R, self.t, self.empty_hint = fs, root, R, t, empty_hint
        try:
            self.renderer = Renderer(K, scene)
        except ValueError as e:
            raise StageError(f"params.yaml render: {e}") from None

    def run(self, lo: int, hi: int) -> dict[str, str]:
        engine.exit_once_for_test()
        buf = np.stack([self.renderer.render(self.R[k], self.t[k]) for k in range(lo, hi)])
        if self.empty_hint and lo == 0 and not buf.any():
            raise StageError(f"render: the target covers no pixels in the first {hi} frames (all black); "
                             f"{self.empty_hint}")
        self.images[lo:hi] = buf
        key = f"c/{lo // self.images.chunks[0]}/0/0/0"
        return {key: chunk_crc32c(self.fs, f"{self.root}/images/{key}")}

    def close(self) -> None:
        self.renderer.close()


def render_to_store(url: str, K: Any, scene: Any, R: np.ndarray, t: np.ndarray, chunk: int,
                    es: engine.EngineSettings, desc: str, empty_hint: str | None = None) -> float:
    """Render every pose into a new store at `url` (one job per chunk) and seal it -> seconds taken;
    bad render settings are refused before any worker starts.

    Each Ray worker renders with render.threads / workers Blender threads (at least 1); Cycles gives
    the same pixels for any thread count and chunk order, so the store equals the in-process one."""
    from tqdm import tqdm

    from pipeline.scene import check_settings

    try:
        check_settings(K, scene)
    except ValueError as e:
        raise StageError(f"params.yaml render: {e}") from None
    n = len(t)
    create_store(url, n, K.height, K.width, chunk)
    if scene.mesh:   # workers may run in another folder
        scene = dataclasses.replace(scene, mesh=str(Path(scene.mesh).resolve()))
    threads = scene.threads if es.in_process else max(1, scene.threads // es.workers)
    jobs = [(lo, min(lo + chunk, n)) for lo in range(0, n, chunk)]
    t0 = time.perf_counter()
    with tqdm(total=n, unit="img", desc=desc, dynamic_ncols=True, mininterval=0.5) as bar:
        crcs = engine.run(RenderWorker, (K, dataclasses.replace(scene, threads=threads), R, t, url, empty_hint),
                          jobs, es, num_cpus=threads, progress=lambda i, _: bar.update(jobs[i][1] - jobs[i][0]))
    seal_zarr(url, {"images": {k: v for c in crcs for k, v in c.items()}})
    return time.perf_counter() - t0
