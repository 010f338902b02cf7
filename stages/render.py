"""`rpod render`: render the 13 approach sequences with Blender Cycles into a zarr stack (or import the
SPEED/SPEED+ folder of `render.source`: stages/speed.py). Writes datasets/render/{images.zarr,
poses.parquet, meta.json} in one atomic step, plus PNG previews in reports/figures/previews/. With
`--shard I/N` a process renders only part I of N (a contiguous block of frames) into
datasets/render_shards/N/I; the last part to finish (or `rpod render --merge N`) merges them.
"""
from __future__ import annotations

import fcntl
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np
import typer

from stages import params as params_mod, speed as speed_io
from stages.artifacts import RENDER as OUT, read_render_store
from stages.io import StageError, atomic_dir, create_array, remove_stale_temps, write_json, write_parquet

SHARDS = Path("datasets/render_shards")
PREVIEWS = Path("reports/figures/previews")
SEED_OFFSET = 100
PREVIEW_WIDTH = 480  # previews are upscaled (nearest neighbour) to about this width for viewing


def frames(p: dict[str, Any]):
    """All frames of the 13 sequences as flat arrays: sequence, frame, R (N,3,3), t (N,3)."""
    from pipeline.trajectories import approach_sequences, flatten

    r = p["render"]
    K = params_mod.intrinsics(p)
    half_fov = min(K.fov_deg) / 2
    if r["pointing_jitter_deg"] > 0.8 * half_fov:
        raise StageError(f"params.yaml render.pointing_jitter_deg={r['pointing_jitter_deg']} would push the "
                         f"target out of view; keep it below {0.8 * half_fov:.1f} deg (80% of the half FOV)")
    try:
        seqs = approach_sequences(int(r["frames_per_sequence"]), float(r["start_range"]), float(r["end_range"]),
                                  float(r["pointing_jitter_deg"]), float(r["max_target_rotation_deg"]),
                                  seed=int(p["seed"]) + SEED_OFFSET)
    except ValueError as e:
        raise StageError(f"params.yaml render: {e}") from None
    return flatten(seqs)


def parse_shard(shard: str) -> tuple[int, int]:
    try:
        i, n = (int(v) for v in shard.split("/"))
    except ValueError:
        raise StageError(f"--shard must look like I/N (e.g. 2/4), got {shard!r}") from None
    if not 1 <= i <= n:
        raise StageError(f"--shard {shard}: need 1 <= I <= N")
    return i, n


def render_part(p: dict[str, Any], start: int, stop: int, dest: Path, desc: str) -> None:
    """Render frames [start, stop) into dest/{images.zarr, poses.parquet, meta.json} (dest is a fresh dir)."""
    import zarr

    from pipeline.scene import EmptyRenderError, Renderer, render_into
    from pipeline.trajectories import poses_table

    r = p["render"]
    K = params_mod.intrinsics(p)
    seq, frm, R, t = frames(p)
    chunk = int(r["chunk"])
    n = stop - start
    store = zarr.open_group(str(dest / "images.zarr"), mode="w")
    images = create_array(store, "images", shape=(n, K.height, K.width, 3), chunks=(chunk, K.height, K.width, 3),
                          dtype="uint8")
    try:
        renderer = Renderer(K, params_mod.scene_settings(r))
    except ValueError as e:
        raise StageError(f"params.yaml render: {e}") from None
    t0 = time.perf_counter()
    try:
        render_into(renderer, R[start:stop], t[start:stop], images, chunk, desc, require_target=True)
    except EmptyRenderError as e:
        raise StageError(f"render: {e}; check render.mesh and render.mesh_scale (metres per mesh unit)") from None
    finally:
        renderer.close()
    seconds = time.perf_counter() - t0
    sl = slice(start, stop)
    write_parquet(poses_table(np.arange(start, stop), seq[sl], frm[sl], R[sl], t[sl]), dest / "poses.parquet")
    write_json(dest / "meta.json", {
        "complete": True, "fingerprint": params_mod.render_fingerprint(p), "frames": n, "start": start,
        "stop": stop, "width": K.width, "height": K.height, "K": K.K, "render": r, "camera": p["camera"],
        "seed": p["seed"], "seconds": seconds, "seconds_per_image": seconds / max(n, 1), "chunk": chunk,
    })


def remove_leftovers(path: Path) -> None:
    """Delete temporary folders that an interrupted (killed) run left next to `path` (never renamed into
    place, so never trusted, but holding disk space); a live concurrent run's folder is kept."""
    for d in remove_stale_temps(path):
        typer.echo(f"removed {d}, left over from an interrupted run")


