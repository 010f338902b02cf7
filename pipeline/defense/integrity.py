"""Integrity of the trusted estimate the guidance flies on: alert limit, HMI, MI, availability.

The vocabulary is that of satellite-navigation integrity monitoring (RAIM/ARAIM), per frame:
- trusted estimate: the defense's trusted `rel` (pipeline/defense/fusion.py: the motion filter's state,
  its prediction on flagged frames): the target's position relative to the chaser, world frame,
  metres; NaN before the filter starts. Its error is the distance (m) to the true `rel`.
- alert limit AL(range) (m): the largest trusted-estimate error the guidance law and the docking
  tolerance absorb at that true range (`alert_limit`, derived below).
- protection level PL (m, optional): the chain's own bound on its error (pipeline/defense/protection.py;
  `DefenseTrace.pl`).
- available: the guidance flies on the trusted estimate (defense mode track or coast, not hold: in
  the "recover" guidance a coasting prediction is flown too) and, where PL is given, PL <= AL.
- HMI (hazardously misleading information): available and error > AL.
- MI (misleading information): error > PL, only on frames that have a PL.
- availability: the fraction of frames that are available (of clean runs: the cost of the defense).
- attack harm: an attacked run is compared frame by frame with the same frames of its clean
  counterpart; a frame counts as the attack's HMI (MI) only when it is not HMI (MI) without the attack.
Rates carry 95% intervals by a bootstrap over trajectories (pipeline/stats.py).

Derivation of AL (pipeline/guidance/law.py, SPEC section 5, variant "paper"). Per axis, with step
limit s (m per step), goal g (`rel` (0, 0, r_g)) and docking tolerance tol (m):
    cmd = clip(est - g, -s, s);  rel_next = est - cmd.
Assumptions: (a) the chaser is on the nominal approach along the line of sight at true range r,
(b) the run's step budget is the nominal approach's remaining ceil((r - r_g) / s) steps plus the
closed loop's `slack_steps` (the guidance stage gives attacked runs the clean run's arrival step +
guidance.slack_steps), (c) one frame's estimate is wrong by E (m, any direction) and every other
estimate is exact, (d) a true range below `collision_range` (m) is a collision (r_g above it).
Because rel_next is computed from the estimate, the error becomes a displacement of the chaser (less
what that step's clipped command takes back); exact frames then close each axis's offset by s per
step. Three directions bound E:
- outward along the line of sight (estimate farther than the truth): the approach already spends
  every step on that axis, so the displacement must fit in the slack: when the budget ends the
  chaser is E - slack s short of the goal, and docks iff E - slack s <= tol:  E <= tol + slack s;
- inward (estimate nearer than the truth): only an estimate beyond the goal, est_z <= r_g - s, sends
  the chaser inside the goal range, to est_z + s = r - E + s (from there the budget brings it back
  out); no collision iff r - E + s >= collision_range:  E <= r + s - collision_range;
- lateral: those axes have the whole budget (>= slack steps) to close an offset, never tighter than
  the outward bound (and the residuals' norm is largest with the error on one axis).
AL is the tightest bound, floored at the docking tolerance (an error the mission accepts anyway):
    AL(r) = max(tol, min(tol + slack s, r + s - collision_range)).
With the defaults (tol 1 m, s 1 m, slack 10 steps, collision range 5 m) AL is 11 m from 15 m out
(at 60 m and 30 m: 11 m) and falls to 6 m at the 10 m goal range, 1 m at 5 m. The docking term
does not grow with range: under a fixed deadline the line-of-sight axis has no spare step at any
range. AL bounds one frame's error with the others exact: errors on several frames share the
slack and compound toward the target (the paper law flies from each estimate), which the
closed-loop (in-loop attacker) counts measure.

The persistent-bias alert limit (`persistent_alert_limit`, the limit of `AlertLimitSettings.kind`
"persistent"). The single-frame AL above misses the failure a navigator under attack is most exposed
to: a bias that stays. The guidance law flies to where the estimate says the goal is, so a bias b
(m, world) still present when the chaser settles docks it at g - b: a miss of |b|. AL_p bounds the
trusted error E at true range r such that the mission still docks within the tolerance, in the
dynamics that execute the command on the true state (variant "true_state": rel_next = rel - cmd,
cmd = clip(rel + b - g, -s, s) per axis; the paper variant's prediction-is-truth dynamics are the
single-frame AL's). Assumptions: (a) the nominal approach, at s per step along the line of sight, so
from true range r it reaches the goal range r_g in (r - r_g) / s steps; (b) every axis may move s per
step independently (the law clips per axis), so the axes across the approach have their whole budget
free, and the line-of-sight axis runs at full speed as long as its estimate is more than s beyond the
goal; (c) the run lingers at the goal for at least one step (the slack), which the AL does not spend.
1. The chaser follows its bias without overshoot: per axis the law moves rel toward g - b by at most
   s, never past it (rel_next - (g - b) = e - clip(e, -s, s) with e = rel + b - g: same sign, smaller).
   So a chaser that has flown on biases bounded by B is displaced from its nominal path by at most B.
2. A bias that disappears before docking is removed in time iff the remaining steps can close it: an
   error E at range r displaces the chaser by at most E; once the estimate is exact again the law
   closes that displacement at s per step and the approach has (r - r_g) / s steps left, so the
   chaser docks within tol iff E - tol <= s (r - r_g) / s:  E <= tol + (r - r_g).
   Along the line of sight the same bound holds: an estimate nearer than the truth by E < r - r_g - s
   leaves the full-speed command unchanged, one farther than the truth changes nothing while it lasts
   (the axis is already at full speed), and the displacement left when it ends is closed as above.
3. A bias present at the goal is not removed: at r = r_g the chaser settles at g - b, so E <= tol.
Hence, with the ratio of the lateral authority s per step to the approach speed s per step,
    AL_p(r) = tol + max(r - r_g, 0)                          (metres, r the true range),
the cone that shrinks to the docking tolerance at the goal: 51 m at 60 m, 6 m at 15 m, 1 m at 10 m with
the defaults (tol 1 m, r_g 10 m). Off the goal's line of sight (a lateral offset d) the approach still
to go is the longest per-axis distance to the goal, shorter than r - r_g by about d^2 / (2 r): on the
evaluation trajectories (lateral starts up to 25 m per axis, projectile paths) up to ~10 m at the 60 m
start, where AL_p is ~60 m, and under 0.1 m inside 20 m, where the limit matters. Any bias sequence with
|b_k| <= AL_p(r_k) on every frame docks within
tol + s one step after arrival (the law acts on the previous frame's bias: the one-step lag) and
within tol once the chaser settles at the goal; it never collides, since the chaser moves inward only
while rel > g - b >= r_g - tol - (r - r_g), so the truth stays above r_g - tol - s (8 m) > collision
range (5 m). Against the single-frame AL, AL_p is looser far out (a bias the approach has time to remove
is harmless) and tighter inside r_g + slack s (20 m): the frames near the goal are where a persistent
bias becomes a miss. A trajectory whose trusted error exceeds AL_p on an available frame near the goal
is a mission failure in waiting (pipeline/evaluation/measures.py counts it as one).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from pipeline.defense.fusion import COAST, MODES, TRACK, DefenseTrace
from pipeline.stats import Rate, bootstrap_rate

FLOWN = (TRACK, COAST)  # defense modes in which the guidance flies on the trusted estimate
KINDS = ("single_frame", "persistent")  # which alert limit `alert_limit` gives (module docstring)


@dataclass(frozen=True)
class AlertLimitSettings:
    """The constants of `alert_limit`: docking tolerance (m), step limit (m per step per axis), slack
    steps of the run's budget beyond the nominal approach, collision range (m); `fixed` (m): a fixed AL at
    every range instead of the derived AL(range) (None: derived); goal_range (m): the goal's range r_g;
    kind: "single_frame" (one wrong frame, the others exact) or "persistent" (a bias that may stay to
    docking), see the module docstring."""

    tolerance: float = 1.0
    max_step: float = 1.0
    slack_steps: int = 10
    collision_range: float = 5.0
    fixed: float | None = None
    goal_range: float = 10.0
    kind: str = "single_frame"

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"alert limit: unknown kind {self.kind!r}; choose one of {', '.join(KINDS)}")
        for name in ("tolerance", "max_step", "collision_range", "goal_range"):
            if not float(getattr(self, name)) > 0:
                raise ValueError(f"alert limit: {name} must be > 0 (metres), got {getattr(self, name)!r}")
        if int(self.slack_steps) != self.slack_steps or self.slack_steps < 0:
            raise ValueError(f"alert limit: slack_steps must be a whole number >= 0, got {self.slack_steps!r}")
        if self.fixed is not None and not float(self.fixed) > 0:
            raise ValueError(f"alert limit: fixed must be None or > 0 (metres), got {self.fixed!r}")


def alert_limit(range_m: np.ndarray | float, settings: AlertLimitSettings = AlertLimitSettings()) -> np.ndarray:
    """AL (m) at true range `range_m` (m) of `settings.kind`: `single_frame_alert_limit` or
    `persistent_alert_limit`, or `settings.fixed` at every range when set."""
    r = np.asarray(range_m, dtype=np.float64)
    if settings.fixed is not None:
        return np.full_like(r, float(settings.fixed))
    if settings.kind == "persistent":
        return persistent_alert_limit(r, settings)
    return single_frame_alert_limit(r, settings)


def persistent_alert_limit(
    range_m: np.ndarray | float, settings: AlertLimitSettings = AlertLimitSettings()
) -> np.ndarray:
    """AL_p (m) at true range `range_m` (m): tol + max(r - r_g, 0), the largest error a bias that may stay
    to docking can have there (derivation in the module docstring; `settings.fixed` is not applied)."""
    r = np.asarray(range_m, dtype=np.float64)
    return settings.tolerance + np.maximum(r - settings.goal_range, 0.0)


def single_frame_alert_limit(
    range_m: np.ndarray | float, settings: AlertLimitSettings = AlertLimitSettings()
) -> np.ndarray:
    """AL (m) at true range `range_m` (m) for one wrong frame: max(tol, min(tol + slack s, r + s -
    collision range)) (the module docstring's first derivation; `settings.fixed` is not applied)."""
    s = settings
    r = np.asarray(range_m, dtype=np.float64)
    docking = s.tolerance + s.slack_steps * s.max_step
    collision = r + s.max_step - s.collision_range
    return np.maximum(s.tolerance, np.minimum(docking, collision))


@dataclass(frozen=True, eq=False)
class IntegrityFrames:
    """Per-frame integrity records of N frames (one or more trajectories).

    trajectory (N,) run ids (the bootstrap's groups); frame (N,) index in its run; trusted, truth
    (N, 3) trusted estimate and true `rel`, world frame (m; trusted NaN where there is none); mode
    (N,) defense mode; alert (N,) AL at the true range (m); pl (N,) protection level (m) or None.
    """

    trajectory: np.ndarray
    frame: np.ndarray
    trusted: np.ndarray
    truth: np.ndarray
    mode: np.ndarray
    alert: np.ndarray
    pl: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = len(self.frame)
        shapes = {"trajectory": (n,), "trusted": (n, 3), "truth": (n, 3), "mode": (n,), "alert": (n,)}
        if self.pl is not None:
            shapes["pl"] = (n,)
        for name, shape in shapes.items():
            if np.shape(getattr(self, name)) != shape:
                raise ValueError(
                    f"integrity frames: {name} must have shape {shape}, got {np.shape(getattr(self, name))}"
                )
        unknown = set(np.unique(self.mode).tolist()) - set(MODES)
        if unknown:
            raise ValueError(f"integrity frames: unknown defense modes {sorted(unknown)}; expected {', '.join(MODES)}")

    @property
    def error(self) -> np.ndarray:
        """(N,) distance of the trusted estimate to the truth (m); NaN where there is no estimate."""
        return np.linalg.norm(self.trusted - self.truth, axis=1)

    @property
    def available(self) -> np.ndarray:
        """(N,) the guidance flies on the trusted estimate (mode in FLOWN, a finite estimate) and PL <= AL
        where PL is given (a NaN PL bounds nothing: not available)."""
        ok = np.isin(self.mode, FLOWN) & np.isfinite(self.error)
        return ok if self.pl is None else ok & (self.pl <= self.alert)

    @property
    def hmi(self) -> np.ndarray:
        """(N,) hazardously misleading: available and error > AL."""
        return self.available & (self.error > self.alert)

    @property
    def has_pl(self) -> np.ndarray:
        """(N,) frames with a finite protection level."""
        return np.zeros(len(self.frame), bool) if self.pl is None else np.isfinite(self.pl)

    @property
    def mi(self) -> np.ndarray:
        """(N,) misleading: error > PL, on frames with a PL and an estimate (False elsewhere)."""
        return self.has_pl & (self.error > (np.inf if self.pl is None else self.pl))


def defense_frames(
    trace: DefenseTrace, truth: np.ndarray, trajectory: Any, settings: AlertLimitSettings, pl: np.ndarray | None = None
) -> IntegrityFrames:
    """The integrity records of one run through the defense: `trace` its DefenseTrace (e.g. of
    pipeline.evaluation.sequences.defend_trace or pipeline.defense.fusion.run_defense), `truth` (N, 3) the true rel (world, m), e.g.
    `Sequence.rel`, `trajectory` the run's id, `pl` (N,) protection levels (m): by default the trace's own
    (`DefenseTrace.pl`, where the defense has one); availability is then flown and PL <= AL, MI error > PL."""
    truth = np.asarray(truth, np.float64)
    pl = trace.pl if pl is None else pl
    n = len(trace.mode)
    if truth.shape != (n, 3):
        raise ValueError(f"defense_frames: truth must be (N, 3) = ({n}, 3), got {truth.shape}")
    return IntegrityFrames(
        np.full(n, trajectory, dtype=object),
        np.arange(n),
        np.asarray(trace.trusted, np.float64),
        truth,
        np.asarray(trace.mode),
        alert_limit(np.linalg.norm(truth, axis=1), settings),
        None if pl is None else np.asarray(pl, np.float64),
    )


def concat(runs: list[IntegrityFrames]) -> IntegrityFrames:
    """Several runs' records as one (all with a PL or all without)."""
    if not runs:
        raise ValueError("concat: no runs")
    if len({r.pl is None for r in runs}) > 1:
        raise ValueError("concat: some runs have a protection level and some do not")
    pl = None if runs[0].pl is None else np.concatenate([r.pl for r in runs])
    return IntegrityFrames(
        *(
            np.concatenate([getattr(r, k) for r in runs])
            for k in ("trajectory", "frame", "trusted", "truth", "mode", "alert")
        ),
        pl,
    )


def _check_paired(attacked: IntegrityFrames, clean: IntegrityFrames) -> None:
    """Refuse an attacked / clean pair whose frames are not the same frames of the same runs."""
    if len(attacked.frame) != len(clean.frame) or not (
        np.array_equal(attacked.frame, clean.frame) and np.array_equal(attacked.trajectory, clean.trajectory)
    ):
        raise ValueError(
            "integrity: the attacked runs and their clean counterparts must hold the same frames "
            "of the same trajectories, in the same order"
        )


def attack_hmi(attacked: IntegrityFrames, clean: IntegrityFrames) -> np.ndarray:
    """(N,) HMI the attack caused: HMI in the attacked run and not on the same frame of the clean run."""
    _check_paired(attacked, clean)
    return attacked.hmi & ~clean.hmi


def attack_mi(attacked: IntegrityFrames, clean: IntegrityFrames) -> np.ndarray:
    """(N,) MI the attack caused: MI in the attacked run and not on the same frame of the clean run."""
    _check_paired(attacked, clean)
    return attacked.mi & ~clean.mi


def _error_stats(frames: IntegrityFrames, mask: np.ndarray) -> dict[str, float]:
    """Mean and max trusted error (m) over the masked frames that have an estimate (NaN when none)."""
    err = frames.error[mask]
    err = err[np.isfinite(err)]
    return {
        "trusted_error_mean_m": float(err.mean()) if err.size else float("nan"),
        "trusted_error_max_m": float(err.max()) if err.size else float("nan"),
    }


def integrity_rates(
    attacked: IntegrityFrames, clean: IntegrityFrames, mask: np.ndarray | None = None, seed: int = 0
) -> dict[str, Any]:
    """Integrity of attacked runs beside the same frames without the attack (`mask` (N,): the frames to
    count, e.g. the attacked ones; all by default). Every rate is a `Rate` with a 95% interval by a
    bootstrap over trajectories:

    hmi: HMI the attack caused, over the counted frames; hmi_attacked / hmi_clean: HMI in the attacked
    runs / on the same frames of the clean runs; mi: MI the attack caused, over the counted frames that
    have a PL in both runs; availability / availability_clean: available frames with / without the
    attack; frames: the counted frames; trusted_error_mean_m / _max_m: over the counted frames of the
    attacked runs that have an estimate (m).
    """
    _check_paired(attacked, clean)
    keep = np.ones(len(attacked.frame), bool) if mask is None else np.asarray(mask, bool)
    if keep.shape != attacked.frame.shape:
        raise ValueError(f"integrity_rates: mask must have shape {attacked.frame.shape}, got {keep.shape}")
    g = attacked.trajectory.astype(str)

    def rate(hits: np.ndarray, where: np.ndarray) -> Rate:
        return bootstrap_rate(hits[where], g[where], seed=seed)

    with_pl = keep & attacked.has_pl & clean.has_pl
    return {
        "hmi": rate(attack_hmi(attacked, clean), keep),
        "hmi_attacked": rate(attacked.hmi, keep),
        "hmi_clean": rate(clean.hmi, keep),
        "mi": rate(attack_mi(attacked, clean), with_pl),
        "availability": rate(attacked.available, keep),
        "availability_clean": rate(clean.available, keep),
        "frames": int(keep.sum()),
        **_error_stats(attacked, keep),
    }


def clean_rates(clean: IntegrityFrames, seed: int = 0) -> dict[str, Any]:
    """Integrity of clean runs: availability, HMI and MI (over the frames with a PL) as `Rate`s
    (bootstrap over trajectories), frames, mean and max trusted error (m)."""
    g = clean.trajectory.astype(str)
    every = np.ones(len(clean.frame), bool)
    has = clean.has_pl
    return {
        "availability": bootstrap_rate(clean.available, g, seed=seed),
        "hmi": bootstrap_rate(clean.hmi, g, seed=seed),
        "mi": bootstrap_rate(clean.mi[has], g[has], seed=seed),
        "frames": len(clean.frame),
        **_error_stats(clean, every),
    }
