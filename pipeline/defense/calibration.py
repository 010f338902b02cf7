"""Calibration of the defense's checks on clean validation trajectories, one check at a time.

The false-alarm budget `target` (fraction of clean frames the defended chain may flag) is split into
shares, one per check, and each check is set to meet its own share on clean validation frames (never
test data), in this order:
1. the detector: its threshold is the smallest probability at which at most share_detector of the
   clean validation frames reach it (a quantile of the chain's own clean frames, not of the SHAP
   split, whose clean samples are partly pose-training images);
2. the gate: the smallest inflations of the fitted noise model (`INFLATIONS`; attitude first, then
   position) at which the gate flags at most share_gate of the frames (fusion "motion", the
   sequential test off): a Gaussian fit under-states the pose errors' heavy, correlated tails;
3. the sequential test: the smallest CUSUM threshold h (`CUSUM_THRESHOLDS`) at which it flags at
   most share_sequential of the frames (fusion "motion", the gate at its inflation): the smallest h
   also gives the smallest protection level (pipeline/defense/protection.py).
Each returns a `CheckResult` that says whether the share was met. The shares add up to the budget, so
the fused chain's rate is at most about the budget (the checks' flags overlap).
4. the protection level's coverage (`protection_coverage`, last: it changes no flag): the smallest share of
   one measurement's variance held as correlated (`CORRELATED`; MotionSettings.correlated_error, assumption C
   of pipeline/defense/protection.py) at which no clean validation frame's trusted error exceeds its PL. The
   pose errors are correlated over the frames the filter starts on, so a PL that treats them as white is
   exceeded on clean approaches (seed 1 of the default profile: 2.2% of the validation frames with a PL); a
   PL that still does at the largest share is a miss, and `UnmetShare` stops the search (`allow_unmet` aside:
   then the smallest share with the fewest misleading frames stands).

The search (`calibrate_to_target`, the one `rpod calibrate` runs): every check to its share
(`calibrate_checks`; an unmet share raises `UnmetShare` unless the budget allows it), then the fused chain on
the clean validation runs; when it flags more than the target although each check met its share (a rejected
frame leaves the filter to coast, which can raise the next innovations), every share is tightened by the
overshoot (at least by TIGHTEN_STEP) and the checks are calibrated again, at most TIGHTEN_TRIES times; the
caller judges the last attempt against the target.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from functools import partial
from typing import Any, Callable, NamedTuple, Sequence

import numpy as np

from pipeline.defense.fusion import DefenseTrace, run_defense
from pipeline.defense.gate import MotionSettings
from pipeline.defense.integrity import AlertLimitSettings, alert_limit
from pipeline.defense.noise import NoiseModel, inflate
from pipeline.defense.settings import DefenseSettings
from pipeline.geometry.rotations import sixd_to_matrix

INFLATIONS = (1.0, 1.25, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 8.0)
CUSUM_THRESHOLDS = (
    1.0,
    1.5,
    2.0,
    2.5,
    3.0,
    3.5,
    4.0,
    5.0,
    6.0,
    7.0,
    8.0,
    10.0,
    12.0,
    15.0,
    20.0,
    25.0,
    30.0,
    40.0,
    50.0,
)
# shares of one measurement's variance the protection level may hold as correlated (assumption C of
# pipeline/defense/protection.py), smallest first
CORRELATED = (0.0, 0.05, 0.1, 0.2, 0.3, 0.5, 0.75, 1.0)
COVERAGE = "protection level"  # the CheckResult name of `protection_coverage`
OFF = 1e12  # a CUSUM threshold no statistic reaches: the sequential test off
# times the shares are tightened (each by the fused chain's overshoot) before the search gives up on the target
TIGHTEN_TRIES = 3
# the least tightening per try: the checks' settings move on coarse grids (gate inflation, CUSUM h), and a share
# tightened only by a small overshoot (0.52% against 0.5%: x0.96) moved none of them (seed 1, AVX-512)
TIGHTEN_STEP = 0.75


@dataclass(frozen=True)
class CheckResult:
    """One check's calibration: `setting` (threshold, inflation or h) chosen, its flag rate `reached`
    on the clean validation frames, its `share` of the budget (fractions), `met` = reached <= share,
    and the rate at every setting tried (`rates`)."""

    check: str
    setting: float
    reached: float
    share: float
    rates: dict[float, float]

    @property
    def met(self) -> bool:
        return self.reached <= self.share


@dataclass(frozen=True)
class CleanRun:
    """One clean validation trajectory as the defense sees it: pose (N, 9) [m, 6-D], prob (N,),
    R_cam (N, 3, 3) camera -> world, u (N, 3) commanded displacements (world, m)."""

    pose: np.ndarray
    prob: np.ndarray
    R_cam: np.ndarray
    u: np.ndarray


def defend_runs(
    settings: DefenseSettings,
    motion: MotionSettings,
    noise: NoiseModel,
    runs: Sequence[CleanRun],
    alert_limit: Callable[[float], float] | None = None,
) -> list[DefenseTrace]:
    """A fresh defense over each run (open loop)."""
    return [
        run_defense(
            settings, motion, noise, r.pose[:, :3], r.prob, r.R_cam, r.u, sixd_to_matrix(r.pose[:, 3:9]), alert_limit
        )
        for r in runs
    ]


def first_meeting(
    rate_at: Callable[[float], float], target: float, grid: Sequence[float]
) -> tuple[float, dict[float, float]]:
    """The first setting of `grid` whose rate `rate_at(setting)` is at most `target`, and every rate
    measured (it stops there); the last setting when none is (check the rate before using it)."""
    rates: dict[float, float] = {}
    for v in grid:
        rates[v] = float(rate_at(v))
        if rates[v] <= target:
            return v, rates
    return grid[-1], rates


def detector_threshold(prob: np.ndarray, share: float) -> CheckResult:
    """The smallest threshold t in (0, 1) with mean(prob >= t) <= share on clean frames `prob` (N,).
    When the frames above the share all sit at the top (ties at probability 1), no t < 1 meets it:
    the result is not met, at t just under 1."""
    p = np.sort(np.asarray(prob, np.float64))[::-1]
    if p.size == 0 or not np.isfinite(p).all():
        raise ValueError("detector calibration needs clean probabilities, finite, at least one")
    allowed = int(math.floor(share * p.size + 1e-9))  # frames that may reach the threshold
    if allowed >= p.size:
        t = float(np.nextafter(0.0, 1.0))
    else:
        t = float(np.nextafter(p[allowed], 1.0))  # just above the first frame that may not
    t = min(max(t, float(np.nextafter(0.0, 1.0))), float(np.nextafter(1.0, 0.0)))
    reached = float(np.mean(p >= t))
    return CheckResult("detector", t, reached, share, {t: reached})


def doubt_level(prob: np.ndarray, share: float, threshold: float) -> float:
    """The detector's doubt level (`DefenseSettings.update_below`): the smallest probability with
    mean(prob >= level) <= share on clean frames `prob` (N,), at most the detector's `threshold`. Frames
    at or above it (and below the threshold) are not flagged but do not update the motion filter, so
    `share` is the fraction of clean frames the filter goes without: a fixed level that most clean frames
    reach starves the filter, which then coasts on a stale state until clean frames disagree with it."""
    return min(detector_threshold(prob, share).setting, float(threshold))


def gate_inflation(
    settings: DefenseSettings,
    motion: MotionSettings,
    noise: NoiseModel,
    runs: Sequence[CleanRun],
    share: float,
    grid: Sequence[float] = INFLATIONS,
) -> tuple[CheckResult, CheckResult]:
    """The gate's two tests, attitude then position: the smallest attitude-noise inflation at which the
    attitude test flags at most half of `share` of the frames, then (with it) the smallest
    position-noise inflation at which the gate (either test) flags at most `share` (fusion "motion",
    the sequential test off). The position noise is inflated no more than the position test needs:
    the sequential test and the protection level scale with it."""
    alone = dataclasses.replace(settings, fusion="motion")
    off = dataclasses.replace(motion, cusum_threshold=OFF)

    def flags(k: float, k_att: float) -> tuple[float, float]:
        traces = defend_runs(alone, off, inflate(noise, k, k_att), runs)
        gate = np.concatenate([t.motion_flag for t in traces])
        att = np.concatenate([t.motion_flag & (np.nan_to_num(t.nis_attitude) > off.gate) for t in traces])
        return float(gate.mean()), float(att.mean())

    k_att, att_rates = first_meeting(lambda a: flags(max(grid), a)[1], share / 2, grid)
    k, rates = first_meeting(lambda k: flags(k, k_att)[0], share, grid)
    return (
        CheckResult("attitude gate", k_att, att_rates[k_att], share / 2, att_rates),
        CheckResult("gate", k, rates[k], share, rates),
    )


def sequential_threshold(
    settings: DefenseSettings,
    motion: MotionSettings,
    noise: NoiseModel,
    runs: Sequence[CleanRun],
    share: float,
    grid: Sequence[float] = CUSUM_THRESHOLDS,
) -> CheckResult:
    """The smallest CUSUM threshold h at which the sequential test flags at most `share` of the frames
    (the gate on, with `noise` as calibrated for it)."""
    alone = dataclasses.replace(settings, fusion="motion")

    def rate(h: float) -> float:
        traces = defend_runs(alone, dataclasses.replace(motion, cusum_threshold=h), noise, runs)
        return float(np.concatenate([t.sequential_flag for t in traces]).mean())

    h, rates = first_meeting(rate, share, grid)
    return CheckResult("sequential test", h, rates[h], share, rates)


def protection_coverage(
    settings: DefenseSettings,
    motion: MotionSettings,
    noise: NoiseModel,
    runs: Sequence[CleanRun],
    truths: Sequence[np.ndarray],
    alert: Any,
    grid: Sequence[float] = CORRELATED,
) -> tuple[CheckResult, dict[str, Any]]:
    """The smallest `correlated_error` of `grid` at which no frame of the clean validation `runs` (their true rel
    `truths`, world m; the fused chain as calibrated) has a trusted error above its protection level: its share is
    0 and its rate the misleading frames' (error > PL) share of the frames with a PL (`alert`: the
    AlertLimitSettings the summary needs). When no share covers them (unmet), the smallest share with the fewest
    such frames: a larger one widens every PL, costing availability, and covers no more (seed 1 of the default
    profile: the frames left from share 0.1 to 1 were one approach's first 7, where the filter started on a gross
    range outlier). Returns it and the runs' `clean_summary` at that setting."""
    limit = None if alert is None else partial(alert_limit, settings=alert)
    summaries: dict[float, dict[str, Any]] = {}

    def rate(f: float) -> float:
        tuned = dataclasses.replace(motion, correlated_error=f)
        summaries[f] = clean_summary(defend_runs(settings, tuned, noise, runs, limit), truths, alert)
        return summaries[f]["mi"].value

    f, rates = first_meeting(rate, 0.0, grid)
    if rates[f] > 0.0:
        f = min(rates, key=lambda g: (rates[g], g))
    return CheckResult(COVERAGE, f, rates[f], 0.0, rates), summaries[f]


