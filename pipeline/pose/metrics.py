"""Pose metrics: per-sample position and attitude errors, the ESA SPEED score, error summaries.

Errors: position ||t_pred - t_gt|| in metres, attitude 2*acos(|<q_pred, q_gt>|) in degrees, with
(N, 9) outputs (t in metres, camera frame, then the 6-D rotation decoded by Gram-Schmidt). The SPEED
score is mean(||t_pred - t_gt|| / ||t_gt||) + mean(attitude error in radians): dimensionless, so a
1% range error weighs as much as 0.01 rad (0.57 deg) of attitude.

The attitude error splits (swing-twist) about the true line of sight u = t_gt / ||t_gt|| (camera frame)
into tilt, out of the image plane (the angle by which the error rotation moves u: what changes the
target's silhouette only through foreshortening) and roll, in the image plane (the error rotation's
twist about u: a rotation of the silhouette). Neither exceeds the total attitude error.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from pipeline.geometry.rotations import matrix_to_quat, normalize_quat, sixd_to_matrix, sixd_to_quat
from pipeline.render.backgrounds import KINDS, background_kinds
from pipeline.stats import mean_interval


def position_error(t_pred: np.ndarray, t_gt: np.ndarray) -> np.ndarray:
    """Euclidean position error ||t_pred - t_gt|| in metres, per sample."""
    return np.linalg.norm(np.asarray(t_pred, float) - np.asarray(t_gt, float), axis=-1)


def attitude_error_deg(q_pred: np.ndarray, q_gt: np.ndarray) -> np.ndarray:
    """Attitude error 2*acos(|<q_pred, q_gt>|) in degrees, per sample."""
    d = np.abs(np.sum(normalize_quat(q_pred) * normalize_quat(q_gt), -1))
    return np.rad2deg(2 * np.arccos(np.clip(d, 0.0, 1.0)))


def pose_errors(pred: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 9) predictions and targets -> position error (m) and attitude error (deg), per sample."""
    pred, target = np.asarray(pred, np.float64), np.asarray(target, np.float64)
    return (
        position_error(pred[:, :3], target[:, :3]),
        attitude_error_deg(sixd_to_quat(pred[:, 3:]), sixd_to_quat(target[:, 3:])),
    )


def tilt_roll_deg(pred: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, 9) predictions and targets -> tilt (out of plane) and roll (in plane) attitude errors in
    degrees, per sample (the swing-twist split about the true line of sight; module doc)."""
    pred, target = np.asarray(pred, np.float64), np.asarray(target, np.float64)
    r_err = sixd_to_matrix(pred[:, 3:]) @ np.swapaxes(sixd_to_matrix(target[:, 3:]), -1, -2)
    u = target[:, :3] / np.linalg.norm(target[:, :3], axis=1, keepdims=True)
    moved = np.einsum("nij,nj->ni", r_err, u)
    tilt = np.rad2deg(np.arccos(np.clip(np.sum(u * moved, 1), -1.0, 1.0)))
    q = matrix_to_quat(r_err)
    roll = np.rad2deg(2 * np.arctan2(np.abs(np.sum(q[:, 1:] * u, 1)), q[:, 0]))
    return tilt, roll


def speed_score(pred: np.ndarray, target: np.ndarray) -> float:
    """ESA SPEED score: mean relative position error + mean attitude error in radians."""
    pos, att = pose_errors(pred, target)
    return float(np.mean(pos / np.linalg.norm(target[:, :3], axis=1)) + np.mean(np.deg2rad(att)))


def summarize_errors(pred: np.ndarray, target: np.ndarray, ranges: np.ndarray, bins: Sequence[float]) -> dict[str, Any]:
    """Error statistics of (N, 9) predictions: position (m) and attitude (deg) mean/median, mean tilt and
    roll (deg, `tilt_roll_deg`), the SPEED score (`speed_score`), mean |tz| error as % of range, mean lateral
    error sqrt(dx^2 + dy^2) (m) at ranges 10-30 m, and the same (but the score) per range bin (`bins`: edges in
    metres, any order; a bin is (low, high], the lowest edge included; ranges outside the edges get their own
    open bins)."""
    pos, att = pose_errors(pred, target)
    tilt, roll = tilt_roll_deg(pred, target)
    pred, target, ranges = np.asarray(pred, np.float64), np.asarray(target, np.float64), np.asarray(ranges, np.float64)
    tz_pct = 100 * np.abs(pred[:, 2] - target[:, 2]) / ranges
    lateral = np.linalg.norm(pred[:, :2] - target[:, :2], axis=1)
    near = (ranges >= 10) & (ranges <= 30)

    def stats(m: np.ndarray) -> dict[str, float]:
        if not m.any():
            return {"n": 0}
        return {
            "n": int(m.sum()),
            "pos_mean_m": float(pos[m].mean()),
            "pos_median_m": float(np.median(pos[m])),
            "att_mean_deg": float(att[m].mean()),
            "att_median_deg": float(np.median(att[m])),
            "tilt_mean_deg": float(tilt[m].mean()),
            "roll_mean_deg": float(roll[m].mean()),
            "tz_pct_range": float(tz_pct[m].mean()),
            "lateral_m": float(lateral[m].mean()),
        }

    edges = sorted(float(b) for b in bins)
    per_bin = []
    if (ranges < edges[0]).any():
        per_bin.append({"range_m": f"<{edges[0]:g}", **stats(ranges < edges[0])})
    for i, (lo, hi) in enumerate(zip(edges[:-1], edges[1:])):
        m = (ranges > lo) & (ranges <= hi) if i else (ranges >= lo) & (ranges <= hi)
        per_bin.append({"range_m": f"{hi:g}-{lo:g}", **stats(m)})
    if (ranges > edges[-1]).any():  # range = ||t||: lateral offsets put the start beyond the last edge
        per_bin.append({"range_m": f">{edges[-1]:g}", **stats(ranges > edges[-1])})
    out = stats(np.ones(len(pos), bool))
    out["speed_score"] = speed_score(pred, target)
    out["lateral_10_30_m"] = float(lateral[near].mean()) if near.any() else float("nan")
    out["tz_pct_10_30"] = float(tz_pct[near].mean()) if near.any() else float("nan")
    out["bins"] = per_bin[::-1]
    return out


def errors_by_background(pred: np.ndarray, target: np.ndarray, backgrounds: Sequence[str] | None) -> dict[str, Any]:
    """Per background kind present (pipeline/render/backgrounds.py KINDS order; `backgrounds` (N,) each frame's
    kind, None = every frame black) of (N, 9) predictions: {n, pos_m, pos_ci, att_deg, att_ci}, the mean position
    (m) and attitude (deg) errors with their 95% intervals (pipeline.stats.mean_interval, floor 0)."""
    pos, att = pose_errors(pred, target)
    kinds = background_kinds(backgrounds, len(pos))
    out: dict[str, Any] = {}
    for kind in (k for k in KINDS if (kinds == k).any()):
        (p, *p_ci), (a, *a_ci) = (mean_interval(e[kinds == kind], floor=0.0) for e in (pos, att))
        out[kind] = {"n": int((kinds == kind).sum()), "pos_m": p, "pos_ci": p_ci, "att_deg": a, "att_ci": a_ci}
    return out
