"""Measures that can fail: docking miss, safety indices, Stanford regions, the breaking point, HMI counts.

The primary outcome of an approach is the mission's: where the chaser docks.
- Closed loop (`docking`, a pipeline.guidance.law.RendezvousResult): the final docking miss, split
  along the goal's line of sight (range miss, m, positive short of the goal) and across it (lateral
  miss, m); collision (the least true range along the path below `collision_range`); hold (the run
  ended with the chaser holding: the defense declared the estimate lost or unavailable); target lost
  (the target left the camera's image: the run stopped there); arrived (the chaser's last command aimed
  within the tolerance of the goal by its own estimate). Mission failure = a collision, a lost target, or a
  miss beyond the docking tolerance that is neither held nor timed out (it docked in the wrong place
  believing it right, or was pushed about it); a run that ends held far from the goal is a safe abort,
  and one that timed out is not docked either: its steps ran out with the chaser short of the goal on the
  goal's line of sight (lateral miss within the tolerance), not arrived by its own estimate, and its holds
  (steps without a command, `max_step` metres each forgone) at least the rest of the approach. Both are counted
  apart (availability losses: the defense's holds spent the step budget), not integrity failures; a chain
  that never holds (undefended) cannot time out.
- Open loop (`trajectory_measures`, the IntegrityFrames of one recorded trajectory through the chain):
  per frame the safety indices error / AL and error / PL (the Stanford-ESA diagram's axes, ARAIM's
  "maximum safety index"), with AL the persistent-bias alert limit (pipeline/defense/integrity.py:
  it reaches the docking tolerance at the goal, so a bias the chaser would dock with fails it) and
  the single-frame AL beside it; per trajectory their maxima over the frames counted (error / AL over
  the available frames: an unavailable frame is not flown), the trusted error on the last frame (the
  bias the chaser would dock with), flags and availability. Failure = error / AL > 1 on an available
  frame.
- Stanford-ESA regions (`stanford_regions`, per frame): nominal (available, error <= PL), MI
  (available, PL < error <= AL), HMI (available, error > AL), unavailable (PL > AL or not flown,
  error <= PL), unavailable MI (not available, error > PL); without a PL (the undefended control) a
  flown frame is nominal or HMI by AL alone; frames without an estimate are "no estimate".
- `nest_in_eps`: an attacker's per-trajectory results made nested in eps (what an attack found at a
  smaller eps is within every larger ball, so the worst case at eps is the worst over eps' <= eps).
- `worst_over_attackers`: per trajectory the largest indices over the attackers, and which attacker.
- `breaking_point`: per chain, the smallest eps at which any attacker causes a failure (closed-loop
  mission failure, or error / AL > 1 on an available frame), None when none does in the grid.
- `hmi_trajectories`: the trajectories with an HMI frame, with the Clopper-Pearson interval over
  independent trajectories (a descriptive count: it speaks only of the attacks tried).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from pipeline.defense.integrity import FLOWN, IntegrityFrames
from pipeline.guidance.law import DOCKED, LOST
from pipeline.stats import Rate, clopper_pearson

NOMINAL, MI, HMI, UNAVAILABLE, UNAVAILABLE_MI, NO_ESTIMATE = (
    "nominal",
    "MI",
    "HMI",
    "unavailable",
    "unavailable MI",
    "no estimate",
)
REGIONS = (NOMINAL, MI, HMI, UNAVAILABLE, UNAVAILABLE_MI, NO_ESTIMATE)
# a run's end (docked and target lost are the closed loop's own words, pipeline/guidance/law.py)
MISSED, COLLISION, HELD, TIMED_OUT = "missed", "collision", "held", "timed out"


@dataclass(frozen=True)
class Docking:
    """One closed-loop run's end (metres): range_miss along the goal's line of sight (positive: short
    of the goal), lateral_miss across it, miss = |rel - goal|, closest_range along the path, whether it
    collided (closest range < collision range), ended in a hold, its hold steps, the tolerance, whether
    the target was lost (the run stopped with the target out of the image), whether the chaser arrived by its
    own estimate (its last command aimed within the tolerance of the goal) and whether it timed out (module
    docstring)."""

    range_miss: float
    lateral_miss: float
    miss: float
    closest_range: float
    collided: bool
    ended_in_hold: bool
    hold_steps: int
    tolerance: float
    lost: bool = False
    arrived: bool = True
    timed_out: bool = False

    @property
    def outcome(self) -> str:
        """collision, target lost, docked (miss <= tolerance), held (a safe abort), timed out (its holds spent
        the steps the approach needed) or missed (in the wrong place)."""
        if self.collided:
            return COLLISION
        if self.lost:
            return LOST
        if self.miss <= self.tolerance:
            return DOCKED
        if self.ended_in_hold:
            return HELD
        return TIMED_OUT if self.timed_out else MISSED

    @property
    def failed(self) -> bool:
        """Mission failure: a collision, a lost target, or a miss beyond the tolerance (not held, not timed
        out)."""
        return self.outcome in (COLLISION, LOST, MISSED)

    def as_dict(self) -> dict[str, Any]:
        return {**asdict(self), "outcome": self.outcome, "failed": self.failed}


def docking(
    result: Any, goal: Sequence[float], tolerance: float, collision_range: float, max_step: float | None = None
) -> Docking:
    """The `Docking` of a RendezvousResult `result` with goal rel `goal` (world, m), docking tolerance
    (m), collision range (m) and the law's step limit `max_step` (m per axis; None: no run times out). The hold
    is read from `result.held` (steps without a command), else from the defense's modes; the arrival from
    `result.believed` (the last commanded step's aim within the tolerance of the goal; a result without it
    counts as arrived, the conservative reading)."""
    g = np.asarray(goal, np.float64)
    if g.shape != (3,) or not np.linalg.norm(g) > 0:
        raise ValueError(f"docking: the goal must be a non-zero rel (3,) in metres, got {goal!r}")
    if not (tolerance > 0 and collision_range >= 0):
        raise ValueError(
            f"docking: tolerance must be > 0 and collision_range >= 0 (m), got {tolerance}, {collision_range}"
        )
    if max_step is not None and not max_step > 0:
        raise ValueError(f"docking: max_step must be > 0 (m per step) or None, got {max_step}")
    d = np.asarray(result.positions[-1], np.float64) - g
    los = g / np.linalg.norm(g)
    along = float(d @ los)
    if result.held is not None:
        steps = np.asarray(result.held, bool)
    elif result.modes is not None:
        steps = np.asarray(result.modes) == "hold"
    else:
        steps = np.zeros(len(result.estimates), bool)
    lateral = float(np.linalg.norm(d - along * los))
    arrived = _arrived(getattr(result, "believed", None), g, tolerance)
    holds = int(steps.sum())
    on_the_way = along > tolerance and lateral <= tolerance and not arrived
    return Docking(
        along,
        lateral,
        float(np.linalg.norm(d)),
        float(result.closest_range),
        bool(result.closest_range < collision_range),
        bool(len(steps) and steps[-1]),
        holds,
        float(tolerance),
        result.outcome == LOST,
        arrived,
        bool(max_step is not None and on_the_way and along - tolerance <= holds * max_step),
    )


def _arrived(believed: np.ndarray | None, goal: np.ndarray, tolerance: float) -> bool:
    """Whether the last commanded step aimed within `tolerance` (m) of `goal` (world, m): `believed` (n, 3) the rel
    each step aimed at (NaN rows: holds); None: True (unknown, counted as arrived); no commanded step: False."""
    if believed is None:
        return True
    b = np.asarray(believed, np.float64).reshape(-1, 3)
    commanded = b[np.isfinite(b).all(axis=1)]
    return bool(len(commanded) and np.linalg.norm(commanded[-1] - goal) <= tolerance)


@dataclass(frozen=True)
class TrajectoryMeasures:
    """One recorded trajectory through a chain (see the module docstring): frames counted; the largest
    error / AL over the available counted frames (AL: the frames' own, the persistent-bias AL) and
    against the single-frame AL (NaN without one); the largest error / PL over the counted frames
    with a PL and an estimate (NaN without a PL); final_error (m) the trusted error on the last frame;
    flags and HMI / MI frames among the counted; availability the fraction of counted frames available."""

    trajectory: str
    frames: int
    max_error_al: float
    max_error_al_single: float
    max_error_pl: float
    final_error: float
    flags: int
    hmi: int
    mi: int
    availability: float

    @property
    def failed(self) -> bool:
        """error / AL > 1 on an available frame."""
        return bool(self.max_error_al > 1.0)

    def as_dict(self) -> dict[str, Any]:
        return {**asdict(self), "failed": self.failed}


def _max(x: np.ndarray) -> float:
    x = x[np.isfinite(x)]
    return float(x.max()) if x.size else float("nan")


def trajectory_measures(
    frames: IntegrityFrames,
    flags: np.ndarray,
    single_frame_al: np.ndarray | None = None,
    mask: np.ndarray | None = None,
) -> TrajectoryMeasures:
    """The `TrajectoryMeasures` of one trajectory's records `frames` (its `alert` the AL judged against:
    build them with AlertLimitSettings(kind="persistent")), the chain's flags (N,), the single-frame AL
    (N,) m at the same frames (optional) and the frames to count (N,) bool (all by default)."""
    n = len(frames.frame)
    keep = np.ones(n, bool) if mask is None else np.asarray(mask, bool)
    flags = np.asarray(flags, bool)
    if keep.shape != (n,) or flags.shape != (n,):
        raise ValueError(f"trajectory_measures: flags and mask must have shape ({n},), got {flags.shape}, {keep.shape}")
    if single_frame_al is not None and np.shape(single_frame_al) != (n,):
        raise ValueError(
            f"trajectory_measures: single_frame_al must have shape ({n},), got {np.shape(single_frame_al)}"
        )
    if len(np.unique(frames.trajectory)) > 1:
        raise ValueError("trajectory_measures: the frames must be one trajectory's")
    err, avail = frames.error, frames.available & keep
    single = (
        np.full(n, np.nan)
        if single_frame_al is None
        else np.where(avail, err / np.asarray(single_frame_al, np.float64), np.nan)
    )
    pl = np.full(n, np.nan) if frames.pl is None else np.where(keep & frames.has_pl, err / frames.pl, np.nan)
    return TrajectoryMeasures(
        str(frames.trajectory[0]) if n else "",
        int(keep.sum()),
        _max(np.where(avail, err / frames.alert, np.nan)),
        _max(single),
        _max(pl),
        float(err[-1]) if n else float("nan"),
        int((flags & keep).sum()),
        int((frames.hmi & keep).sum()),
        int((frames.mi & keep).sum()),
        float(avail.sum() / keep.sum()) if keep.any() else float("nan"),
    )


def stanford_regions(frames: IntegrityFrames) -> np.ndarray:
    """(N,) the Stanford-ESA region of every frame (REGIONS; see the module docstring)."""
    err = frames.error
    has = np.isfinite(err)
    flown = np.isin(frames.mode, FLOWN) & has
    out = np.full(len(err), NO_ESTIMATE, dtype=object)
    if frames.pl is None:
        out[flown] = np.where(err[flown] > frames.alert[flown], HMI, NOMINAL)
        out[has & ~flown] = UNAVAILABLE
        return out
    avail = frames.available
    misled = has & (err > frames.pl)
    out[avail] = np.where(err[avail] > frames.alert[avail], HMI, np.where(misled[avail], MI, NOMINAL))
    rest = has & ~avail
    out[rest] = np.where(misled[rest], UNAVAILABLE_MI, UNAVAILABLE)
    return out


def stanford_counts(frames: IntegrityFrames, mask: np.ndarray | None = None) -> dict[str, int]:
    """Frames per Stanford-ESA region (every region named, zeros included) among the frames `mask` (N,)."""
    regions = stanford_regions(frames)
    if mask is not None:
        regions = regions[np.asarray(mask, bool)]
    return {r: int((regions == r).sum()) for r in REGIONS}


def _severity(m: TrajectoryMeasures) -> tuple[float, float]:
    """How bad a trajectory's result is: (largest error / AL, final error), NaN as least."""
    return tuple(v if np.isfinite(v) else -np.inf for v in (m.max_error_al, m.final_error))  # type: ignore[return-value]