def clean_summary(traces: Sequence[DefenseTrace], truths: Sequence[np.ndarray], alert: Any) -> dict[str, Any]:
    """What the defense does on clean runs (`traces`, their true rel (N, 3) world m, `alert` the
    AlertLimitSettings): flag rates of each check and of the fused chain, availability (flown and PL
    <= AL at the true range), MI (error > PL, frames with a PL), as Rates with a bootstrap over runs;
    frames; the median and 95th percentile of the finite PL and of the trusted error (m)."""
    from pipeline.defense.integrity import concat, defense_frames
    from pipeline.stats import bootstrap_rate

    groups = np.concatenate([np.full(len(t.flag), i) for i, t in enumerate(traces)])
    out: dict[str, Any] = {
        name: bootstrap_rate(np.concatenate([getattr(t, attr) for t in traces]), groups)
        for name, attr in (
            ("detector", "shap_flag"),
            ("gate", "motion_flag"),
            ("sequential", "sequential_flag"),
            ("fused", "flag"),
        )
    }
    frames = concat([defense_frames(t, truth, i, alert) for i, (t, truth) in enumerate(zip(traces, truths))])
    has = frames.has_pl
    out["availability"] = bootstrap_rate(frames.available, groups)
    out["mi"] = bootstrap_rate(frames.mi[has], groups[has])
    out["frames"] = int(len(groups))
    err = frames.error[np.isfinite(frames.error)]
    for name, v in (("pl_m", frames.pl[has]), ("error_m", err)):
        out[name] = {
            "median": float(np.median(v)) if v.size else math.nan,
            "p95": float(np.quantile(v, 0.95)) if v.size else math.nan,
        }
    return out


