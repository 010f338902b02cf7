"""`rpod render`: render the 13 approach sequences with Blender Cycles into a zarr stack (or import the
SPEED/SPEED+ folder of `render.source`: stages/artifacts/speed.py, pipeline/formats/speed_folder.py).

Writes datasets/render/{images.zarr, poses.parquet, meta.json} in one atomic step, plus PNG
previews in reports/figures/previews/ and the render time in reports/metrics/render.json (never in
meta.json: the same params give a byte-identical folder, so its DVC hash is stable). The frames' chunks fan out
over `engine.workers` workers (Ray
actors, each with one Blender scene; a Ray cluster via `engine.address` or $RAY_ADDRESS) that write
straight into one store: datasets/render/images.zarr, or in the shared folder or fsspec URL `engine.store`
the store of this render's params fingerprint, render-<fingerprint>.zarr (written beside it and swapped in
when complete, so a failed or refused render leaves the previous one; a local one is locked while written).
Two renders into one checkout are refused too: datasets/.render.lock.
"""

from __future__ import annotations

import contextlib
import dataclasses
from pathlib import Path
from typing import Any

import numpy as np
import typer

from pipeline.io.atomic import atomic_dir, atomic_outputs, exclusive, remove_stale_temps, write_json
from pipeline.io.tables import write_parquet
from pipeline.seeds import seed_for
from stages.artifacts import speed as speed_io
from stages.artifacts.dvc import write_metrics
from stages.artifacts.paths import PREVIEWS
from stages.artifacts.paths import RENDER as OUT
from stages.artifacts.paths import RENDER_METRICS as METRICS
from stages.artifacts.readers import read_render_store
from stages.config import params as params_mod
from stages.config.build import intrinsics, scene_settings
from stages.config.schema import Params
from stages.engine.chunks import device_record, frame_backgrounds, keyed_store, render_to_store, replacing, store_url
from stages.engine.pool import engine_settings
from stages.errors import StageError

PREVIEW_WIDTH = 480  # previews are upscaled (nearest neighbour) to about this width for viewing


def frames(p: Params) -> tuple[Any, Any, Any, Any]:
    """All frames of the 13 sequences as flat arrays: sequence, frame, R (N,3,3), t (N,3)."""
    from pipeline.geometry.trajectories import flatten

    return flatten(sequences(p))


def sequences(p: Params) -> list[Any]:
    """The 13 approach sequences (pipeline.geometry.trajectories.Sequence) of the render params."""
    from pipeline.geometry.trajectories import approach_sequences

    r = p.render
    K = intrinsics(p)
    half_fov = min(K.fov_deg) / 2
    if r.pointing_jitter_deg > 0.8 * half_fov:
        raise StageError(
            f"params.yaml render.pointing_jitter_deg={r.pointing_jitter_deg} would push the "
            f"target out of view; keep it below {0.8 * half_fov:.1f} deg (80% of the half FOV)"
        )
    try:
        seqs = approach_sequences(
            r.frames_per_sequence,
            float(r.start_range),
            float(r.end_range),
            float(r.pointing_jitter_deg),
            float(r.max_target_rotation_deg),
            seed=seed_for(p.seed, "render"),
            attitude=r.target_attitude,
        )
    except ValueError as e:
        raise StageError(f"params.yaml render: {e}") from None
    return seqs


