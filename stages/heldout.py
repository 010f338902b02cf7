"""`rpod heldout`: issue 38's held-out confirmation -> reports/heldout.md, reports/metrics/heldout.json,
datasets/heldout/. A stage of optional/dvc.yaml (`dvc repro optional/dvc.yaml:heldout`), not of the default
`dvc repro`: it needs the fy360 pose trial (`rpod pose_trial fy360`, about 10 minutes of training on 2 cores).

Three choices were made looking at numbers that are also reported as results (README, "Choices made on reported
numbers"). Each is re-checked once here, on a final set of approaches drawn from their own base seed
(`run_base(seed, "heldout")`: pipeline/seeds.py), which no choice, calibration or training
read: `evaluate.trajectories` approaches of the evaluation's kind (`evaluate.frames`, `lateral_range`, flown
with `guidance.execution`'s error), rendered once with the params' camera and once with the fy360 trial's.
- **Camera default** (reports/camera.md): the committed standard model (models/pose.pt) on the held-out frames
  of its camera against the fy360 trial's model on the same approaches rendered with fy = 360: position,
  attitude and depth (tz, 10-30 m) errors, each difference paired by approach; and the lab half of what the
  choice was made on: the two models on held-out lab-like recordings (lab.sequences drawn `LAB_DRAWS` times from
  the held-out base, datasets/heldout/lab/), each against the targets of its own camera, paired by recording.
- **Motion checks' calibration** (on validation approaches of the mission's kind, datasets/val_render, kept over
  calibrating them on the envelope validation set, datasets/val_envelope): the shipped chain flown clean on the
  held-out approaches with its committed defense (models/defense.json) and with the alternative, calibrated here
  by the same search (pipeline.defense.calibration.calibrate_to_target) with the noise model, gate and sequential
  test fitted on the envelope set (the detector's threshold and doubt level as committed: the same clean
  probabilities): availability, false alarms, MI, PL.
- **Black-level clamp** (`train.adversarial.black_level`): the held-out frames' background under the simulated lab
  shift (pipeline.pose.robustness.black_level_stats) against the threshold.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import typer

from pipeline.geometry.labels import TARGET
from pipeline.io.atomic import atomic_write_text, check_writable
from pipeline.io.files import read_yaml
from pipeline.seeds import seed_for
from stages.artifacts.clean_runs import chain_outputs, clean_runs, fit_pose_noise
from stages.artifacts.dvc import write_metrics
from stages.artifacts.models import load_chain, load_pose, load_trial_pose
from stages.artifacts.paths import HELDOUT, HELDOUT_METRICS, HELDOUT_REPORT, POSE_TRIALS, SHIPPED
from stages.artifacts.readers import read_eval_render, read_heldout, read_val_envelope
from stages.config.build import alert_limit_settings, defense_settings, intrinsics, scene_settings
from stages.config.params import CONF_STAMP, PARAMS_FILE, heldout_fingerprint, heldout_seed
from stages.config.schema import Params, build
from stages.engine import pool as engine
from stages.engine.trajectory_sets import render_set, trajectories
from stages.errors import StageError
from stages.pages.heldout import heldout_page

CHOSEN, ALTERNATIVE = "chosen", "fy360"  # the held-out sets: the params' camera, the fy360 trial's
LAB, LAB_DRAWS = "lab", 3  # held-out lab-like recordings: lab.sequences drawn LAB_DRAWS times (datasets/heldout/lab/)
TRIAL_SECTIONS = ("seed", "render", "label", "train")  # what the fy360 trial's model was trained on besides its camera


def main(params: Params) -> None:
    """Re-check the camera default, the motion checks' calibration and the black-level clamp once on final
    held-out approaches that no choice read -> reports/heldout.md, reports/metrics/heldout.json.

    Params: `seed` (the held-out base follows it), `evaluate.trajectories`, `frames`, `lateral_range`,
    `batch_size`; `guidance.execution` (the flown motion); `camera`, `render`; `defense` (the calibration's
    budget and shares); `train.adversarial.black_level`, `lab.domain_shift` (the clamp's check); `lab` (the held-out lab-like
    recordings: its sequences, mock-up, camera and loader); `engine`.
    Needs datasets/pose_trials/fy360 (`rpod pose_trial fy360`).
    """
    from stages.config.device import torch_setup

    check_writable(HELDOUT.parent, HELDOUT_REPORT.parent, HELDOUT_METRICS.parent)
    trial = _fy360_trial(params)
    device = torch_setup(params)
    t0 = time.perf_counter()
    cameras = {CHOSEN: params, ALTERNATIVE: trial}
    render_s = {**_render(cameras), LAB: _render_lab(params)}
    sets = {name: read_heldout(p, HELDOUT / name) for name, p in cameras.items()}
    models = {CHOSEN: load_pose(params).model, ALTERNATIVE: load_trial_pose(trial, POSE_TRIALS / ALTERNATIVE, device)}
    metrics = {
        "seed": heldout_seed(params),
        "trajectories": int(params.evaluate.trajectories),
        "frames": int(len(sets[CHOSEN][0])),
        "camera": _camera(params, trial, sets, models, device),
        "lab_camera": _lab_camera(cameras, models, device),
        "calibration": _calibration(params, *sets[CHOSEN]),
        "clamp": _clamp(params, *sets[CHOSEN]),
        "render_seconds": render_s,
        "seconds": time.perf_counter() - t0,
    }
    write_metrics(HELDOUT_METRICS, metrics, params.profile_name)
    atomic_write_text(HELDOUT_REPORT, heldout_page(metrics, params))
    c = metrics["camera"]["position_m"]
    typer.echo(
        f"heldout: camera {c['verdict']} (position {c['difference'][0]:+.3f} m), calibration "
        f"{metrics['calibration']['verdict']}, clamp {metrics['clamp']['verdict']} -> {HELDOUT_REPORT}"
    )


def _fy360_trial(params: Params, current: Path = PARAMS_FILE) -> Params:
    """The fy360 pose trial's params: `params` (read from `current`) with the camera of the trial's own record
    (datasets/pose_trials/fy360/params.yaml). Refused when the record is missing, when it was trained on other
    params than the camera (TRIAL_SECTIONS: then it is not the default's model with another camera) or when its
    camera is the default's. Params added since the trial was trained (another stage's knobs) do not matter."""
    folder = POSE_TRIALS / ALTERNATIVE
    if not (folder / PARAMS_FILE).exists():
        raise StageError(f"{folder} not found: run `rpod pose_trial fy360` (dvc repro optional/dvc.yaml:trial_fy360)")
    record, now = read_yaml(folder / PARAMS_FILE), read_yaml(current)
    if not isinstance(record, dict):
        raise StageError(
            f"{folder / PARAMS_FILE} must hold a mapping of params sections: re-run `rpod pose_trial fy360`"
        )
    changed = [key for key in TRIAL_SECTIONS if record.get(key) != now.get(key)]
    if changed or "camera" not in record:
        raise StageError(
            f"{folder / PARAMS_FILE} differs from {current} in {', '.join(changed) or 'camera (missing)'}, not in the "
            "camera alone: re-run `rpod pose_trial fy360` (dvc repro optional/dvc.yaml:trial_fy360)"
        )
    now.pop(CONF_STAMP, None)
    trial = build({**now, "camera": record["camera"]})
    if trial.camera == params.camera:
        raise StageError(
            f"params.yaml camera = {folder / PARAMS_FILE}'s camera (fy = {params.camera.fy:g}): nothing to compare; "
            "the held-out check compares the default camera with the paper's printed fy = 360"
        )
    return trial


def _render(cameras: dict[str, Params]) -> dict[str, Any]:
    """Render the held-out approaches once per camera into datasets/heldout/<name>/ (the same approaches: the
    trajectories depend on the held-out base, `evaluate` and `render`, not on the camera)."""
    timings = {}
    first = next(iter(cameras.values()))
    es = engine.engine_settings(first)
    with engine.session(es):
        for name, p in cameras.items():
            base = heldout_seed(p)
            seqs = trajectories(p, base, p.evaluate.trajectories, flown=True)
            timings[name] = render_set(
                intrinsics(p),
                scene_settings(p.render),
                es,
                seqs,
                HELDOUT / name,
                heldout_fingerprint(p),
                f"check params.yaml evaluate.lateral_range={list(p.evaluate.lateral_range)} (lateral start offsets, m)",
                seed_for(base, "background"),
                stage="heldout",
            )
    return timings


def _render_lab(params: Params) -> float:
    """Render the held-out lab-like recordings into datasets/heldout/lab/draw<d>/ (seconds): lab.sequences with the
    lab camera and domain shift (stages/engine/lab_sets.py), each draw from the "heldout.lab" stream of the held-out
    base, so no recording is one of `rpod lab`'s. The lab camera is the ZED's: one render serves both cameras."""
    from pipeline.io.atomic import atomic_dir
    from stages.engine.lab_sets import render_lab

    t0, base = time.perf_counter(), heldout_seed(params)
    with atomic_dir(HELDOUT / LAB) as tmp:
        for d in range(LAB_DRAWS):
            render_lab(params, tmp / f"draw{d + 1}", seed_for(base, "heldout.lab", d))
    return time.perf_counter() - t0


def _lab_camera(cameras: dict[str, Params], models: dict[str, Any], device: Any) -> dict[str, Any]:
    """The lab half of the camera check: each camera's model on the held-out lab-like recordings read through the
    real-data loader, against the synthetic-frame targets of its own camera (pipeline.evaluation.lab.chain_sequences:
    the lab image is the same, the camera it is taken to be differs), paired by recording; tz on the frames within the
    band for both cameras."""
    from pipeline.evaluation.heldout import compare_models, pose_errors_by_frame
    from pipeline.evaluation.lab import chain_sequences
    from pipeline.pose.train import PoseDataset, predict
    from stages.artifacts.recordings import read_recordings
    from stages.engine.lab_sets import cameras as lab_cameras

    errors = {}
    for name, p in cameras.items():
        recs = [r for d in range(LAB_DRAWS) for r in read_recordings(p, HELDOUT / LAB / f"draw{d + 1}")]
        K_syn, K_zed = lab_cameras(p)
        lab = p.lab
        seqs, _ = chain_sequences(
            recs, K_syn, K_zed, float(lab.scale), float(p.evaluate.p_start), lab.attack_length, lab.seed
        )
        targets = np.concatenate([q.targets for q in seqs])
        ids = np.concatenate([np.full(len(q.targets), i) for i, q in enumerate(seqs)])
        images = np.concatenate([q.images for q in seqs])
        pred = predict(models[name], PoseDataset(images, targets, None, 0), device=device)
        errors[name] = pose_errors_by_frame(pred, targets, ids)
    both = np.isfinite(errors[CHOSEN]["tz_near_pct"]) & np.isfinite(errors[ALTERNATIVE]["tz_near_pct"])
    for e in errors.values():
        e["tz_near_pct"] = np.where(both, e["tz_near_pct"], np.nan)
    return {"recordings": len(seqs), **compare_models(errors[CHOSEN], errors[ALTERNATIVE])}


def _camera(params: Params, trial: Params, sets: dict[str, Any], models: dict[str, Any], device: Any) -> dict[str, Any]:
    """The committed standard model on the chosen camera's held-out frames against the fy360 trial's model on the
    same approaches rendered with its camera (pipeline.evaluation.heldout.compare_models)."""
    from pipeline.evaluation.heldout import compare_models, pose_errors_by_frame
    from pipeline.pose.train import PoseDataset, predict

    errors = {}
    for name, (images, poses) in sets.items():
        targets = poses[TARGET].to_numpy(np.float32)
        pred = predict(models[name], PoseDataset(images, targets, None, 0), device=device)
        errors[name] = pose_errors_by_frame(pred, targets, poses["trajectory"].to_numpy())
    return {
        "chosen_fy": float(params.camera.fy),
        "alternative_fy": float(trial.camera.fy),
        **compare_models(errors[CHOSEN], errors[ALTERNATIVE]),
    }


def _calibration(params: Params, images: np.ndarray, poses: Any) -> dict[str, Any]:
    """The shipped chain flown clean on the held-out approaches with its committed defense and with the motion
    checks calibrated on the envelope validation set instead (module docstring)."""
    from pipeline.defense.calibration import Budget, calibrate_to_target
    from pipeline.evaluation.heldout import calibration_verdict, defended_summary

    d, batch = params.defense, params.evaluate.batch_size
    safety = load_chain(params, SHIPPED)
    chain, committed = safety.onboard, safety.defended
    val_images, _, _ = read_eval_render(params, validation=True)
    env_images, env_poses = read_val_envelope(params)
    _, val_prob = chain_outputs(chain, val_images, batch, "heldout (validation)")
    env_pose, env_prob = chain_outputs(chain, env_images, batch, "heldout (envelope)")
    pose, prob = chain_outputs(chain, images, batch, "heldout (held-out)")
    env_runs, env_truths = clean_runs(env_poses, env_pose, env_prob)
    fitted = fit_pose_noise(
        env_poses[TARGET].to_numpy(np.float32), env_pose, d.noise_bins, f"{len(env_images)} envelope validation frames"
    )
    alert = alert_limit_settings(params)
    budget = Budget(d.target_false_alarm, d.shares.detector, d.shares.gate, d.shares.sequential, d.doubt_share, True)
    alt = calibrate_to_target(
        *defense_settings(d, chain.threshold), fitted, env_runs, (val_prob, env_prob), env_truths, alert, budget
    )
    runs, truths = clean_runs(poses, pose, prob)
    chosen = defended_summary(committed.settings, committed.motion, committed.noise, runs, truths, alert)
    other = defended_summary(alt.settings, alt.motion, alt.noise, runs, truths, alert)
    return {
        "chosen": _summary_json(chosen),
        "alternative": _summary_json(other),
        "alternative_unmet": [c.check for c in alt.checks if not c.met],
        "alternative_settings": {
            "gate_inflation": alt.checks[2].setting,
            "attitude_inflation": alt.checks[1].setting,
            "cusum_threshold": alt.motion.cusum_threshold,
        },
        "target_false_alarm": d.target_false_alarm,
        "verdict": calibration_verdict(chosen, other, d.target_false_alarm),
    }


def _summary_json(s: dict[str, Any]) -> dict[str, Any]:
    """A clean_summary for JSON: rates as {value, ci}, the rest as is."""
    return {k: {"value": v.value, "ci": v.ci()} if hasattr(v, "ci") else v for k, v in s.items()}


def _clamp(params: Params, images: np.ndarray, poses: Any) -> dict[str, Any]:
    """The black-level clamp's statistics on the held-out frames over a black background
    (pipeline.pose.robustness.black_level_stats, on the held-out base's stream) and its verdict."""
    from pipeline.evaluation.heldout import clamp_verdict
    from pipeline.pose.robustness import black_level_stats
    from stages.artifacts.data import backgrounds

    shift = params.lab.domain_shift
    stats = black_level_stats(
        images,
        float(params.train.adversarial.black_level),
        float(shift.noise_std),
        float(shift.blur_sigma),
        seed_for(heldout_seed(params), "evaluate.black_level"),
        backgrounds=backgrounds(poses),
    )
    return {**stats, "verdict": clamp_verdict(stats)}
