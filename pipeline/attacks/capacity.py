"""Attacker capacity F(eps, range): how far an attack of budget eps moves the pose estimate, per frame
(issue 40), as the overbound the integrity bound (pipeline/defense/bound.py) takes.

Input: per attacked frame the shift of the estimate from the same frame's clean estimate (`measure_shifts`,
camera frame, metres): its component along the true line of sight (LOS = t_true / |t_true|, the range
direction), the norm of its component across it (the two cross axes together: rotation-invariant about
the LOS), and the attitude change (degrees), with the frame's true range. The strongest attack suite
produces them, per eps, on validation frames; this module only summarises them.

Overbound (`fit_capacity`): in range bins, the `quantile` of each shift times (1 + `margin`): a
high quantile rather than the maximum (one outlier frame would set it), widened by a stated margin for
what the sample and the attacks tried did not reach. Frames past the bins' ends are refused, not
extrapolated. `capacity_at` makes F monotone in eps (an attack with a larger budget reaches at least as
far: the elementwise max over every measured eps up to the one used) and takes, for an eps between the
measured ones, the next larger measured eps. As a box per frame [along, across, across] (`Capacity.at`)
the cross term bounds each of the two cross axes separately, a square about the measured disk: the bound
lets the attacker reach up to sqrt(2) further on the diagonals than measured (conservative).
The attitude capacity is recorded for completeness; the position bound does not use it (the attacker it
models leaves the attitude at its clean value).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np


@dataclass(frozen=True, eq=False)
class Shifts:
    """The shifts an attack at `eps` caused on N frames: range_m (N,) true range (m); along (N,) |shift| along
    the true line of sight (m); across (N,) |shift| across it (m); attitude_deg (N,) attitude change (deg)."""

    eps: float
    range_m: np.ndarray
    along: np.ndarray
    across: np.ndarray
    attitude_deg: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.range_m)
        for name in ("range_m", "along", "across", "attitude_deg"):
            v = np.asarray(getattr(self, name), np.float64)
            if v.shape != (n,) or not np.isfinite(v).all() or (v < 0).any():
                raise ValueError(f"shifts: {name} must be ({n},) finite values >= 0, got shape {v.shape}")
            object.__setattr__(self, name, v)
        if not float(self.eps) > 0:
            raise ValueError(f"shifts: eps must be > 0, got {self.eps}")


def measure_shifts(
    eps: float,
    t_true: np.ndarray,
    t_clean: np.ndarray,
    t_attacked: np.ndarray,
    R_clean: np.ndarray | None = None,
    R_attacked: np.ndarray | None = None,
) -> Shifts:
    """`Shifts` of N frames from the true, clean and attacked positions (N, 3) (camera frame, m) and,
    optionally, the clean and attacked attitudes (N, 3, 3) (target -> camera; without them the attitude
    change is 0)."""
    t_true, t_clean, t_attacked = (np.asarray(a, np.float64) for a in (t_true, t_clean, t_attacked))
    n = len(t_true)
    if t_true.shape != (n, 3) or t_clean.shape != (n, 3) or t_attacked.shape != (n, 3):
        raise ValueError(
            f"measure_shifts needs (N, 3) positions, got {t_true.shape}, {t_clean.shape}, {t_attacked.shape}"
        )
    rng = np.linalg.norm(t_true, axis=1)
    if not (rng > 0).all():
        raise ValueError("measure_shifts: a true position at the camera has no line of sight")
    los = t_true / rng[:, None]
    delta = t_attacked - t_clean
    along = np.einsum("ni,ni->n", delta, los)
    across = np.linalg.norm(delta - along[:, None] * los, axis=1)
    att = np.zeros(n)
    if R_clean is not None and R_attacked is not None:
        rel = np.asarray(R_attacked, np.float64) @ np.swapaxes(np.asarray(R_clean, np.float64), 1, 2)
        att = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)))
    return Shifts(float(eps), rng, np.abs(along), across, att)


@dataclass(frozen=True, eq=False)
class Capacity:
    """F at one eps: edges (B + 1,) increasing range bin edges (m); along, across (B,) the overbound of the
    shift along and across the line of sight per bin (m); attitude_deg (B,) (deg); count (B,) frames
    measured per bin; quantile and margin of `fit_capacity` (F = quantile x (1 + margin))."""

    eps: float
    edges: np.ndarray
    along: np.ndarray
    across: np.ndarray
    attitude_deg: np.ndarray
    count: np.ndarray
    quantile: float
    margin: float

    def at(self, range_m: np.ndarray) -> np.ndarray:
        """(N, 3) per frame the box half-widths [along LOS, cross 1, cross 2] (m) at true ranges (N,) (m),
        the bin's values (pipeline/defense/bound.py `worst_case` takes it as `capacity`)."""
        r = np.asarray(range_m, np.float64)
        if r.ndim != 1 or not np.isfinite(r).all() or (r < self.edges[0]).any() or (r > self.edges[-1]).any():
            raise ValueError(
                f"capacity: ranges must lie within the measured bins [{self.edges[0]}, {self.edges[-1]}] m"
            )
        b = np.clip(np.searchsorted(self.edges, r, side="right") - 1, 0, len(self.along) - 1)
        return np.column_stack([self.along[b], self.across[b], self.across[b]])