def write_previews(images, poses, n_previews: int) -> list[Path]:
    """PNG previews: the first (60 m) and last (10 m) frame of sequence 0, then frames spread over the
    rotating sequences; upscaled by an integer factor (nearest neighbour) for viewing."""
    import cv2

    from pipeline.trajectories import preview_picks

    shutil.rmtree(PREVIEWS, ignore_errors=True)
    PREVIEWS.mkdir(parents=True, exist_ok=True)
    out = []
    for k, idx in enumerate(preview_picks(poses["sequence"].to_numpy(), poses["index"].to_numpy(), n_previews)):
        img = np.asarray(images[idx])
        row = poses.iloc[idx]
        scale = max(1, round(PREVIEW_WIDTH / img.shape[1]))
        big = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
        path = PREVIEWS / f"{k:02d}_seq{int(row.sequence):02d}_frame{int(row.frame):04d}_{row.tz:.0f}m.png"
        if not cv2.imwrite(str(path), big[..., ::-1]):
            raise StageError(f"could not write {path}")
        out.append(path)
    return out


def merge(p: dict[str, Any], n: int) -> None:
    """Merge the N shard parts of this params fingerprint into datasets/render (atomically)."""
    import pandas as pd
    import zarr

    parts = [SHARDS / str(n) / str(i) for i in range(1, n + 1)]
    missing = [str(d) for d in parts if not (d / "meta.json").exists()]
    if missing:
        raise StageError(f"cannot merge: shard parts missing: {', '.join(missing)}")
    checked = [read_render_store(d, "render shard") for d in parts]
    fp = params_mod.render_fingerprint(p)
    stale = [str(d) for d, (_, _, m) in zip(parts, checked) if m["fingerprint"] != fp]
    if stale:
        raise StageError(f"shard parts {', '.join(stale)} were rendered with other params; re-render them")
    n_total = len(frames(p)[0])
    if sum(m["frames"] for _, _, m in checked) != n_total:
        raise StageError(f"shard parts hold {sum(m['frames'] for _, _, m in checked)} frames, expected {n_total}")
    first = checked[0][2]
    chunk = int(p["render"]["chunk"])
    with atomic_dir(OUT) as tmp:
        store = zarr.open_group(str(tmp / "images.zarr"), mode="w")
        dst = create_array(store, "images", shape=(n_total, first["height"], first["width"], 3),
                       chunks=(chunk, first["height"], first["width"], 3), dtype="uint8")
        for images, _, m in checked:
            for lo in range(0, m["frames"], chunk):  # one chunk at a time: memory stays small
                hi = min(lo + chunk, m["frames"])
                dst[m["start"] + lo:m["start"] + hi] = images[lo:hi]
        write_parquet(pd.concat([ps for _, ps, _ in checked], ignore_index=True), tmp / "poses.parquet")
        seconds = sum(m["seconds"] for _, _, m in checked)
        meta = {k: v for k, v in first.items() if k not in ("start", "stop")}
        meta.update(frames=n_total, seconds=seconds, seconds_per_image=seconds / n_total, shards=n)
        write_json(tmp / "meta.json", meta)
    shutil.rmtree(SHARDS / str(n), ignore_errors=True)


def main(
    shard: str = typer.Option("1/1", help="Render only part I of N (e.g. 2/4): contiguous, chunk-aligned blocks "
                                          "of frames, for parallel processes or machines. When all N parts "
                                          "exist they are merged into datasets/render."),
    merge_parts: int = typer.Option(0, "--merge", metavar="N",
                                    help="Only merge the N finished parts in datasets/render_shards/N/ (no rendering)."),
) -> None:
    """Render the 13 approach sequences with Blender Cycles (CPU, headless), or import the SPEED/SPEED+
    folder of `render.source`. Writes datasets/render/ (images.zarr, poses.parquet, meta.json) atomically
    and PNG previews to reports/figures/previews/. Parameters: `seed`, `camera` and `render` in params.yaml.
    """
    p = params_mod.load()
    if params_mod.given(p["render"]["source"]):   # a SPEED/SPEED+ folder instead of rendering
        speed_io.import_source(p, OUT)
    elif merge_parts:
        merge(p, merge_parts)
    else:
        n_frames = len(frames(p)[0])
        i, n = parse_shard(shard)
        if n == 1:
            remove_leftovers(OUT)
            with atomic_dir(OUT) as tmp:
                render_part(p, 0, n_frames, tmp, "render")
        else:
            from pipeline.scene import shard_range

            start, stop = shard_range(n_frames, int(p["render"]["chunk"]), i, n)
            remove_leftovers(SHARDS / str(n) / str(i))
            with atomic_dir(SHARDS / str(n) / str(i)) as tmp:
                render_part(p, start, stop, tmp, f"render {i}/{n}")
            with open(SHARDS / f".merge-{n}.lock", "w") as lock:  # parts finishing together merge once
                fcntl.flock(lock, fcntl.LOCK_EX)
                done = [j for j in range(1, n + 1) if (SHARDS / str(n) / str(j) / "meta.json").exists()]
                if len(done) < n:
                    typer.echo(f"part {i}/{n} done ({stop - start} frames); {len(done)}/{n} parts present. "
                               f"The last part to finish merges them (or run `rpod render --merge {n}`).")
                    return
                merge(p, n)
    images, poses, meta = read_render_store(OUT)
    previews = write_previews(images, poses, int(p["render"]["previews"]))
    typer.echo(f"{OUT}: {meta['frames']} images {meta['width']}x{meta['height']}, "
               f"{meta['seconds_per_image']:.3f} s/image; previews: {', '.join(str(x) for x in previews)}")
