"""Per-frame attack schedule for the integrated evaluation (its frame-level detection metrics:
pipeline/detectors/metrics.py, `frame_metrics`).

Schedule: walking the frames in order, a frame that is not already inside an attack starts one
with probability `p_start`; an attack then covers exactly `length` consecutive frames (a burst is
cut short only by the end of the sequence). Once a burst ends, the very next frame may start a new
one, so bursts can touch but never overlap.
"""

from __future__ import annotations

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
            attacked[i : i + length] = True
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


def attacked_fraction(p_start: float, length: int) -> float:
    """The long-run fraction of frames `attack_schedule(n, p_start, length, seed)` attacks, as n grows.

    Between bursts the schedule draws clean frames until one starts an attack: (1 - p_start) / p_start of
    them on average (a geometric count), then `length` attacked frames, so the fraction is
    length / (length + (1 - p_start) / p_start) = length p / (length p + 1 - p). The paper's integrated
    evaluation (p = 0.2, 5-frame attacks) attacks 5/9 = 55.6% of its frames; its lab one (10-frame
    attacks) 10/14 = 71.4%. Finite sequences attack slightly less: a burst is cut short at the end.
    """
    if not 0.0 < p_start <= 1.0:
        raise ValueError(f"p_start must be a probability in (0, 1], got {p_start}")
    if length < 1:
        raise ValueError(f"attack length must be >= 1 frame, got {length}")
    return length * p_start / (length * p_start + 1.0 - p_start)
