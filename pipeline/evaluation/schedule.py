"""Per-frame attack schedule and per-frame detection metrics for the integrated evaluation.

Schedule: walking the frames in order, a frame that is not already inside an attack starts one
with probability `p_start`; an attack then covers exactly `length` consecutive frames (a burst is
cut short only by the end of the sequence). Once a burst ends, the very next frame may start a new
one, so bursts can touch but never overlap.

Metrics count frames, as the paper does: accuracy = frames classified correctly / all frames,
where a frame is correct when its flag equals its attacked state. TPR = flagged attacked frames /
attacked frames, FPR = flagged clean frames / clean frames. The detection delay of a burst is the
number of frames from its first frame to its first flagged frame (0 = flagged at once); bursts
with no flag at all are counted as missed and have no delay.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np


def attack_schedule(n_frames: int, p_start: float, length: int, seed: int) -> np.ndarray:
    """(n_frames,) bool mask of attacked frames; seeded, bursts of exactly `length` frames."""
    if n_frames < 0:
        raise ValueError(f"n_frames must be >= 0, got {n_frames}")
    if not 0.0 <= p_start <= 1.0:
        raise ValueError(f"p_start must be a probability in [0, 1], got {p_start}")
    if length < 1:
        raise ValueError(f"attack length must be >= 1 frame, got {length}")
    draws = np.random.default_rng(seed).random(n_frames)
    attacked = np.zeros(n_frames, dtype=bool)
    i = 0
    while i < n_frames:
        if draws[i] < p_start:
            attacked[i:i + length] = True
            i += length
        else:
            i += 1
    return attacked


def bursts(mask: np.ndarray) -> list[tuple[int, int]]:
    """Runs of True in a 1-D bool mask as (start, stop) frame indices, stop exclusive."""
    m = np.asarray(mask, dtype=bool).astype(np.int8)
    edges = np.diff(np.concatenate([[0], m, [0]]))
    return list(zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist()))


def schedule_bursts(attacked: np.ndarray, length: int) -> list[tuple[int, int]]:
    """The bursts of a schedule, splitting touching bursts into their `length`-frame attacks."""
    out: list[tuple[int, int]] = []
    for start, stop in bursts(attacked):
        out += [(s, min(s + length, stop)) for s in range(start, stop, length)]
    return out


def detection_delays(attacked_bursts: list[tuple[int, int]], flagged: np.ndarray) -> np.ndarray:
    """Per burst: frames from its start to its first flag, NaN when no frame of it was flagged."""
    flagged = np.asarray(flagged, dtype=bool)
    delays = np.full(len(attacked_bursts), np.nan)
    for k, (start, stop) in enumerate(attacked_bursts):
        hits = np.flatnonzero(flagged[start:stop])
        if len(hits):
            delays[k] = hits[0]
    return delays


@dataclass(frozen=True)
class DetectionMetrics:
    """Frame-level detection figures for one sequence (rates in [0, 1]; NaN when undefined)."""

    frames: int
    attacked: int
    flagged: int
    accuracy: float
    tpr: float
    fpr: float
    bursts: int
    missed_bursts: int
    mean_delay: float            # frames, over bursts that were flagged at least once

    def as_dict(self) -> dict[str, float | int]:
        return asdict(self)


def _rate(num: int, den: int) -> float:
    return float(num) / den if den else float("nan")


def detection_metrics(attacked: np.ndarray, flagged: np.ndarray,
                      attacked_bursts: list[tuple[int, int]] | None = None) -> DetectionMetrics:
    """Accuracy (correct flags / all frames), TPR, FPR and burst delays of one flag sequence.

    `attacked_bursts` defaults to the runs of `attacked`; pass `schedule_bursts(...)` to count
    touching bursts separately.
    """
    attacked = np.asarray(attacked, dtype=bool)
    flagged = np.asarray(flagged, dtype=bool)
    if attacked.shape != flagged.shape or attacked.ndim != 1:
        raise ValueError(f"attacked {attacked.shape} and flagged {flagged.shape} must be equal 1-D shapes")
    n = len(attacked)
    tp = int(np.sum(attacked & flagged))
    fp = int(np.sum(~attacked & flagged))
    tn = int(np.sum(~attacked & ~flagged))
    b = bursts(attacked) if attacked_bursts is None else attacked_bursts
    delays = detection_delays(b, flagged)
    hit = delays[~np.isnan(delays)]
    return DetectionMetrics(
        frames=n, attacked=int(attacked.sum()), flagged=int(flagged.sum()),
        accuracy=_rate(tp + tn, n), tpr=_rate(tp, int(attacked.sum())), fpr=_rate(fp, int((~attacked).sum())),
        bursts=len(b), missed_bursts=int(np.isnan(delays).sum()),
        mean_delay=float(hit.mean()) if len(hit) else float("nan"),
    )


def undetected_mask(attacked: np.ndarray, flagged: np.ndarray) -> np.ndarray:
    """Attacked frames the detector did not flag (the ones whose bad pose reaches guidance)."""
    return np.asarray(attacked, dtype=bool) & ~np.asarray(flagged, dtype=bool)


def mean_over(values: np.ndarray, mask: np.ndarray) -> float:
    """Mean of `values` where `mask` holds (e.g. pose error on undetected attacked frames); NaN if none."""
    values, mask = np.asarray(values, dtype=np.float64), np.asarray(mask, dtype=bool)
    return float(values[mask].mean()) if mask.any() else float("nan")