def fit_capacity(
    shifts: Shifts, edges: Sequence[float], quantile: float = 0.99, margin: float = 0.25, min_count: int = 20
) -> Capacity:
    """F(eps, range) of one eps's `shifts`: per range bin of `edges` (m, increasing) the `quantile` of each
    shift times (1 + `margin`); a bin with fewer than `min_count` frames is refused."""
    edges = np.asarray(edges, np.float64)
    if edges.ndim != 1 or len(edges) < 2 or not np.isfinite(edges).all() or not (np.diff(edges) > 0).all():
        raise ValueError(f"capacity: edges must be >= 2 increasing finite ranges (m), got {edges}")
    if not 0 < quantile <= 1 or not margin >= 0:
        raise ValueError(f"capacity: quantile must be in (0, 1] and margin >= 0, got {quantile} and {margin}")
    inside = (shifts.range_m >= edges[0]) & (shifts.range_m <= edges[-1])
    b = np.clip(np.searchsorted(edges, shifts.range_m, side="right") - 1, 0, len(edges) - 2)
    count = np.bincount(b[inside], minlength=len(edges) - 1)
    if (count < min_count).any():
        k = int(np.argmax(count < min_count))
        raise ValueError(
            f"capacity: range bin {edges[k]:g}-{edges[k + 1]:g} m has {count[k]} frames, fewer than {min_count}"
        )
    q = [
        [np.quantile(getattr(shifts, name)[inside & (b == k)], quantile) * (1 + margin) for k in range(len(edges) - 1)]
        for name in ("along", "across", "attitude_deg")
    ]
    return Capacity(shifts.eps, edges, *(np.array(v) for v in q), count, float(quantile), float(margin))


def capacity_at(capacities: Sequence[Capacity], eps: float, range_m: np.ndarray) -> np.ndarray:
    """(N, 3) F(eps, range) per frame (m, `Capacity.at`) from capacities measured at several eps (the same
    bins): that of the smallest measured eps >= `eps`, made monotone in eps (elementwise max over every
    measured eps up to it); an eps above every measured one is refused."""
    caps = sorted(capacities, key=lambda c: c.eps)
    if not caps or eps > caps[-1].eps:
        raise ValueError(f"capacity: eps {eps} is above every measured eps {[c.eps for c in caps]}")
    if any(not np.array_equal(c.edges, caps[0].edges) for c in caps):
        raise ValueError("capacity: the capacities of different eps must share their range bins")
    upto = next(i for i, c in enumerate(caps) if c.eps >= eps)
    return np.max([c.at(range_m) for c in caps[: upto + 1]], axis=0)


def proportional_capacity(eps: float, edges: Sequence[float], along_per_m: float, across_per_m: float) -> Capacity:
    """A placeholder F growing in proportion to range (no attack measured): per bin along = along_per_m x the
    bin's far edge and across = across_per_m x the far edge (m per m of range), attitude 0; count 0."""
    edges = np.asarray(edges, np.float64)
    if edges.ndim != 1 or len(edges) < 2 or not (np.diff(edges) > 0).all() or min(along_per_m, across_per_m) < 0:
        raise ValueError("capacity: edges must be increasing ranges (m) and the slopes >= 0")
    far = edges[1:]
    return Capacity(
        float(eps), edges, along_per_m * far, across_per_m * far, np.zeros(len(far)), np.zeros(len(far), int), 1.0, 0.0
    )