@dataclass(frozen=True)
class Budget:
    """The false-alarm budget: `target`, the fraction of clean validation frames the defended chain may flag;
    each check's share of it (`detector`, `gate`, `sequential`: fractions adding up to 1); `doubt_share`, the
    fraction of clean validation frames at or above the doubt level (None: no doubt zone); `allow_unmet`: a
    check that cannot meet its share stands (else `UnmetShare`)."""

    target: float
    detector: float
    gate: float
    sequential: float
    doubt_share: float | None = None
    allow_unmet: bool = False


class UnmetShare(ValueError):
    """A check could not meet its share of the budget (`check`: its CheckResult)."""

    def __init__(self, check: CheckResult) -> None:
        best = min(check.rates.values())
        super().__init__(f"the {check.check} cannot meet its share {check.share:g}: it flags {best:g} at best")
        self.check = check


class Calibrated(NamedTuple):
    """The outcome of `calibrate_to_target`: the checks as calibrated (CheckResults: detector, attitude gate,
    gate, sequential test), the chain's settings, the inflated noise model, `clean_summary` of the defended
    validation runs, and the share tightening."""

    checks: list[CheckResult]  # detector, attitude gate, gate, sequential test, protection level
    settings: DefenseSettings
    motion: MotionSettings
    noise: NoiseModel
    final: dict[str, Any]
    scale: float  # the factor the shares were calibrated with (1: not tightened)
    tightened: list[dict[str, Any]]  # each overshooting attempt: its scale and fused false alarms (%)


