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

from pathlib import Path
from typing import Annotated, Any

import typer

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
from stages.config.build import intrinsics, scene_settings
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
from stages.engine.trajectory_sets import render_set, trajectories


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
    sets = _detector_set(params) if detector else _evaluation_sets(params)
    timings: dict[str, Any] = {}
    hint = f"check params.yaml evaluate.lateral_range={list(params.evaluate.lateral_range)} (lateral start offsets, m)"
    with engine.session(es):
        for folder, seqs, fingerprint, seed in sets:
            timings[folder.name] = render_set(
                K, scene, es, seqs, folder, fingerprint, hint, seed_for(seed, "background")
            )
    write_metrics(
        DETECT_RENDER_METRICS if detector else EVAL_RENDER_METRICS,
        {"workers": es.workers, "sets": timings},
        params.profile_name,
    )


def _detector_set(params: Params) -> list[tuple[Path, list[Any], str, int]]:
    """The detector split: (folder, trajectories, fingerprint, base seed) of datasets/detect_render."""
    s = params.shap
    return [
        (
            DETECT_RENDER,
            trajectories(params, s.seed, detector_trajectories(params), s.frames, envelope=True),
            detect_render_fingerprint(params),
            s.seed,
        )
    ]


def _evaluation_sets(params: Params) -> list[tuple[Path, list[Any], str, int]]:
    """The evaluation, validation and envelope validation sets: (folder, trajectories, fingerprint, base seed)."""
    d, e = params.defense, params.evaluate
    evaluation, validation = evaluation_seed(params), validation_seed(params)
    envelope_seed = seed_for(validation, "eval_render.envelope")
    return [
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
