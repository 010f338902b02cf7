"""Held-out confirmation of the choices made looking at reported numbers (issue 38, item 5): each choice is
re-checked once on a final set of trajectories that no choice, calibration or training read.

- The camera default (square pixels against the paper's printed fy = 360): the two models' pose errors on the
  same held-out approaches, each rendered with its own camera (`pose_errors_by_frame`, `compare_models`).
- The motion checks' calibration (on validation approaches of the mission's kind against the envelope
  validation set): the shipped chain flown clean on the held-out approaches with each (`defended_summary`,
  pipeline.defense.calibration.clean_summary), judged by `calibration_verdict`.
- The black-level clamp: pipeline.pose.robustness.black_level_stats on the held-out frames (`clamp_verdict`).

Intervals are 95% percentile bootstraps over whole trajectories (pipeline/pose/decomposition.py), since the
frames of one approach are correlated.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

NEAR_RANGE_M = (10.0, 30.0)  # the range band of the camera comparison's tz error (reports/camera.md)
METRICS = ("position_m", "attitude_deg", "tz_near_pct")  # the camera comparison's errors, lower is better


def pose_errors_by_frame(
    pred: np.ndarray, target: np.ndarray, trajectory: np.ndarray, near: tuple[float, float] = NEAR_RANGE_M
) -> dict[str, np.ndarray]:
    """Per frame of held-out approaches: position error (m), attitude error (deg), the depth (tz, camera frame)
    error in % of the range on frames within `near` (m; NaN elsewhere) and the trajectory id. `pred`, `target`:
    (N, 9) poses [t (m, camera frame), 6-D rotation]."""
    from pipeline.pose.metrics import pose_errors

    pred, target = np.asarray(pred, np.float64), np.asarray(target, np.float64)
    if pred.shape != target.shape or pred.ndim != 2 or pred.shape[1] != 9 or len(trajectory) != len(pred):
        raise ValueError(
            f"need poses (N, 9) for prediction and target and N trajectory ids, got {pred.shape}, {target.shape} "
            f"and {len(trajectory)}"
        )
    pos, att = pose_errors(pred, target)
    rng = np.linalg.norm(target[:, :3], axis=1)
    inside = (rng >= near[0]) & (rng <= near[1])
    tz = np.where(inside, 100.0 * np.abs(pred[:, 2] - target[:, 2]) / np.maximum(rng, 1e-9), np.nan)
    return {
        "position_m": np.asarray(pos, np.float64),
        "attitude_deg": np.asarray(att, np.float64),
        "tz_near_pct": tz,
        "trajectory": np.asarray(trajectory),
    }


def verdict(difference: Sequence[float]) -> str:
    """Whether a choice holds from (mean, lo, hi) of chosen minus alternative (lower is better): "holds" when the
    interval lies below 0, "reversed" above 0, else "holds (not significant)" or "reversed (not significant)" by
    the sign of the mean."""
    mean, lo, hi = (float(v) for v in difference)
    if hi < 0:
        return "holds"
    if lo > 0:
        return "reversed"
    return "holds (not significant)" if mean <= 0 else "reversed (not significant)"


def compare_models(chosen: dict[str, np.ndarray], alternative: dict[str, np.ndarray]) -> dict[str, Any]:
    """Per error of METRICS: each model's mean with its interval and the chosen minus the alternative, paired by
    trajectory (the same approaches rendered for each), with its `verdict`; the frames that enter each (tz: only
    those within the near band; none there: verdict "no frames", no figures)."""
    from pipeline.pose.decomposition import bootstrap_mean, bootstrap_model_difference

    out: dict[str, Any] = {}
    for key in METRICS:
        a, b = chosen[key], alternative[key]
        ma, mb = np.isfinite(a), np.isfinite(b)
        if not (ma.any() and mb.any()):  # e.g. no frame within the tz band: nothing to compare
            out[key] = {"chosen": None, "alternative": None, "difference": None, "verdict": "no frames", "frames": 0}
            continue
        diff = bootstrap_model_difference(a[ma], chosen["trajectory"][ma], b[mb], alternative["trajectory"][mb])
        out[key] = {
            "chosen": bootstrap_mean(a[ma], chosen["trajectory"][ma]),
            "alternative": bootstrap_mean(b[mb], alternative["trajectory"][mb]),
            "difference": diff,
            "verdict": verdict(diff),
            "frames": int(ma.sum()),
        }
    return out


def defended_summary(
    settings: Any, motion: Any, noise: Any, runs: Sequence[Any], truths: Sequence[np.ndarray], alert: Any
) -> dict[str, Any]:
    """pipeline.defense.calibration.clean_summary of a defense (`settings`, `motion`, `noise`) flown clean over
    `runs` (CleanRuns; their true rel `truths`, world m) against the alert limit `alert` (AlertLimitSettings)."""
    from functools import partial

    from pipeline.defense.calibration import clean_summary, defend_runs
    from pipeline.defense.integrity import alert_limit

    return clean_summary(
        defend_runs(settings, motion, noise, runs, partial(alert_limit, settings=alert)), truths, alert
    )


def calibration_verdict(chosen: dict[str, Any], alternative: dict[str, Any], target: float) -> str:
    """Whether the chosen calibration holds on held-out approaches (`clean_summary`s): it flags at most `target`
    of the clean frames and is at least as available as the alternative ("holds"); "holds (availability within
    the interval)" when it is less available but inside the alternative's interval; else "reversed" (or "misses
    its false-alarm target")."""
    if chosen["fused"].value > target:
        return "misses its false-alarm target"
    a, b = chosen["availability"], alternative["availability"]
    if a.value >= b.value:
        return "holds"
    return "holds (availability within the interval)" if a.value >= b.lo else "reversed"


def clamp_verdict(stats: dict[str, float]) -> str:
    """Whether the clamp threshold still sits above the held-out frames' lab black level (the 99.9th percentile
    of their background under the simulated lab shift): "holds" or "reversed"."""
    return "holds" if stats["threshold"] > stats["lab_black_999"] else "reversed"