def calibrate_to_target(
    settings: DefenseSettings,
    motion: MotionSettings,
    fitted: NoiseModel,
    runs: Sequence[CleanRun],
    prob: tuple[np.ndarray, ...],
    truths: Sequence[np.ndarray],
    alert: AlertLimitSettings | None,
    budget: Budget,
) -> Calibrated:
    """The search of the module docstring, from the chain's `settings` and `motion` (the params', with the
    detector checkpoint's threshold), the `fitted` noise model, the clean validation `runs` (their true rel
    `truths`, world m), the clean probabilities `prob` (`calibrate_checks`) and the alert limit `alert`."""
    scale, tightened = 1.0, []
    limit = None if alert is None else partial(alert_limit, settings=alert)
    while True:
        checks, calibrated, filtered = calibrate_checks(settings, motion, fitted, runs, prob, budget, scale)
        noise = inflate(fitted, checks[2].setting, checks[1].setting)
        final = clean_summary(defend_runs(calibrated, filtered, noise, runs, limit), truths, alert)
        fused = final["fused"].value
        if fused <= budget.target or len(tightened) == TIGHTEN_TRIES:
            coverage, final = protection_coverage(calibrated, filtered, noise, runs, truths, alert)
            if not (budget.allow_unmet or coverage.met):
                raise UnmetShare(coverage)
            filtered = dataclasses.replace(filtered, correlated_error=coverage.setting)
            return Calibrated([*checks, coverage], calibrated, filtered, noise, final, scale, tightened)
        tightened.append({"shares_scale": scale, "fused_pct": round(100 * fused, 4)})
        scale *= min(budget.target / fused, TIGHTEN_STEP)


def calibrate_checks(
    settings: DefenseSettings,
    motion: MotionSettings,
    fitted: NoiseModel,
    runs: Sequence[CleanRun],
    prob: tuple[np.ndarray, ...],
    budget: Budget,
    scale: float = 1.0,
) -> tuple[list[CheckResult], DefenseSettings, MotionSettings]:
    """The detector, the gate (its attitude test, then both) and the sequential test, each to its share of the
    budget (times `scale` <= 1, when the fused chain overshot the target), in that order (each later one with the
    earlier ones' settings); an unmet share raises UnmetShare there unless `budget.allow_unmet`. The detector's
    threshold meets its share on every set of clean probabilities in `prob` (the validation runs' frames, then
    the envelope's): the highest of their thresholds; the doubt level is calibrated on the first set."""
    total = budget.target * scale

    def judged(check: CheckResult) -> CheckResult:
        if not (budget.allow_unmet or check.met):
            raise UnmetShare(check)
        return check

    detector = judged(max((detector_threshold(p, budget.detector * total) for p in prob), key=lambda c: c.setting))
    doubt = None if budget.doubt_share is None else doubt_level(prob[0], budget.doubt_share, detector.setting)
    settings = dataclasses.replace(settings, threshold=detector.setting, update_below=doubt)
    attitude, gate = (judged(c) for c in gate_inflation(settings, motion, fitted, runs, budget.gate * total))
    sequential = judged(
        sequential_threshold(
            settings, motion, inflate(fitted, gate.setting, attitude.setting), runs, budget.sequential * total
        )
    )
    motion = dataclasses.replace(motion, cusum_threshold=sequential.setting)
    return [detector, attitude, gate, sequential], settings, motion
