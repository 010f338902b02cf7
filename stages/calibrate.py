"""`rpod calibrate [--model robust|standard]`: calibrate the defense of one chain on clean validation
trajectories, one check at a time: the robust model's chain (the one that ships, dvc stage `calibrate`) ->
models/defense.json; the standard model's (the paper's reproduction, stage `calibrate_standard`, for its
integrity and defended rows beside the shipped chain's) -> models/defense_standard.json.

Runs the safety chain clean over the validation approaches `rpod eval_render` rendered into
datasets/val_render/ (their base seed follows `seed`, never the evaluation's; the same kind of mission as the
evaluation's, flown with the execution error the filter is not told: `defense.position_noise` is its std per
step) and over the frames of datasets/val_envelope/ (every kind of clean view the pose network was trained for:
the detector's threshold must meet its share on both), fits the pose model's
range-dependent measurement noise and bias (`pipeline.defense.noise.fit_noise`, `defense.noise_bins`
range bins), then sets each check to its own share (`defense.shares`) of the false-alarm budget
`defense.target_false_alarm` (pipeline/defense/calibration.py): the detector's threshold (a quantile of
these clean frames' probabilities), the noise inflation of the gate, the sequential test's threshold.
When every check meets its share but their fusion flags more than the target (a rejected frame leaves the
filter to coast, which can raise the next innovations), every share is tightened by the overshoot (at least x0.75) and
the checks are calibrated again, at most three times (the search: pipeline.defense.calibration.calibrate_to_target;
models/defense.json records it under `tightened`).
A check that cannot meet its share stops the stage with one line naming it and what it reached,
unless `defense.allow_unmet` (then models/defense.json lists it under `unmet`, and the reports that
use the defense say so in their first line). Writes the defense file (pipeline/formats/defense.py):
the noise model, the thresholds, the doubt level (the detector probability from which a frame does not
update the filter: at most `defense.doubt_share` of the clean validation frames reach it), the settings, and
the defended chain's false alarms of each check, availability and protection levels on those clean
validation frames.
"""

from __future__ import annotations

from typing import Annotated, Any

import numpy as np
import typer

from pipeline.formats.defense import DEFENSE_FORMAT, DefenseFile, Validation, parse_defense
from pipeline.geometry.labels import TARGET
from pipeline.io.atomic import write_json
from stages.artifacts.clean_runs import chain_outputs, clean_runs, fit_pose_noise
from stages.artifacts.models import load_chain, model_option
from stages.artifacts.paths import CHAINS, Model
from stages.artifacts.readers import read_eval_render, read_val_envelope
from stages.config.build import alert_limit_settings, defense_settings
from stages.config.device import torch_setup
from stages.config.params import validation_seed
from stages.config.schema import Params
from stages.errors import StageError
from stages.pages.calibrate import summary_line, unmet_line

ModelOption = Annotated[Model, model_option("Writes models/defense.json (robust) or models/defense_standard.json.")]


