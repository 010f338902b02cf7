"""`rpod lab_models`: the synthetic-lab pose model and detector that `rpod lab` uses when it may not reuse
the main ones; a cheap no-op otherwise.

The lab stage may reuse models/pose.pt and models/detector.pt when the lab mock-up is the main
target mesh (our K_blender already has the lab images' 16:9 aspect). With `lab.retrain: always` (the
paper profile), or whenever `lab.mesh` names another mock-up, it trains them again on a
"synthetic-lab" set instead: the mock-up rendered at `lab.scale` times its size (so the ranges
60..10 m of the 13 approach sequences are preserved) with the same camera K_blender at
render.width x render.height.

The retraining runs the pipeline's own stage commands (`rpod render`, `label`, `train`,
`eval_render --detector`, `shap`, `detect`) unchanged, each as a subprocess in the stage's output folder `datasets/lab_models/` with a
params.yaml derived from the main one (`sub_params`): the same training recipe (`train`, `shap`,
`detect`, `label` sections), the mock-up mesh, `lab.train_frames_per_sequence` frames per sequence,
base seed `lab.seed` (its stream in pipeline/seeds.py), and no detector baselines (the lab chain uses the LSTM only).
That folder then holds what the main pipeline holds at the top level: datasets/render/,
datasets/labels.parquet, models/pose.pt, datasets/detect_render/, datasets/shap.zarr, models/detector.pt, reports/*.md and
reports/metrics/{train,detect}.json, plus summary.json (what `rpod lab` reads: whether and why it
retrained, the model paths, the synthetic-lab test errors). Without retraining only summary.json is
written, so DVC runs this stage as a no-op and `rpod lab` is not re-run for it.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from pipeline.io.atomic import atomic_dir, file_hash, read_json, write_json
from pipeline.seeds import seed_for
from stages.artifacts.paths import DETECT_METRICS, DETECTOR, LAB_MODELS, LAB_MODELS_SUMMARY, POSE, RENDER, TRAIN_METRICS
from stages.config.build import mockup, retrain_reason
from stages.config.params import NONE
from stages.config.schema import Params
from stages.engine.subrun import run_steps


def sub_params(p: Params) -> Params:
    """params.yaml of the synthetic-lab sub-pipeline: the main params with the mock-up as the target."""
    lab = p.lab
    mesh, mesh_scale = mockup(p)
    frames = p.render.frames_per_sequence if lab.train_frames_per_sequence is None else lab.train_frames_per_sequence
    # source: the synthetic-lab set is rendered, never a SPEED import
    render = dataclasses.replace(p.render, mesh=mesh, mesh_scale=mesh_scale, source=NONE, frames_per_sequence=frames)
    return dataclasses.replace(
        p,
        seed=seed_for(lab.seed, "lab_models"),
        render=render,
        detect=dataclasses.replace(p.detect, baselines=[]),
        engine=dataclasses.replace(p.engine, store=None),
    )  # its renders stay in its folder


# the sub-pipeline, in order: dvc.yaml stage name -> its `rpod` command (the detector's false alarms on
# evaluation trajectories are left out: the lab stage measures this detector on the lab frames)
STEPS = {
    "render": ["render"],
    "label": ["label"],
    "train": ["train"],
    "detect_render": ["eval_render", "--detector"],
    "shap": ["shap"],
    "detect": ["detect", "--no-eval-alarms"],
}


def retrain(p: Params, dest: Path, final: Path) -> dict[str, Any]:
    """Render, label, train, explain and detect on the synthetic-lab set in `dest` (a fresh folder that
    becomes `final`); returns the summary the lab report and metrics show (seconds per step)."""
    sub = sub_params(p)
    seconds = run_steps(sub, STEPS, dest, final, "lab.retrain", "on the synthetic-lab set in")
    train_m = read_json(dest / TRAIN_METRICS)
    detect_m = read_json(dest / DETECT_METRICS)
    meta = read_json(dest / RENDER / "meta.json")
    r = sub.render
    return {
        "retrained": True,
        "folder": str(final),
        "reason": retrain_reason(p),
        "seed": sub.seed,
        "mesh": r.mesh,
        "mesh_scale": r.mesh_scale,
        "frames_per_sequence": r.frames_per_sequence,
        "images": int(meta["frames"]),
        "size": [int(meta["width"]), int(meta["height"])],
        "pose": str(final / POSE),
        "pose_hash": file_hash(dest / POSE),
        "detector": str(final / DETECTOR),
        "train_test": {k: train_m["test"][k] for k in ("n", "pos_mean_m", "att_mean_deg")},
        "best_epoch": train_m["best_epoch"],
        "epochs_run": train_m["epochs_run"],
        "shap_samples": int(detect_m["counts"]["samples"]),
        "detector_test_accuracy": detect_m["detectors"]["lstm"]["all"]["accuracy"],
        "seconds": seconds,
    }


def main(params: Params) -> None:
    """Train the synthetic-lab pose model and detector into datasets/lab_models/ when `rpod lab` may not
    reuse the main ones (lab.retrain: always, or another mock-up in lab.mesh); else only record that.
    Params: the `lab` section and the training recipe (`render`, `label`, `train`, `shap`, `detect`)."""
    reason = retrain_reason(params)
    with atomic_dir(LAB_MODELS) as tmp:
        if reason is None:
            summary: dict[str, Any] = {"retrained": False, "reason": None}
        else:
            print(f"lab_models: retraining the pose model and detector on a synthetic-lab set ({reason})", flush=True)
            summary = retrain(params, tmp, LAB_MODELS)
        write_json(tmp / LAB_MODELS_SUMMARY.name, summary)
    print(
        f"lab_models: {'retrained' if reason else 'nothing to train (the lab reuses the main models)'} "
        f"-> {LAB_MODELS_SUMMARY}"
    )
