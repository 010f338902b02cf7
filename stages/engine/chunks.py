"""Chunk-aligned render jobs written straight into one zarr store, fanned out by stages/engine/pool.py.

The driver creates the store (array `images`, uint8 (N, H, W, 3), chunked by frames); each worker
holds one Blender scene, renders whole chunks, writes them into the store itself (a local path or an
fsspec URL) and returns each chunk's crc32c (a worker on a machine that cannot see the store returns
the pixels and the driver writes them); the driver writes the manifest last (`pipeline.io.store.seal_zarr`).
No merge step: the store is complete when the manifest is there. A `RenderWorker` gets a `RenderSetup`
and one `FrameRange` per job; a `PoseRenderWorker` (poses rendered and sent back, `render_poses`) gets a
`PoseSetup` and one `PoseBatch` per job.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import secrets
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from pipeline.io.store import chunk_crc32c, create_array, reopen_array, seal_zarr, store_fs
from pipeline.visibility import empty_problem, out_of_view
from stages.engine import pool as engine
from stages.errors import StageError


def store_url(path: Path | str) -> str:
    """An absolute location every worker can open: a local path made absolute, a URL as given."""
    return str(path) if "://" in str(path) else str(Path(path).resolve())


def keyed_store(store: str, fingerprint: str) -> str:
    """Where a render with this params `fingerprint` keeps its images in the shared folder or fsspec URL
    `store` (`engine.store`): one store per fingerprint, so runs of other params never write over it."""
    return f"{store_url(store).rstrip('/')}/render-{fingerprint}.zarr"


@contextlib.contextmanager
def replacing(url: str) -> Iterator[str]:
    """Yield a temporary sibling URL to write a store into; once the block ends it replaces `url` whole (the
    previous store stays until then, and stays as it was when the block fails: the temporary is removed).
    A local store is locked for the block (one writer at a time, one message for the others), and the
    temporaries of killed writers beside it are removed first. The temporary store lies inside a folder that
    holds its token (`pipeline.io.atomic.owned_temp`), as the store being replaced does while they are
    swapped: nothing else beside the store is ever deleted."""
    from pipeline.io.atomic import OLD, OWNER, exclusive, remove_stale_temps

    with contextlib.ExitStack() as stack:
        try:
            fs, root = store_fs(url)
            if "file" in (fs.protocol if isinstance(fs.protocol, tuple) else (fs.protocol,)):
                stack.enter_context(exclusive(f"{root}.lock", f"image store {url}"))
                remove_stale_temps(root)
        except (OSError, ValueError, ImportError) as e:  # a path below a file, an unknown protocol, ...
            raise unwritable(url, e) from None
        parent, name = url.rstrip("/").rsplit("/", 1)
        owner = f".{name}.{os.getpid()}.{secrets.token_hex(4)}.tmp"  # holds its token, as atomic.owned_temp's
        held = store_fs(f"{parent}/{owner}")[1]
        fs.makedirs(held)
        fs.pipe_file(f"{held}/{OWNER}", owner.encode())
        try:
            yield f"{parent}/{owner}/{name}"
            if fs.exists(root):
                fs.mv(root, f"{held}/{OLD}", recursive=True)
            try:
                fs.mv(f"{held}/{name}", root, recursive=True)
            except BaseException:
                if fs.exists(f"{held}/{OLD}"):
                    fs.mv(f"{held}/{OLD}", root, recursive=True)
                raise
        finally:
            fs.rm(held, recursive=True)


def create_store(url: str, n: int, height: int, width: int, chunk: int, fingerprint: str | None = None) -> None:
    """An empty store at `url` (replacing one there) with the array `images` (n, height, width, 3) uint8; with a
    `fingerprint`, its root attribute `render_fingerprint` names the render params it holds
    (pipeline.formats.renders checks it against meta.json's)."""
    import zarr

    try:
        group = zarr.open_group(url, mode="w")
        if fingerprint is not None:
            group.attrs["render_fingerprint"] = fingerprint
        create_array(group, "images", shape=(n, height, width, 3), chunks=(chunk, height, width, 3), dtype="uint8")
    except Exception as e:  # fsspec and zarr raise many types for a bad URL or a read-only place
        raise unwritable(url, e) from None


def unwritable(url: str, e: Exception) -> StageError:
    """The one-line refusal of an image store that cannot be written."""
    return StageError(
        f"image store {url} cannot be written ({type(e).__name__}: {e}); set engine.store to a "
        f"writable folder or fsspec URL"
    )


@dataclass(frozen=True)
class RenderSetup:
    """What one RenderWorker holds: the camera, the scene and every pose of the store."""

    K: Any  # pipeline.geometry.camera.Intrinsics (pixels)
    scene: Any  # pipeline.render.scene.SceneSettings, checked by `prepare`
    R: np.ndarray  # (N, 3, 3) target attitudes, target frame -> camera frame
    t: np.ndarray  # (N, 3) target positions in the camera frame, metres
    url: str  # the store (`store_url`: an absolute path or an fsspec URL)
    empty_hint: str | None  # how to fix a first chunk the target covers no pixel of (refused); None: not checked
    backgrounds: tuple[Any, ...] | None = None  # per frame a backgrounds.FrameBackground or None (black)


@dataclass(frozen=True)
class FrameRange:
    """One render job: the frames lo .. hi - 1 of the store, exactly one chunk."""

    lo: int  # first frame (a multiple of the store's chunk length)
    hi: int  # one past the last frame


class RenderWorker:
    """One Blender scene: `run(FrameRange)` renders the poses R[lo:hi], t[lo:hi] of its setup (camera
    frame, metres), exactly one chunk, into the store's `images` and returns {chunk key: crc32c}; a
    worker that cannot see the store (another machine without shared storage) returns the pixels for
    the driver to write."""

    def __init__(self, setup: RenderSetup) -> None:
        from pipeline.render.scene import Renderer

        self.fs, self.root = store_fs(setup.url)
        self.images = reopen_array(setup.url, "images") if visible(self.fs, self.root) else None
        self.R, self.t, self.empty_hint = setup.R, setup.t, setup.empty_hint
        self.backgrounds = setup.backgrounds or (None,) * len(setup.t)
        self.renderer = Renderer(setup.K, setup.scene)  # settings checked by the driver (`prepare`)

    def run(self, job: FrameRange) -> dict[str, str] | np.ndarray:
        lo, hi = job.lo, job.hi
        out = [self.renderer.render_with_alpha(self.R[k], self.t[k], self.backgrounds[k]) for k in range(lo, hi)]
        buf = np.stack([rgb for rgb, _ in out])
        if self.empty_hint and lo == 0 and not any(alpha.any() for _, alpha in out):
            raise StageError(f"render: the target covers no pixels in the first {hi} frames; {self.empty_hint}")
        if self.images is None:
            return buf
        return write_chunk(self.images, self.fs, self.root, lo, buf)

    def close(self) -> None:
        self.renderer.close()


def visible(fs: Any, root: str) -> bool:
    """Whether this process sees the store the driver created (its zarr.json)."""
    return fs.exists(f"{root}/zarr.json")


def write_chunk(images: Any, fs: Any, root: str, lo: int, buf: np.ndarray) -> dict[str, str]:
    """Write one whole chunk (frames lo .. lo + len(buf)) into the array `images` -> {its key: crc32c}."""
    images[lo : lo + len(buf)] = buf
    key = f"c/{lo // images.chunks[0]}/0/0/0"
    return {key: chunk_crc32c(fs, f"{root}/images/{key}")}


@dataclass(frozen=True)
class PoseSetup:
    """What one PoseRenderWorker holds: the camera and the scene."""

    K: Any  # pipeline.geometry.camera.Intrinsics (pixels)
    scene: Any  # pipeline.render.scene.SceneSettings, checked by `prepare`


@dataclass(frozen=True)
class PoseBatch:
    """One pose render job: n poses sent to the worker, rendered and sent back."""

    R: np.ndarray  # (n, 3, 3) target attitudes, target frame -> camera frame
    t: np.ndarray  # (n, 3) target positions in the camera frame, metres


class PoseRenderWorker:
    """One Blender scene: `run(PoseBatch)` renders its poses and returns them to the driver
    -> (RGB (n, H, W, 3) uint8 on black, alpha (n, H, W) float32 in [0, 1])."""

    def __init__(self, setup: PoseSetup) -> None:
        from pipeline.render.scene import Renderer

        self.renderer = Renderer(setup.K, setup.scene)

    def run(self, job: PoseBatch) -> tuple[np.ndarray, np.ndarray]:
        out = [self.renderer.render_with_alpha(Ri, ti) for Ri, ti in zip(job.R, job.t)]
        return np.stack([rgb for rgb, _ in out]), np.stack([alpha for _, alpha in out])

    def close(self) -> None:
        self.renderer.close()


def check(K: Any, scene: Any) -> None:
    """StageError naming the first bad render setting (camera size, scene, background)."""
    from pipeline.render.scene import check_settings

    try:
        check_settings(K, scene)
    except ValueError as e:
        raise StageError(f"params.yaml render: {e}") from None


def device_record(scene: Any) -> dict[str, Any]:
    """Where Blender on this machine renders `scene` (render.device resolved by pipeline.render.scene.resolve_device:
    requested, used, GPU backend, a note when auto fell back to the CPU), for a render's metadata; a `gpu` that bpy
    cannot see is a StageError. Each worker resolves it again on its own machine."""
    from pipeline.render.scene import resolve_device

    try:
        return resolve_device(scene.device).record(scene.device)
    except ValueError as e:
        raise StageError(f"params.yaml render.device: {e}") from None


def prepare(K: Any, scene: Any, es: engine.EngineSettings) -> tuple[Any, int]:
    """(scene settings for one worker, its Blender threads): settings checked before any worker starts
    (StageError), the mesh path made absolute (workers may run elsewhere), and render.threads / workers
    threads (at least 1) per Ray worker. Cycles gives the same pixels for any thread count and chunk
    order, so the images equal the in-process ones."""
    check(K, scene)
    threads = es.threads(scene.threads)
    mesh = str(Path(scene.mesh).resolve()) if scene.mesh else None
    return dataclasses.replace(scene, threads=threads, mesh=mesh), threads


def render_poses(
    K: Any, scene: Any, R: np.ndarray, t: np.ndarray, chunk: int, es: engine.EngineSettings, desc: str
) -> tuple[np.ndarray, np.ndarray]:
    """Every pose rendered by the engine's workers, `chunk` poses per job -> (RGB, alpha) in pose order."""
    from tqdm import tqdm

    scene, threads = prepare(K, scene, es)
    jobs = [PoseBatch(R[lo : lo + chunk], t[lo : lo + chunk]) for lo in range(0, len(t), chunk)]
    with tqdm(total=len(t), unit="img", desc=desc, dynamic_ncols=True, mininterval=0.5) as bar:
        out = engine.run(
            PoseRenderWorker,
            PoseSetup(K, scene),
            jobs,
            es,
            num_cpus=threads,
            progress=lambda i, _: bar.update(len(jobs[i].t)),
        )
    return np.concatenate([rgb for rgb, _ in out]), np.concatenate([alpha for _, alpha in out])


def render_to_store(
    url: str,
    K: Any,
    scene: Any,
    R: np.ndarray,
    t: np.ndarray,
    chunk: int,
    es: engine.EngineSettings,
    desc: str,
    empty_hint: str | None = None,
    fingerprint: str | None = None,
    backgrounds: list[Any] | None = None,
) -> float:
    """Render every pose into a new store at `url` (one job per chunk; `fingerprint`: of the render params,
    recorded in it; `backgrounds`: per frame its background draw or None, `frame_backgrounds`) and seal it ->
    seconds taken; bad render settings are refused before any worker starts (`prepare`). With `empty_hint` (how to
    fix it, naming the params), a first chunk without a lit pixel stops the render at once and a store with more
    than MAX_EMPTY_SHARE of its frames out of view (the lit-pixel rule, pipeline/visibility.py) is refused once
    rendered (a StageError ending in the hint)."""
    from tqdm import tqdm

    scene, threads = prepare(K, scene, es)
    n = len(t)
    chunk = max(1, min(chunk, n))  # a chunk longer than the store would allocate for frames that do not exist
    create_store(url, n, K.height, K.width, chunk, fingerprint)
    jobs = [FrameRange(lo, min(lo + chunk, n)) for lo in range(0, n, chunk)]
    crcs: dict[str, str] = {}
    fs, root = store_fs(url)
    images = reopen_array(url, "images")

    def done(i: int, result: dict[str, str] | np.ndarray) -> None:
        """Record a chunk's checksum; write the chunks a worker could not (it returned the pixels)."""
        crcs.update(write_chunk(images, fs, root, jobs[i].lo, result) if isinstance(result, np.ndarray) else result)
        bar.update(jobs[i].hi - jobs[i].lo)

    t0 = time.perf_counter()
    with tqdm(total=n, unit="img", desc=desc, dynamic_ncols=True, mininterval=0.5) as bar:
        engine.run(
            RenderWorker,
            RenderSetup(K, scene, R, t, url, empty_hint, backgrounds and tuple(backgrounds)),
            jobs,
            es,
            num_cpus=threads,
            progress=done,
        )
    seal_zarr(url, {"images": crcs})
    if empty_hint:
        problem = empty_problem(out_of_view(images), f"frames of {desc}")
        if problem:
            raise StageError(f"{problem}; {empty_hint}")
    return time.perf_counter() - t0


def frame_backgrounds(
    K: Any, scene: Any, R: np.ndarray, R_cam: np.ndarray, seed: int
) -> tuple[list[Any] | None, list[str] | None]:
    """The background draws of a render set's frames (R (N, 3, 3): target -> camera; R_cam (N, 3, 3): camera ->
    world; seed: the set's), each keyed by its index in the set, and their `background` column values -> (draws,
    kinds); (None, None) while scene.background is off (share 0: every frame black, no column)."""
    from pipeline.render.backgrounds import draw, kind

    check(K, scene)
    bg = scene.background
    if bg.share == 0:
        return None, None
    draws = [draw(bg, Rc, seed, k) for k, Rc in enumerate(R_cam)]
    sun = np.asarray(scene.sun_direction, dtype=np.float64)
    return draws, [kind(K, bg, d, Rk @ sun) for d, Rk in zip(draws, R)]
