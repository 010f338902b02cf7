"""`rpod eval_render`: render the fresh evaluation trajectories once, for `rpod evaluate` and its eps;
`rpod eval_render --detector`: the detector split, the images `rpod shap` explains.

Renders `evaluate.trajectories` projectile-shaped approaches (their base seed follows `seed`:
stages.config.params.evaluation_seed), their chunks fanned out over `engine.workers` Blender scenes
(stages/engine/pool.py), into datasets/eval_render/ (images.zarr, poses.parquet, meta.json with the params
fingerprint), so changing eps or the models never re-renders; and, in the same Ray session,
`defense.val_trajectories` validation approaches of their own base seed (`validation_seed`) into
datasets/val_render/ (what `rpod calibrate` fits the defense on: never the evaluation seeds). Both sets are flown,
not planned: each planned step is commanded and executed with the thrusters' error and Clohessy-Wiltshire motion
(`guidance.execution`, pipeline/guidance/dynamics.py `execute_plan`, seeded per trajectory), at the closed loop's
speed (a frame of 0.25 m takes a quarter of its 1 m step's interval). poses.parquet holds the truth and what the
chaser knows of itself: rel (target relative to the chaser, world axes, m: the flown path), the commanded
displacement of rel since the previous frame cmd_x, cmd_y, cmd_z (world, m: the planned steps, what the chain is
told; zero on a trajectory's first frame) and the camera attitude c0..c8 (camera -> world, row-major).

With `--detector` (dvc.yaml stage `detect_render`) it renders only the detector split into
datasets/detect_render/: approaches drawn like the evaluation ones but from `shap.seed`, `shap.frames`
frames each, as many as the SHAP sample plan's source images need (stages.config.params.detector_trajectories).
The pose network never saw these images, so the detector's clean and attacked samples come from the
same unseen images (issue 27: clean samples partly from the pose-training split made "unfamiliar"
read as "attacked"). Render times go to reports/metrics/{eval_render,detect_render}.json, never into
meta.json, so the same params give byte-identical folders (stable DVC hashes).
"""

from __future__ import annotations

from functools import partial
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer

from pipeline.geometry.labels import pose_columns
from pipeline.io.atomic import atomic_dir, write_json
from pipeline.io.tables import write_parquet
from pipeline.seeds import seed_for
from stages.artifacts.dvc import write_metrics
from stages.artifacts.paths import (
    DETECT_RENDER,
    DETECT_RENDER_METRICS,
    EVAL_RENDER,
    EVAL_RENDER_METRICS,
    VAL_ENVELOPE,
    VAL_RENDER,
)
from stages.config.build import execution_settings, intrinsics, scene_settings
from stages.config.params import (
    detect_render_fingerprint,
    detector_trajectories,
    eval_render_fingerprint,
    evaluation_seed,
    val_envelope_fingerprint,
    val_render_fingerprint,
    validation_seed,
)
from stages.config.schema import Params
from stages.engine import pool as engine
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


def main(
    params: Params,
    detector: Annotated[
        bool,
        typer.Option(
            "--detector",
            help="Render the detector split instead (datasets/detect_render: shap.seed, shap.frames per trajectory).",
        ),
    ] = False,
) -> None:
    """Render the fresh evaluation trajectories into datasets/eval_render/, the defense's validation
    trajectories (the same kind of mission) into datasets/val_render/ and validation frames over the whole
    envelope (for the detector threshold) into datasets/val_envelope/, fanned out over `engine.workers`
    Blender scenes; with --detector the detector split into datasets/detect_render/.

    Params: `seed` (the trajectories' base seeds follow it), `evaluate.trajectories`, `frames`, `lateral_range`;
    `defense.val_trajectories`; `guidance.execution` and `max_step` (the flown motion); `shap.frames`, `seed`
    (--detector); `render`/`camera`; and `engine` (workers, Ray cluster address).
    """
    K, scene, es = intrinsics(params), scene_settings(params.render), engine.engine_settings(params)
    d, e, s = params.defense, params.evaluate, params.shap
    if detector:
        sets = [
            (
                DETECT_RENDER,
                trajectories(params, s.seed, detector_trajectories(params), s.frames, envelope=True),
                detect_render_fingerprint(params),
                s.seed,
            )
        ]
    else:
        evaluation, validation = evaluation_seed(params), validation_seed(params)
        envelope_seed = seed_for(validation, "eval_render.envelope")
        sets = [
            (
                EVAL_RENDER,
                trajectories(params, evaluation, e.trajectories, flown=True),
                eval_render_fingerprint(params),
                evaluation,
            ),
            (
                VAL_RENDER,
                trajectories(params, validation, d.val_trajectories, flown=True),
                val_render_fingerprint(params),
                validation,
            ),
            (
                VAL_ENVELOPE,
                trajectories(params, envelope_seed, d.val_trajectories, envelope=True),
                val_envelope_fingerprint(params),
                envelope_seed,
            ),
        ]
    timings: dict[str, Any] = {}
    hint = f"check params.yaml evaluate.lateral_range={list(e.lateral_range)} (lateral start offsets, m)"
    with engine.session(es):
        for folder, seqs, fingerprint, seed in sets:
            timings[folder.name] = _render_set(
                K, scene, es, seqs, folder, fingerprint, hint, seed_for(seed, "background")
            )
    write_metrics(
        DETECT_RENDER_METRICS if detector else EVAL_RENDER_METRICS,
        {"workers": es.workers, "sets": timings},
        params.profile_name,
    )


def _render_set(
    K: Any, scene: Any, es: Any, seqs: list[Any], folder: Path, fingerprint: str, hint: str, seed: int
) -> dict[str, Any]:
    """Render the trajectories `seqs` into `folder` (images.zarr, poses.parquet, meta.json; the frames' background
    draws from `seed`, their kinds in the poses' `background` column while render.background is on); returns the
    frame count and render time (s) for the metrics JSON. A set mostly out of view is refused (`hint`: the params
    that put it there)."""
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
            f"eval_render {folder.name}",
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
    typer.echo(f"eval_render: {n} images ({len(seqs)} trajectories) in {seconds:.0f} s -> {folder}")
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
