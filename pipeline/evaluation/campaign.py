"""The integrity campaign of one chain (`rpod robustness`: the shipped chain, the standard one and the undefended
robust control): the chain flown clean over recorded trajectories, then every chain-level attacker at every eps of
an increasing ladder. Each attacked flight is judged twice: against the same trajectory unattacked (the
descriptive integrity rows: HMI and MI the attack caused, detection, availability;
pipeline/evaluation/integrity_runs.py) and by the measures that can fail (pipeline/evaluation/measures.py: per
trajectory the largest error / AL on an available frame, AL of the campaign's kind, the persistent-bias one by
default, beside the single-frame AL; the largest error / PL; the trusted error on the last frame, the bias the chaser
would dock with; flags; availability; Stanford regions). The nested burst's attacked frames are also seen per frame
(the paper's view: pipeline/evaluation/robustness.py).

The planner-driven attackers (`Plan`: capture, drift) run from their first attacked frame to the end of every
trajectory, all plans and trajectories of one eps in lockstep (`plan_attack`). The ladder may stop once the chain
has broken (`Campaign.stop_at_break`): after the first eps at which some attacker fails some trajectory the breaking
point is known, and the larger eps are not flown (their rows are absent, not zero). The burst, nested through the
whole ladder by construction, runs first.

`safety_summary` turns a campaign's flights into the safety evidence of the chain: per eps the worst over attackers
per trajectory (each attacker nested in eps first: an attack found within a smaller ball is within every larger
one), the trajectories failed, the largest indices, the Stanford counts and the trajectories with an HMI frame
(Clopper-Pearson over independent trajectories, a descriptive count); the breaking point; the clean trajectories'
measures (availability, false alarms).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from pipeline.defense.chain import Defended, OnboardChain
from pipeline.defense.integrity import AlertLimitSettings, IntegrityFrames, single_frame_alert_limit
from pipeline.evaluation.integrity_runs import (
    Flown,
    Track,
    as_json,
    burst_attack,
    clean_row,
    counted,
    fly,
    integrity_row,
    plan_attack,
    raw_errors,
)
from pipeline.evaluation.measures import (
    REGIONS,
    TrajectoryMeasures,
    breaking_point,
    nest_in_eps,
    stanford_counts,
    trajectory_measures,
    worst_over_attackers,
)
from pipeline.evaluation.robustness import fused_row
from pipeline.stats import Rate, bootstrap_rate, clopper_pearson

BURST_ROW = "fused chain: burst (nested, worst over lambda and restarts)"  # its per-frame row's name
RANGE_BANDS_M = (0.0, 15.0, 20.0, 30.0, float("inf"))  # true-range bands (m) of the clean availability's split


@dataclass(frozen=True)
class Plan:
    """A planner-driven attacker: `name` (e.g. "capture/lateral 5 m"), its `settings` (DriftSettings or
    CaptureSettings: anything with `planner(defense)`) and its first attacked frame `start` (it attacks every frame
    from there to the end)."""

    name: str
    settings: Any
    start: int


@dataclass(frozen=True)
class Campaign:
    """What a campaign flies: `eps` (increasing; L-inf, pixels in [0, 1]); the planner-driven attackers `plans`, each
    frame crafted by `frame_attack` (a pipeline.attackers.drift.FrameAttack) seeded `frame_seed`; the burst attacker
    (pipeline/attackers/burst.py, seeded; None: not flown) on the `bursts` (start, stop) of each track; `limit` the
    AL judged against, `single` the single-frame AL (the second column); the batch size of the chain's passes, the
    harm threshold of the per-frame rows (m), the seed of the rows' bootstrap; `stop_at_break`: stop the ladder
    after the eps at which the chain breaks."""

    eps: list[float]
    plans: list[Plan]
    frame_attack: Any
    frame_seed: int
    burst: Any
    bursts: list[list[tuple[int, int]]]
    limit: AlertLimitSettings
    single: AlertLimitSettings
    batch_size: int
    harm_m: float
    seed: int
    stop_at_break: bool = False


@dataclass(frozen=True)
class Flights:
    """A campaign's outcome: the clean flights and their false alarms (bootstrap over tracks); every attacked run
    (attacker, eps, its flights, the attacked frames per track); the descriptive integrity rows (the burst's with
    `bursts_with_hmi`), the clean row and the nested burst's per-frame rows; the measures per attacker and eps
    flown (per track, as flown: `safety_summary` nests them), the clean tracks' measures; the Stanford region
    counts per eps over every attacker's counted frames, and the clean frames'; `stopped`: the eps at which the
    ladder stopped (the chain broke there), None when every eps was flown; `bursts_hmi`: the burst's [bursts with
    an HMI frame, bursts] per eps ({} without the burst)."""

    clean: list[Flown]
    alarms: Rate
    runs: list[tuple[str, float, list[Flown], list[np.ndarray]]]
    rows: list[dict[str, Any]]
    clean_row: dict[str, Any]
    fused_rows: list[dict[str, Any]]
    measures: dict[str, dict[float, list[TrajectoryMeasures]]]
    clean_measures: list[TrajectoryMeasures]
    stanford: dict[float, dict[str, int]]
    stanford_clean: dict[str, int]
    stopped: float | None
    bursts_hmi: dict[float, list[int]]


def judge(flown: Flown, mask: np.ndarray, single: AlertLimitSettings) -> TrajectoryMeasures:
    """The measures of one flight over its counted frames (from the first attacked frame of `mask` (N,) to the end;
    every frame when none is attacked), with the single-frame AL of `single` at the true ranges as second column."""
    mask = np.asarray(mask, bool)
    keep = counted(mask) if mask.any() else np.ones(len(mask), bool)
    single_al = single_frame_alert_limit(np.linalg.norm(flown.frames.truth, axis=1), single)
    return trajectory_measures(flown.frames, flown.trace.flag, single_al, keep)


def fly_campaign(
    chain: OnboardChain,
    target: Any,
    defended: Defended | None,
    tracks: Sequence[Track],
    campaign: Campaign,
    progress: Callable[[], Any] = lambda: None,
) -> Flights:
    """The campaign of the module docstring on `chain` (its differentiable copy `target`: a PerFrameChain, or the
    bare pose network for the undefended control) with a fresh `defended` defense per flight (None: the undefended
    control); `progress()` after each attacked track of the burst and each attacked frame of the plans."""
    c = campaign
    clean = [fly(chain, defended, t, c.limit, c.batch_size) for t in tracks]
    runs: list[tuple[str, float, list[Flown], list[np.ndarray]]] = []
    bursts_hmi: dict[float, list[int]] = {}
    broken: float | None = None

    def record(name: str, e: float, flights: list[Flown], masks: list[np.ndarray]) -> None:
        nonlocal broken
        runs.append((name, e, flights, masks))
        if any(judge(f, m, c.single).failed for f, m in zip(flights, masks)):
            broken = e if broken is None else min(broken, e)

    if c.burst is not None:
        masks = [np.isin(np.arange(len(t)), [k for a, b in bs for k in range(a, b)]) for t, bs in zip(tracks, c.bursts)]
        stored, worst = burst_attack(target, defended, tracks, masks, c.burst, c.eps, progress)
        for e in c.eps:
            record(
                "burst",
                e,
                [fly(chain, defended, t, c.limit, c.batch_size, s, f) for t, s, f in zip(tracks, stored[e], clean)],
                masks,
            )
        bursts_hmi = {e: [sum(int(b.hmi.any()) for bs in worst[e] for b in bs), sum(map(len, worst[e]))] for e in c.eps}
    stopped = None
    for e in c.eps if c.plans else []:
        if c.stop_at_break and broken is not None and e > broken:
            stopped = broken
            break
        stored = plan_attack(
            target,
            defended,
            tracks,
            clean,
            [(p.settings, p.start) for p in c.plans],
            e,
            c.frame_seed,
            c.frame_attack,
            done=progress,
        )
        for plan, per in zip(c.plans, stored):
            record(
                plan.name,
                e,
                [fly(chain, defended, t, c.limit, c.batch_size, s, f) for t, s, f in zip(tracks, per, clean)],
                [np.arange(len(t)) >= plan.start for t in tracks],
            )
    return _flights(tracks, clean, runs, bursts_hmi, stopped, c)


@dataclass(frozen=True)
class TrackFlights:
    """One trajectory's share of a campaign flown to the end of its ladder (`fly_track`): its clean flight; per
    attacked run (attacker, eps, its flight, the attacked frames (N,) bool) in the campaign's order; the burst's
    [bursts with an HMI frame, bursts] per eps ({} without the burst)."""

    clean: Flown
    runs: list[tuple[str, float, Flown, np.ndarray]]
    bursts_hmi: dict[float, list[int]]


def fly_track(
    chain: OnboardChain,
    target: Any,
    defended: Defended | None,
    track: Track,
    campaign: Campaign,
    progress: Callable[[], Any] = lambda: None,
) -> TrackFlights:
    """`fly_campaign` on one track (`campaign.bursts` holds that track's bursts only) at every eps of the ladder
    (no stop at the breaking point: a track alone cannot know it): a resumable share of the campaign, which
    `assemble` joins with the other tracks' into the campaign's Flights. The attacks draw on the campaign's seeds
    as given (the caller gives each track its own)."""
    if campaign.stop_at_break:
        raise ValueError("fly_track flies the whole ladder: the campaign must not stop at the breaking point")
    f = fly_campaign(chain, target, defended, [track], campaign, progress)
    return TrackFlights(f.clean[0], [(a, e, fl[0], m[0]) for a, e, fl, m in f.runs], f.bursts_hmi)


def assemble(tracks: Sequence[Track], shares: Sequence[TrackFlights], campaign: Campaign) -> Flights:
    """The campaign's Flights from each track's `fly_track` share (in the order of `tracks`): the same rows,
    measures and counts as one `fly_campaign` over every track that draws the same attacks."""
    if len(shares) != len(tracks) or not shares:
        raise ValueError(f"assemble needs one share per track, got {len(shares)} for {len(tracks)} tracks")
    keys = [(a, e) for a, e, _, _ in shares[0].runs]
    if any([(a, e) for a, e, _, _ in s.runs] != keys for s in shares):
        raise ValueError("assemble: the tracks' shares flew different attackers or eps (one campaign's shares only)")
    runs = [(a, e, [s.runs[k][2] for s in shares], [s.runs[k][3] for s in shares]) for k, (a, e) in enumerate(keys)]
    hmi = {e: [sum(s.bursts_hmi[e][i] for s in shares) for i in (0, 1)] for e in shares[0].bursts_hmi}
    return _flights(tracks, [s.clean for s in shares], runs, hmi, None, campaign)


def _flights(
    tracks: Sequence[Track],
    clean: list[Flown],
    runs: list[tuple[str, float, list[Flown], list[np.ndarray]]],
    bursts_hmi: dict[float, list[int]],
    stopped: float | None,
    c: Campaign,
) -> Flights:
    """The Flights of the clean flights and the attacked runs: false alarms, measures, rows, Stanford counts."""
    flags = np.concatenate([f.trace.flag for f in clean])
    alarms = bootstrap_rate(flags, np.concatenate([np.full(len(t), g) for g, t in enumerate(tracks)]))
    measures: dict[str, dict[float, list[TrajectoryMeasures]]] = {}
    for name, e, flown, masks in runs:
        measures.setdefault(name, {})[e] = [judge(f, m, c.single) for f, m in zip(flown, masks)]
    rows = [
        integrity_row(name, e, flown, clean, masks, seed=c.seed)
        | ({"bursts_with_hmi": bursts_hmi[e]} if name == "burst" else {})
        for name, e, flown, masks in runs
    ]
    fused = []
    for name, e, flown, masks in runs:
        if name == "burst":
            err, flag, group = raw_errors(flown, tracks, masks)
            fused.append(fused_row(BURST_ROW, e, None, err, flag, group, c.harm_m))
    stanford: dict[float, dict[str, int]] = {}
    for _, e, flown, masks in runs:
        counts = stanford.setdefault(e, dict.fromkeys(REGIONS, 0))
        for f, m in zip(flown, masks):
            for region, k in stanford_counts(f.frames, counted(m)).items():
                counts[region] += k
    every = [np.zeros(len(t), bool) for t in tracks]
    clean_stanford = dict.fromkeys(REGIONS, 0)
    for f in clean:
        for region, k in stanford_counts(f.frames).items():
            clean_stanford[region] += k
    return Flights(
        clean,
        alarms,
        runs,
        rows,
        clean_row(clean, seed=c.seed),
        fused,
        measures,
        [judge(f, m, c.single) for f, m in zip(clean, every)],
        stanford,
        clean_stanford,
        stopped,
        bursts_hmi,
    )


def availability_by_range(
    frames: Sequence[IntegrityFrames], edges: Sequence[float] = RANGE_BANDS_M
) -> list[dict[str, Any]]:
    """Where availability is lost: per band [lo, hi) of true range (m) of `edges` (the last may be open: inf),
    pooled over the runs' records `frames`, the frames in it and the share available (None: no frame); [] without
    records."""
    if not frames:
        return []
    rng = np.concatenate([np.linalg.norm(f.truth, axis=1) for f in frames])
    available = np.concatenate([f.available for f in frames])
    out = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        inside = (rng >= lo) & (rng < hi)
        out.append(
            {
                "from_m": float(lo),
                "to_m": float(hi) if np.isfinite(hi) else None,
                "frames": int(inside.sum()),
                "available": float(available[inside].mean()) if inside.any() else None,
            }
        )
    return out


def _largest(values: Sequence[float]) -> float | None:
    """The largest finite value, None when there is none (the JSON's missing number)."""
    finite = [float(v) for v in values if np.isfinite(v)]
    return max(finite) if finite else None


def _plain(row: dict[str, Any]) -> dict[str, Any]:
    """A measures row for JSON: a NaN (no such frame) as None."""
    return {k: None if isinstance(v, float) and not np.isfinite(v) else v for k, v in row.items()}


def _cp_json(r: Rate) -> dict[str, Any]:
    return {
        "value": None if r.n == 0 else float(r.value),
        "ci": r.ci(),
        "n": int(r.n),
        "ci_method": "Clopper-Pearson over trajectories",
    }


def safety_summary(flights: Flights) -> dict[str, Any]:
    """The chain's safety evidence (module docstring) as the metrics JSON holds it: `breaking_eps` (None: held over
    every eps flown), `eps_flown`, `stopped_at`, `per_eps` {"%g": worst over attackers: largest error / AL (the
    campaign's AL, on available frames), error / AL single-frame, error / PL, final error (m), failed trajectories
    of `trajectories`, the attacker behind the largest error / AL, trajectories with an HMI frame (Clopper-Pearson),
    Stanford counts, `per_trajectory` rows}, `attackers` {name: {"%g": per-trajectory measures, nested in eps}},
    `clean` {per-trajectory measures, largest indices, mean availability over trajectories, the availability and
    false alarms over frames with their bootstrap intervals, the availability per true-range band
    (`availability_by_range`), Stanford counts}."""
    f = flights
    nested = {a: nest_in_eps(by_eps) for a, by_eps in f.measures.items()}
    flown = sorted({e for by_eps in f.measures.values() for e in by_eps})
    per_eps: dict[str, Any] = {}
    for e in flown:
        at = {a: nested[a][e] for a in nested if e in nested[a]}
        worst = worst_over_attackers(at)
        hmi = sum(any(ms[i].hmi > 0 for ms in at.values()) for i in range(len(worst)))
        top = max(worst, key=lambda w: w["max_error_al"] if np.isfinite(w["max_error_al"]) else -np.inf)
        per_eps[f"{e:g}"] = {
            "max_error_al": _largest([w["max_error_al"] for w in worst]),
            "max_error_al_single": _largest([w["max_error_al_single"] for w in worst]),
            "max_error_pl": _largest([w["max_error_pl"] for w in worst]),
            "final_error_max_m": _largest([w["final_error"] for w in worst]),
            "failed": sum(bool(w["failed"]) for w in worst),
            "trajectories": len(worst),
            "worst_attacker": top["worst_attacker"],
            "hmi_trajectories": _cp_json(clopper_pearson(hmi, len(worst))),
            "stanford": f.stanford.get(e, {}),
            "per_trajectory": [_plain(w) for w in worst],
        }
    records = [(e, m.failed) for by_eps in f.measures.values() for e, ms in by_eps.items() for m in ms]
    clean = f.clean_measures
    return {
        "breaking_eps": breaking_point(records),
        "eps_flown": flown,
        "stopped_at": f.stopped,
        "trajectories": len(f.clean),
        "per_eps": per_eps,
        "attackers": {
            a: {f"{e:g}": [_plain(m.as_dict()) for m in ms] for e, ms in by_eps.items()} for a, by_eps in nested.items()
        },
        "clean": {
            "trajectories": [_plain(m.as_dict()) for m in clean],
            "max_error_al": _largest([m.max_error_al for m in clean]),
            "max_error_al_single": _largest([m.max_error_al_single for m in clean]),
            "max_error_pl": _largest([m.max_error_pl for m in clean]),
            "final_error_max_m": _largest([m.final_error for m in clean]),
            "failed": sum(m.failed for m in clean),
            "availability": f.clean_row["availability"],
            "availability_by_range": availability_by_range([fl.frames for fl in f.clean]),
            "false_alarms": as_json(f.alarms, len(f.clean)),
            "stanford": f.stanford_clean,
        },
    }


def how_it_broke(flights: Flights, breaking: float | None, trusted_start: int) -> list[dict[str, Any]]:
    """How a defended chain broke, measured: at the breaking eps, each failed flight's trajectory and attacker, the
    frame its filter first started on (its first trusted estimate), its first failing frame (error / AL > 1 on an
    available counted frame) and whether that frame lies within the `trusted_start` frames after the start, where the
    protection level assumes no fault and the detector alone guards (assumption A of pipeline/defense/protection.py).
    [] when the chain never broke."""
    out: list[dict[str, Any]] = []
    for name, e, flown, masks in flights.runs:
        if breaking is None or e != breaking:
            continue
        for f, m in zip(flown, masks):
            keep = counted(m) if np.any(m) else np.ones(len(m), bool)
            bad = np.flatnonzero(f.frames.available & keep & (f.frames.error > f.frames.alert))
            if not bad.size:
                continue
            started = np.flatnonzero(np.isfinite(f.frames.trusted[:, 0]))
            start = int(started[0]) if started.size else None
            first = int(bad[0])
            out.append(
                {
                    "trajectory": str(f.frames.trajectory[0]),
                    "attacker": name,
                    "start_frame": start,
                    "first_failure_frame": first,
                    "inside_trusted_start": start is not None and first - start <= int(trusted_start),
                }
            )
    return out
