"""The rendered trajectory sets of `rpod eval_render` and `rpod heldout`: which approaches a set holds
(`trajectories`), its poses table (`poses_table`) and rendering it into a folder (`render_set`: images.zarr,
poses.parquet, meta.json with the params fingerprint), fanned out over the engine's Blender scenes.
"""

from __future__ import annotations

from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import typer

from pipeline.geometry.labels import pose_columns
from pipeline.io.atomic import atomic_dir, write_json
from pipeline.io.tables import write_parquet
from pipeline.seeds import seed_for
from stages.config.build import execution_settings
from stages.config.schema import Params
from stages.engine.chunks import frame_backgrounds, render_to_store, store_url


def trajectories(
    p: Params, seed: int, count: int, frames: int | None = None, envelope: bool = False, flown: bool = False
) -> list[Any]:
    """`count` approaches from `seed`, `frames` (default evaluate.frames) frames each; `flown`: each executed with
    guidance.execution's error (seeded per trajectory), the planned steps kept as its commands.

    The evaluation trajectories of the spec (and the defense's validation ones, the same kind of mission):
    lateral start offsets |x|, |y| uniform in evaluate.lateral_range with random signs, projectile paths,
    the target at rest (identity attitude). With `envelope`: the views the pose network was trained for, so
    that a detector, or a detector threshold, fitted on them has seen every kind of clean view: x, y uniform
    in +-max(evaluate.lateral_range), the paths cycling through projectile and straight (the training
    sequences' shape, seen obliquely), each with the target at rest and turned afresh every frame by up to
    render.max_target_rotation_deg about each axis (as the rotating training sequences). Until issue 27's
    envelope fix the detector split was drawn like the evaluation trajectories, and the shipped detector at
    its calibrated threshold flagged 46% of clean pose-test frames (oblique and turned views it had never seen).
    """
    from pipeline.geometry.trajectories import approach_trajectory
    from pipeline.guidance.dynamics import execute_plan

    e, r = p.evaluate, p.render
    rng = np.random.default_rng(seed)
    lo, hi = e.lateral_range
    n = frames or e.frames
    step = (float(r.start_range) - float(r.end_range)) / (n - 1)  # m per frame along the approach
    out = []
    for i in range(count):
        if envelope:
            xy, path = rng.uniform(-hi, hi, 2), ("projectile", "straight")[i % 2]
            rot = float(r.max_target_rotation_deg) if i % 4 >= 2 else 0.0
        else:
            xy, path, rot = rng.uniform(lo, hi, 2) * rng.choice([-1.0, 1.0], 2), "projectile", 0.0
        execute = (
            partial(execute_plan, settings=execution_settings(p, seed_for(seed, "eval_render.execution", i), step))
            if flown
            else None
        )
        out.append(
            approach_trajectory(
                n,
                (float(xy[0]), float(xy[1])),
                float(r.start_range),
                float(r.end_range),
                seed=seed_for(seed, "eval_render.trajectory", i),
                jitter_deg=float(r.pointing_jitter_deg),
                max_rot_deg=rot,
                sequence=i,
                path=path,
                execute=execute,
            )
        )
    return out


def render_set(
    K: Any,
    scene: Any,
    es: Any,
    seqs: list[Any],
    folder: Path,
    fingerprint: str,
    hint: str,
    seed: int,
    stage: str = "eval_render",
) -> dict[str, Any]:
    """Render the trajectories `seqs` into `folder` (images.zarr, poses.parquet, meta.json; the frames' background
    draws from `seed`, their kinds in the poses' `background` column while render.background is on); returns the
    frame count and render time (s) for the metrics JSON; `stage` names it in the progress and the summary line.
    A set mostly out of view is refused (`hint`: the params that put it there)."""
    n = sum(len(s) for s in seqs)
    R, t = np.concatenate([s.R for s in seqs]), np.concatenate([s.t for s in seqs])
    R_cam = np.concatenate([s.R_cam for s in seqs])
    poses = poses_table(seqs)
    draws, kinds = frame_backgrounds(K, scene, R, R_cam, seed)
    if kinds is not None:
        poses["background"] = kinds
    with atomic_dir(folder) as tmp:
        seconds = render_to_store(
            store_url(tmp / "images.zarr"),
            K,
            scene,
            R,
            t,
            min(n, 100),
            es,
            f"{stage} {folder.name}",
            empty_hint=hint,
            backgrounds=draws,
        )
        write_parquet(poses, tmp / "poses.parquet")
        write_json(
            tmp / "meta.json",
            {
                "complete": True,
                "fingerprint": fingerprint,
                "frames": n,
                "trajectories": len(seqs),
                "width": K.width,
                "height": K.height,
                "K": K.K,
                "start_xy": [s.rel[0, :2].tolist() for s in seqs],
            },
        )
    typer.echo(f"{stage}: {n} images ({len(seqs)} trajectories) in {seconds:.0f} s -> {folder}")
    return {"frames": n, "seconds": seconds, "images_per_s": n / seconds if seconds > 0 else None}


def poses_table(seqs: list[Any]) -> Any:
    """poses.parquet of the trajectories `seqs`: index, trajectory, frame, the label pose (t, q, 6-D; the flown
    truth), range, rel_x..z (the flown rel, world, m), cmd_x..z (the commanded displacement of rel since the previous
    frame: a sequence's planned steps when it was flown with execution error, else its own steps; zero on its first
    frame) and c0..c8 (camera -> world, row-major)."""
    import pandas as pd

    from pipeline.geometry.rotations import matrix_to_6d, matrix_to_quat

    n = sum(len(s) for s in seqs)
    R, t = np.concatenate([s.R for s in seqs]), np.concatenate([s.t for s in seqs])
    rel, R_cam = np.concatenate([s.rel for s in seqs]), np.concatenate([s.R_cam for s in seqs])
    cmd = np.concatenate(
        [np.vstack([np.zeros(3), np.diff(s.rel, axis=0)]) if s.commands is None else s.commands for s in seqs]
    )
    q, r6 = matrix_to_quat(R), matrix_to_6d(R)
    return pd.DataFrame(
        {
            "index": np.arange(n),
            "trajectory": np.concatenate([np.full(len(s), s.sequence) for s in seqs]),
            "frame": np.concatenate([s.frame for s in seqs]),
            **pose_columns(t, q, r6),
            "range": np.linalg.norm(t, axis=1),
            **{f"rel_{a}": rel[:, j] for j, a in enumerate("xyz")},
            **{f"cmd_{a}": cmd[:, j] for j, a in enumerate("xyz")},
            **{f"c{j}": R_cam[:, j // 3, j % 3] for j in range(9)},
        }
    )
