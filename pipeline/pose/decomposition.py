"""Pose errors split by a grouping of the frames (issue 38's attitude decomposition): e.g. the training set's
sequences with a fixed target attitude against those whose attitude is drawn afresh every frame
(`pipeline.geometry.trajectories.attitude_groups`).

Frames of one sequence are correlated (neighbouring frames look alike), so every mean comes with a 95% percentile
bootstrap interval over the sequences: sequences are resampled whole (within their group), and the statistic is the
pooled mean over the resampled sequences' frames. With the 5 fixed and 8 rotating sequences of the training set the
intervals are coarse, as they should be.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from pipeline.pose.metrics import pose_errors, tilt_roll_deg

LEVEL = 0.95


def _per_sequence(values: np.ndarray, sequence: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(sum of values, frame count) per sequence, in the order of np.unique(sequence)."""
    ids, inverse = np.unique(sequence, return_inverse=True)
    return np.bincount(inverse, weights=values, minlength=len(ids)), np.bincount(inverse, minlength=len(ids))


def _draw(sums: np.ndarray, counts: np.ndarray, rng: np.random.Generator, n_resamples: int) -> np.ndarray:
    """Pooled means of `n_resamples` resamples of the sequences (with replacement)."""
    idx = rng.integers(0, len(sums), size=(n_resamples, len(sums)))
    return sums[idx].sum(axis=1) / counts[idx].sum(axis=1)


def bootstrap_mean(
    values: np.ndarray, sequence: np.ndarray, n_resamples: int = 2000, seed: int = 0
) -> tuple[float, float, float]:
    """(mean, lo, hi): the mean of per-frame `values` and its 95% percentile bootstrap interval over the sequences
    (`sequence`: an id per frame). With one sequence the interval is the mean itself (nothing to resample)."""
    values, sequence = np.asarray(values, np.float64).ravel(), np.asarray(sequence).ravel()
    if values.shape != sequence.shape or values.size == 0:
        raise ValueError(f"need as many sequence ids as values (> 0), got {sequence.shape} and {values.shape}")
    sums, counts = _per_sequence(values, sequence)
    boot = _draw(sums, counts, np.random.default_rng(seed), n_resamples)
    lo, hi = np.percentile(boot, [50 * (1 - LEVEL), 50 * (1 + LEVEL)])
    return float(values.mean()), float(lo), float(hi)


def bootstrap_difference(
    values: np.ndarray, sequence: np.ndarray, in_a: np.ndarray, n_resamples: int = 2000, seed: int = 0
) -> tuple[float, float, float]:
    """(difference, lo, hi): mean of `values` over the frames `in_a` minus the mean over the others, with the 95%
    percentile bootstrap interval that resamples each side's sequences independently (a sequence lies on one side)."""
    values, sequence, in_a = (
        np.asarray(values, np.float64).ravel(),
        np.asarray(sequence).ravel(),
        np.asarray(in_a, bool).ravel(),
    )
    if len(np.intersect1d(sequence[in_a], sequence[~in_a])):
        raise ValueError("a sequence lies on both sides of the difference")
    if in_a.all() or not in_a.any():
        raise ValueError("the difference needs frames on both sides")
    rng = np.random.default_rng(seed)
    a, b = (_draw(*_per_sequence(values[m], sequence[m]), rng, n_resamples) for m in (in_a, ~in_a))
    lo, hi = np.percentile(a - b, [50 * (1 - LEVEL), 50 * (1 + LEVEL)])
    return float(values[in_a].mean() - values[~in_a].mean()), float(lo), float(hi)


def bootstrap_model_difference(
    a: np.ndarray, a_sequence: np.ndarray, b: np.ndarray, b_sequence: np.ndarray, n_resamples: int = 2000, seed: int = 0
) -> tuple[float, float, float]:
    """(difference, lo, hi): the mean of per-frame values `a` minus the mean of `b`, two models' errors on the
    same sequences (their frames may differ, e.g. two renders of one approach), with the 95% percentile bootstrap
    interval that draws the sequences once per resample for both sides (paired by sequence: what the sequences
    share cancels). Raises ValueError when the two sides do not hold the same sequence ids."""
    return bootstrap_contrast([(a, a_sequence), (b, b_sequence)], [1.0, -1.0], n_resamples, seed)


def bootstrap_contrast(
    sides: Sequence[tuple[np.ndarray, np.ndarray]], weights: Sequence[float], n_resamples: int = 2000, seed: int = 0
) -> tuple[float, float, float]:
    """(contrast, lo, hi): sum_i weights[i] x the mean of side i's per-frame values, each side (values, sequence ids)
    one model's errors on the same sequences (e.g. a - b, or the interaction ab - a - b + s of two changes made alone
    and together), with the 95% percentile bootstrap interval that draws the sequences once per resample for every
    side (paired by sequence). Raises ValueError when the sides do not all hold the same sequence ids."""
    if len(sides) != len(weights) or not sides:
        raise ValueError(f"need one weight per side (> 0 sides), got {len(weights)} weights for {len(sides)} sides")
    flat = [(np.asarray(v, np.float64).ravel(), np.asarray(q).ravel()) for v, q in sides]
    if any(v.shape != q.shape or not v.size for v, q in flat):
        raise ValueError("need one sequence id per value on each side (> 0 values)")
    ids = np.unique(flat[0][1])
    if any(not np.array_equal(ids, np.unique(q)) for _, q in flat):
        raise ValueError("every side must hold the same sequences")
    idx = np.random.default_rng(seed).integers(0, len(ids), size=(n_resamples, len(ids)))
    value, boot = 0.0, 0.0
    for w, (v, q) in zip(weights, flat):
        sums, counts = _per_sequence(v, q)
        value = value + float(w) * v.mean()
        boot = boot + float(w) * (sums[idx].sum(axis=1) / counts[idx].sum(axis=1))
    lo, hi = np.percentile(boot, [50 * (1 - LEVEL), 50 * (1 + LEVEL)])
    return float(value), float(lo), float(hi)


def group_errors(
    pred: np.ndarray, target: np.ndarray, sequence: np.ndarray, group: np.ndarray
) -> dict[str, dict[str, object]]:
    """Per group (`group`: a label per frame, e.g. `attitude_groups(sequence)`): frames, sequences, and the mean
    position (m), attitude, tilt and roll (deg) errors of (N, 9) predictions against targets (m, 6-D), each as
    (mean, lo, hi) with the bootstrap over the group's sequences (`bootstrap_mean`)."""
    pos, att = pose_errors(pred, target)
    tilt, roll = tilt_roll_deg(pred, target)
    sequence, group = np.asarray(sequence), np.asarray(group)
    out: dict[str, dict[str, object]] = {}
    for g in np.unique(group):
        m = group == g
        out[str(g)] = {
            "frames": int(m.sum()),
            "sequences": int(len(np.unique(sequence[m]))),
            **{
                k: bootstrap_mean(v[m], sequence[m])
                for k, v in (("position_m", pos), ("attitude_deg", att), ("tilt_deg", tilt), ("roll_deg", roll))
            },
        }
    return out