def render_all(p: Params, dest: Path) -> tuple[float, dict[str, Any]]:
    """Render every frame into dest/{poses.parquet, meta.json} and the image store (dest/images.zarr, or
    `engine.store`'s store for this fingerprint, which meta.json then names); `dest` is a fresh folder.
    Returns the render time (s) and the Cycles device used (`device_record`): timings go to
    reports/metrics/render.json, never into meta.json, so the folder's hash is stable; meta.json records the device
    when render.device is not cpu (the CPU path's meta.json is as it was)."""
    from pipeline.geometry.trajectories import flatten, poses_table

    r, es, store = p.render, engine_settings(p), p.engine.store
    K, scene = intrinsics(p), scene_settings(r)
    device = device_record(scene)
    seqs = sequences(p)
    seq, frm, R, t = flatten(seqs)
    draws, kinds = frame_backgrounds(
        K, scene, R, np.concatenate([s.R_cam for s in seqs]), seed_for(p.seed, "background")
    )
    fp = params_mod.render_fingerprint(p)
    url = keyed_store(store, fp) if store else store_url(dest / "images.zarr")
    with replacing(url) if store else contextlib.nullcontext(url) as target:
        seconds = render_to_store(
            target,
            K,
            scene,
            R,
            t,
            r.chunk,
            es,
            "render",
            fingerprint=fp,
            empty_hint="check render.mesh and render.mesh_scale (metres per mesh unit)",
            backgrounds=draws,
        )
    n = len(t)
    poses = poses_table(np.arange(n), seq, frm, R, t)
    if kinds is not None:
        poses["background"] = kinds
    write_parquet(poses, dest / "poses.parquet")
    write_json(
        dest / "meta.json",
        {
            "complete": True,
            "fingerprint": fp,
            "frames": n,
            "width": K.width,
            "height": K.height,
            "K": K.K,
            "render": params_mod.render_record(r),
            "camera": dataclasses.asdict(p.camera),
            "seed": p.seed,
            "chunk": min(r.chunk, n),
            **({"store": url} if store else {}),
            **({"cycles_device": device} if r.device != "cpu" else {}),
        },
    )
    return seconds, device


def remove_leftovers(path: Path) -> None:
    """Delete temporary folders that an interrupted (killed) run left next to `path` (never renamed into
    place, so never trusted, but holding disk space); a live concurrent run's folder is kept."""
    for d in remove_stale_temps(path):
        typer.echo(f"removed {d}, left over from an interrupted run")


def write_previews(images, poses, n_previews: int) -> list[Path]:
    """PNG previews: the first (60 m) and last (10 m) frame of sequence 0, then frames spread over the
    rotating sequences; upscaled by an integer factor (nearest neighbour) for viewing. Written into a temporary
    folder that replaces the previews folder whole once every image is in (an interrupted run leaves the old one)."""
    import cv2

    from pipeline.geometry.trajectories import preview_picks

    out = []
    with atomic_outputs(dirs=(PREVIEWS,)) as (tmp,):
        for k, idx in enumerate(preview_picks(poses["sequence"].to_numpy(), poses["index"].to_numpy(), n_previews)):
            img = np.asarray(images[idx])
            row = poses.iloc[idx]
            scale = max(1, round(PREVIEW_WIDTH / img.shape[1]))
            big = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
            name = f"{k:02d}_seq{int(row.sequence):02d}_frame{int(row.frame):04d}_{row.tz:.0f}m.png"
            if not cv2.imwrite(str(tmp / name), big[..., ::-1]):
                raise StageError(f"could not write {PREVIEWS / name}")
            out.append(PREVIEWS / name)
    return out


def main(params: Params) -> None:
    """Render the 13 approach sequences with Blender Cycles (headless; render.device: CPU or GPU), or import the SPEED/SPEED+
    folder of `render.source`. Writes datasets/render/ (images.zarr, poses.parquet, meta.json) atomically
    and PNG previews to reports/figures/previews/. Parameters: `seed`, `camera`, `render` and `engine`
    (workers, Ray cluster address, image store) in params.yaml.
    """
    imported = params_mod.given(params.render.source) is not None  # a SPEED/SPEED+ folder instead of rendering
    with exclusive(OUT.parent / ".render.lock", str(OUT)):
        device = None
        if imported:
            seconds = speed_io.import_source(params, OUT)
        else:
            remove_leftovers(OUT)
            with atomic_dir(OUT) as tmp:
                seconds, device = render_all(params, tmp)
    images, poses, meta = read_render_store(OUT)
    previews = write_previews(images, poses, params.render.previews)
    n = int(meta["frames"])
    write_metrics(
        METRICS,
        {
            "frames": n,
            "seconds": seconds,
            "seconds_per_image": seconds / max(n, 1),
            "workers": None if imported else engine_settings(params).workers,
            "imported": imported,
            "cycles_device": device,
        },
        params.profile_name,
    )
    typer.echo(
        f"{OUT}: {n} images {meta['width']}x{meta['height']}, {seconds / max(n, 1):.3f} s/image "
        f"(-> {METRICS}); previews: {', '.join(str(x) for x in previews)}"
    )