def main(params: Params, model: ModelOption = Model.robust) -> None:
    """Calibrate the defense's checks of one chain on clean validation trajectories -> its defense file.

    Params: `defense` (noise_bins, target_false_alarm, shares, allow_unmet, val_trajectories and the filter
    settings), `evaluate.batch_size`, the alert limit's (`guidance.tolerance`, `max_step`,
    `slack_steps`, `integrity.collision_range_m`) for the availability it records.
    """
    from pipeline.defense.calibration import Budget, UnmetShare, calibrate_to_target

    d = params.defense
    torch_setup(params)
    images, poses, _ = read_eval_render(params, validation=True)
    envelope, _ = read_val_envelope(params)
    safety = load_chain(params, model, defended=False)
    chain, model_hash = safety.onboard, safety.pose_hash
    pose, prob = chain_outputs(chain, images, params.evaluate.batch_size, "calibrate")
    _, envelope_prob = chain_outputs(chain, envelope, params.evaluate.batch_size, "calibrate")
    targets = poses[TARGET].to_numpy(np.float32)
    fitted = fit_pose_noise(
        targets, pose, d.noise_bins, f"{len(images)} validation frames (defense.val_trajectories, defense.noise_bins)"
    )
    runs, truths = clean_runs(poses, pose, prob)
    alert = alert_limit_settings(params)
    budget = Budget(
        d.target_false_alarm, d.shares.detector, d.shares.gate, d.shares.sequential, d.doubt_share, d.allow_unmet
    )
    try:
        c = calibrate_to_target(
            *defense_settings(d, chain.threshold), fitted, runs, (prob, envelope_prob), truths, alert, budget
        )
    except UnmetShare as e:
        raise StageError(unmet_line(e.check, len(images))) from None
    checks, settings, motion, noise, final = c.checks, c.settings, c.motion, c.noise, c.final
    unmet = _unmet(params, c, len(images))
    out = CHAINS[model].defense
    record = DefenseFile(
        DEFENSE_FORMAT,
        model.value,
        model_hash,
        chain.threshold,
        settings.threshold,
        motion.cusum_threshold,
        checks[2].setting,
        checks[1].setting,
        noise,
        fitted,
        settings,
        motion,
        alert,
        tuple(unmet),
        Validation(**_validation(params, len(images), checks, final, envelope_prob, prob, settings.update_below)),
        {"shares_scale": c.scale, "before": c.tightened} if c.tightened else None,
    ).to_json()
    parse_defense(record, str(out))  # what every reader will require of it
    write_json(out, record)
    typer.echo(summary_line(record, out))


def _unmet(params: Params, c: Any, frames: int) -> list[str]:
    """The lines naming each check that missed its share and, when the fused chain flags more than the target, the
    fusion's; raises a StageError on the latter unless `defense.allow_unmet`."""
    d = params.defense
    unmet = [unmet_line(check, frames) for check in c.checks if not check.met]
    if c.final["fused"].value > d.target_false_alarm:
        unmet.append(unmet_line(None, frames, c.final["fused"].value, d.target_false_alarm, len(c.tightened)))
        if not d.allow_unmet:
            raise StageError(unmet[-1])
    return unmet


def _validation(
    params: Params,
    frames: int,
    checks: list[Any],
    final: dict[str, Any],
    envelope_prob: np.ndarray,
    prob: np.ndarray,
    doubt: float | None,
) -> dict[str, Any]:
    """defense.json's record of the validation frames: each check's calibration and the fused chain, the
    detector's false alarms on the envelope frames at its threshold, and the share of the validation frames
    (probabilities `prob`) at or above the doubt level `doubt`."""
    d = params.defense

    def pct(r: Any) -> dict[str, Any]:
        return {"pct": round(100 * r.value, 4), "ci95_pct": [round(100 * v, 4) for v in r.ci()]}

    alarms = float(np.mean(envelope_prob >= checks[0].setting))
    return {
        "trajectories": d.val_trajectories,
        "seed": validation_seed(params),
        "frames": frames,
        "envelope": {"frames": int(envelope_prob.size), "detector_pct": round(100 * alarms, 4)},
        "doubt": {
            "level": doubt,
            "share_pct": None if d.doubt_share is None else 100 * d.doubt_share,
            "reached_pct": None if doubt is None else round(100 * float(np.mean(prob >= doubt)), 4),
        },
        "target_pct": 100 * d.target_false_alarm,
        "checks": {
            c.check: {
                "setting": c.setting,
                "share_pct": round(100 * c.share, 4),
                "reached_pct": round(100 * c.reached, 4),
                "met": c.met,
                "tried": {f"{k:g}": round(100 * v, 4) for k, v in c.rates.items()},
            }
            for c in checks
        },
        "false_alarms": {k: pct(final[k]) for k in ("detector", "gate", "sequential", "fused")},
        "availability": pct(final["availability"]),
        "mi": pct(final["mi"]),
        "pl_m": final["pl_m"],
        "error_m": final["error_m"],
    }