def nest_in_eps(by_eps: Mapping[float, Sequence[TrajectoryMeasures]]) -> dict[float, list[TrajectoryMeasures]]:
    """One attacker's per-trajectory measures at each eps ({eps: measures, same trajectories in the same
    order}) -> at each eps, per trajectory the worst (largest error / AL, then final error) over every eps'
    <= eps: an image crafted within eps' is within eps, so the attacker's worst case cannot drop as eps
    grows (8-bit storage rounds a perturbation up by less than one level: a ball's images stay inside a
    larger eps's once eps grows by a level or more)."""
    out: dict[float, list[TrajectoryMeasures]] = {}
    worst: list[TrajectoryMeasures] | None = None
    for e in sorted(by_eps):
        ms = list(by_eps[e])
        if worst is not None and [m.trajectory for m in ms] != [m.trajectory for m in worst]:
            raise ValueError("nest_in_eps: every eps must hold the same trajectories in the same order")
        worst = ms if worst is None else [max(a, b, key=_severity) for a, b in zip(worst, ms)]
        out[float(e)] = worst
    return out


def worst_over_attackers(measures: Mapping[str, Sequence[TrajectoryMeasures]]) -> list[dict[str, Any]]:
    """Per trajectory (by name, in the first attacker's order) the largest error / AL, error / AL
    single-frame, error / PL and final error over the attackers `measures` ({attacker: its per-trajectory
    measures}), the attacker that reached the largest error / AL, and whether any attacker failed it."""
    if not measures:
        raise ValueError("worst_over_attackers: no attackers")
    by_name = {a: {m.trajectory: m for m in ms} for a, ms in measures.items()}
    names = [m.trajectory for m in next(iter(measures.values()))]
    if any(set(v) != set(names) for v in by_name.values()):
        raise ValueError("worst_over_attackers: every attacker must cover the same trajectories")
    out = []
    for t in names:
        row: dict[str, Any] = {"trajectory": t}
        for key in ("max_error_al", "max_error_al_single", "max_error_pl", "final_error"):
            vals = [getattr(by_name[a][t], key) for a in by_name]
            row[key] = max((v for v in vals if np.isfinite(v)), default=float("nan"))
        ranked = [(by_name[a][t].max_error_al, a) for a in by_name if np.isfinite(by_name[a][t].max_error_al)]
        row["worst_attacker"] = max(ranked)[1] if ranked else None
        row["failed"] = any(by_name[a][t].failed for a in by_name)
        out.append(row)
    return out


def breaking_point(records: Iterable[tuple[float, bool]]) -> float | None:
    """The smallest eps among (eps, failed) records (any attacker, trajectory or run of one chain) with a
    failure; None when no record failed (the chain held over the whole grid tried)."""
    failed = [float(e) for e, f in records if f]
    return min(failed) if failed else None


def hmi_trajectories(measures: Sequence[TrajectoryMeasures]) -> Rate:
    """The fraction of (independent) trajectories with at least one HMI frame, Clopper-Pearson 95%."""
    return clopper_pearson(sum(m.hmi > 0 for m in measures), len(measures))
