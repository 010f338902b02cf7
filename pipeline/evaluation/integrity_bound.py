"""The integrity bound of one chain on recorded trajectories (issue 40), as JSON-ready dicts: per trajectory and
eps the worst trusted error that fault sequences within the attacker's capacity F(eps, range)
(pipeline/attacks/capacity.py) cause without tripping a check of the chain's defense
(pipeline/defense/bound.py `worst_case`, which solves the program and replays it), against the alert limit AL and
the protection level PL; beside it the same attacker sparing the frames the PL assumes fault-free (its assumption
A); and the interval-bound certificate of the pose network (pipeline/pose/certify.py) on a sample of frames,
against the capacity.

The detector is modelled as blind: every frame keeps the detector probability of the clean run (its doubt and
flags), so the attacker neither trips it nor is slowed by it. F is what the caller measured (an empirical
overbound: a quantile of the strongest suite's shifts times (1 + margin)), not a certificate.

Per trajectory (`bound_run`; `bound_track` first reads its frames through the chain): the real defense records
the filter's choices on the clean run; the targets are every `stride`-th frame from the filter's first start, and
the last frame. Per eps and target frame n, `worst_case` gives the program's upper bound on the trusted error at n
(m), the feasible attack's error replayed through the real defense (m), the replay's PL, and whether the replay
reproduced the program. Two attackers per eps:
- `bound`: F on every frame from the first on (the start and the trusted-start frames included);
- `spared`: F on the frames after the PL's anchor T only (T: the `trusted_start`-th frame the sequential test saw
  after the first start; `trusted_frame`): the attacker the PL claims to bound. Its achieved / PL above 1 is
  misleading information under the PL's own assumptions.
Measures per attacker (over the trajectory's modelled targets, `_measures`): the largest upper / AL (the bound's
safety index against the AL), its frame and true range; the largest upper (m); the replayed attack's largest error
(m) and error / AL; the largest upper / PL and achieved / PL (above 1: the PL missed a real attack); the targets
with upper / AL > 1 (all and available ones: PL <= AL and flown); the share of replays that reproduced the program.
A target after the clean run's first restart is not modelled (the program stops there; counted as `unmodelled`).
Once per trajectory, a third attacker limited by the checks alone (`checks_only`: no capacity, sparing the trusted
frames): its replayed error is a floor under any PL sound against it with these checks, so the share of target
frames where that error stays within AL (`checks_only_rates`) is a ceiling on the availability such a PL can have.

Over trajectories (`worst_over_trajectories`) the largest of each index, the trajectories whose bound exceeds AL,
and `first_over(per_eps)`: the smallest eps whose bound exceeds AL on some trajectory; `over_al_rate`: the share
of target frames whose bound exceeds AL, with a 95% interval bootstrapped over trajectories.
"""

from __future__ import annotations

import time
from functools import partial
from typing import Any, Callable, Sequence

import numpy as np

from pipeline.attacks.capacity import Capacity, capacity_at
from pipeline.defense.bound import ACCEPT, ALARM, HUBER, Recording, WorstCase, record, worst_case
from pipeline.defense.calibration import CleanRun
from pipeline.defense.chain import Defended, OnboardChain
from pipeline.defense.fusion import HOLD
from pipeline.defense.integrity import AlertLimitSettings, alert_limit
from pipeline.evaluation.integrity_runs import Track
from pipeline.evaluation.robustness import pose_estimates
from pipeline.stats import Rate, bootstrap_rate

ATTACKERS = ("bound", "spared")  # F from the first frame on | F after the PL's trusted frames only (assumption A)
TESTED = (ACCEPT, HUBER, ALARM)  # the filter choices on frames the sequential test saw (the trusted-start count)


def targets_of(n: int, start: int, stride: int) -> list[int]:
    """Target frames of an n-frame run whose filter starts at `start`: every `stride`-th frame from it, and the
    last frame (none when the filter never starts)."""
    if stride < 1:
        raise ValueError(f"bound: stride must be >= 1, got {stride}")
    return sorted(set(range(start, n, stride)) | {n - 1}) if start < n else []


def trusted_frame(rec: Recording, trusted_start: int) -> int:
    """The PL's anchor T of a recorded run: the `trusted_start`-th frame after the first start that the sequential
    test saw (assumption A of pipeline/defense/protection.py spares the start and the frames up to T); the start
    itself when `trusted_start` is 0; the last frame when the test never saw that many."""
    if trusted_start == 0:
        return rec.start
    tested = np.flatnonzero(np.isin(rec.kind, TESTED) & (np.arange(len(rec.kind)) > rec.start))
    return int(tested[trusted_start - 1]) if len(tested) >= trusted_start else len(rec.kind) - 1


def _largest(values: np.ndarray) -> float | None:
    """The largest finite value (None when there is none)."""
    v = np.asarray(values, np.float64)
    v = v[np.isfinite(v)]
    return float(v.max()) if v.size else None


def _measures(w: WorstCase, range_m: np.ndarray) -> dict[str, Any]:
    """The measures of one attacker's `worst_case` over its modelled targets (module docstring); `range_m` (N,)
    the trajectory's true range per frame (m)."""
    ok = np.isfinite(w.upper)
    out: dict[str, Any] = {"targets": int(len(w.targets)), "unmodelled": int((~ok).sum()), "seconds": w.seconds}
    if not ok.any():
        return {**out, "max_error_al": None}
    ratio = np.where(ok, w.ratio, -np.inf)
    k = int(np.argmax(ratio))
    over = ok & (w.ratio > 1)
    return {
        **out,
        "max_error_al": float(w.ratio[k]),
        "frame": int(w.targets[k]),
        "range_m": float(range_m[w.targets[k]]),
        "max_error_m": _largest(w.upper),
        "max_achieved_m": _largest(w.achieved),
        "max_achieved_al": _largest(w.achieved / w.alert),
        "max_error_pl": _largest(w.upper / w.pl),
        "max_achieved_pl": _largest(w.pl_index),
        "over_al": int(over.sum()),
        "over_al_available": int((over & w.available).sum()),
        "exact": float(np.mean(w.exact[ok])),
    }


def bound_run(
    defended: Defended,
    name: str,
    run: CleanRun,
    truth: np.ndarray,
    capacities: Sequence[Capacity],
    eps: Sequence[float],
    stride: int,
    limit: AlertLimitSettings,
    progress: Callable[[], Any] = lambda: None,
) -> dict[str, Any]:
    """One trajectory's clean run `run` (pose network estimates and detector probabilities, camera attitudes,
    commands) with the true rel `truth` (N, 3) (world, m) through `defended` (module docstring): per eps of `eps`
    (L-inf, pixels in [0, 1]) and attacker of ATTACKERS the `_measures` of `worst_case` at the target frames, with F
    per frame from `capacities` (`capacity_at`: the smallest measured eps >= each eps) at the true range, and AL of
    `limit` at the true range; per attacker also `ratio`, upper / AL per target (None where unmodelled), for the
    rates over trajectories; `progress()` after each (eps, attacker). ValueError when a frame's range lies outside
    the capacity's bins or an eps above every measured one."""
    rng = np.linalg.norm(truth, axis=1)
    al = alert_limit(rng, limit)
    d, limit_fn = defended, partial(alert_limit, settings=limit)
    clean = record(d.settings, d.motion, d.noise, run, alert_limit=limit_fn)
    n, trusted = len(run.pose), trusted_frame(clean, d.motion.trusted_start)
    targets = targets_of(n, clean.start, stride)
    error = np.linalg.norm(clean.trace.trusted - truth, axis=1)
    out: dict[str, Any] = {
        "name": name,
        "frames": n,
        "start": clean.start,
        "trusted_frame": trusted,
        "restart": None if clean.horizon == n else clean.horizon,
        "range_m": [float(rng[0]), float(rng[-1])],
        "targets": targets,
        "clean": {
            "max_error_m": _largest(error),
            "max_error_al": _largest(error / al),
            "max_error_pl": _largest(error / clean.trace.pl),
        },
        "per_eps": {},
    }
    out["checks_only"] = checks_only(d, run, truth, clean, trusted, stride, al, limit_fn)
    progress()
    for e in eps:
        cap = capacity_at(capacities, float(e), rng)
        spared = cap.copy()
        spared[: trusted + 1] = 0.0
        row = {}
        for who, box, frames in (("bound", cap, targets), ("spared", spared, [j for j in targets if j > trusted])):
            w = worst_case(d.settings, d.motion, d.noise, run, truth, box, al, targets=frames, alert_limit=limit_fn)
            row[who] = {**_measures(w, rng), "ratio": [float(v) if np.isfinite(v) else None for v in w.ratio]}
            progress()
        out["per_eps"][f"{float(e):g}"] = {
            "capacity_eps": min(c.eps for c in capacities if c.eps >= float(e)),
            "capacity_start_m": cap[clean.start].tolist() if clean.start < n else None,
            **row,
        }
    return out


def checks_only(
    defended: Defended,
    run: CleanRun,
    truth: np.ndarray,
    clean: Recording,
    trusted: int,
    stride: int,
    alert: np.ndarray,
    alert_limit: Callable[[float], float],
) -> dict[str, Any]:
    """The attacker limited by the checks alone (no capacity): a box as wide as the true range on every axis (m)
    on the frames after the PL's anchor `trusted` (none before: assumption A), with `clean` the clean run's
    recording and `alert` (N,) AL at the true range (m). Its replayed error (a sequence that passes every check
    with the clean run's flags, through the real defense) is a floor for any protection level sound against it with
    these checks: where it exceeds AL, no such PL can make the frame available.

    Targets: every frame from the start whose AL is below the clean run's largest PL (where a PL of the chain's
    size could be unavailable), the others every `stride`-th frame, each standing for the frames up to the next
    target (`weight`, so that the weights count every frame from the start once). Per target: `achieved_al`
    (replayed error / AL; None where unmodelled), `flown` (the clean run's mode is not hold), `pl_available` (flown
    and the clean run's PL <= AL); `goal`: the last frame's replayed error, AL and PL (m); `largest_shift_range`:
    the largest shift the worst sequences used over the true range (below 1: the box did not bind)."""
    truth = np.asarray(truth, np.float64)
    rng, n = np.linalg.norm(truth, axis=1), len(truth)
    pl = clean.trace.pl
    finite = pl[np.isfinite(pl)]
    dense = (alert < (finite.max() if finite.size else 0.0)) & (np.arange(n) >= clean.start)
    tg = np.array(sorted(set(targets_of(n, clean.start, stride)[:-1]) | set(np.flatnonzero(dense).tolist())), int)
    tg = tg[tg < n]
    if tg.size and tg[-1] != n - 1 and clean.start < n:
        tg = np.append(tg, n - 1)
    weight = np.diff(np.append(tg, n)) if tg.size else tg
    box = np.repeat(rng[:, None], 3, axis=1)
    box[: trusted + 1] = 0.0
    d = defended
    w = worst_case(d.settings, d.motion, d.noise, run, truth, box, alert, targets=tg, alert_limit=alert_limit)
    ok = np.isfinite(w.achieved)
    flown = clean.trace.mode[tg] != HOLD
    shift = np.linalg.norm(w.shift, axis=2) / rng[None, :]
    return {
        **_measures(w, rng),
        "targets": tg.tolist(),
        "weight": weight.tolist(),
        "achieved_al": [float(v) if k else None for v, k in zip(w.achieved / w.alert, ok)],
        "flown": flown.tolist(),
        "pl_available": (flown & (pl[tg] <= alert[tg])).tolist(),
        "goal": {"achieved_m": _largest(w.achieved[-1:]), "alert_m": _largest(w.alert[-1:]), "pl_m": _largest(pl[-1:])},
        "largest_shift_range": float(shift.max()) if shift.size else 0.0,
    }


def checks_only_rates(tracks: Sequence[dict[str, Any]], seed: int = 0) -> dict[str, Any]:
    """Over the `bound_run` outputs `tracks`, every frame from the filter's start counted once (each target's
    `weight`; unmodelled targets left out): `ceiling`, the share of frames a PL sound against the checks-only
    attacker could make available at most (flown and its replayed error <= AL), beside `pl`, the share the chain's
    PL made available; each with its 95% interval bootstrapped over trajectories; the replayed error at the last
    frame (m: median, largest) against AL and the PL there; the largest shift over range."""
    hits: dict[str, list[bool]] = {"ceiling": [], "pl": []}
    groups: list[int] = []
    for g, t in enumerate(tracks):
        c = t["checks_only"]
        for ratio, flown, avail, k in zip(c["achieved_al"], c["flown"], c["pl_available"], c["weight"]):
            if ratio is None:
                continue
            hits["ceiling"] += [bool(flown and ratio <= 1.0)] * k
            hits["pl"] += [bool(avail)] * k
            groups += [g] * k
    goal = [t["checks_only"]["goal"] for t in tracks if t["checks_only"]["goal"]["achieved_m"] is not None]
    out: dict[str, Any] = {}
    for key, h in hits.items():
        r = bootstrap_rate(np.array(h, bool), np.array(groups, int), seed=seed)
        out[key] = {"value": r.value if r.n else None, "ci": r.ci(), "n": r.n}
    return {
        **out,
        "targets": sum(len(t["checks_only"]["targets"]) for t in tracks),
        "goal_achieved_m": {
            "median": float(np.median([g["achieved_m"] for g in goal])) if goal else None,
            "max": _largest(np.array([g["achieved_m"] for g in goal])),
        },
        "goal_alert_m": _largest(np.array([g["alert_m"] for g in goal])),
        "goal_pl_m": {
            "min": float(min(g["pl_m"] for g in goal)) if goal else None,
            "max": _largest(np.array([g["pl_m"] for g in goal])),
        },
        "max_achieved_al": _largest(np.array([t["checks_only"].get("max_achieved_al") or np.nan for t in tracks])),
        "largest_shift_range": _largest(np.array([t["checks_only"]["largest_shift_range"] for t in tracks])),
        "trajectories": len(tracks),
    }


def bound_track(
    chain: OnboardChain,
    defended: Defended,
    track: Track,
    capacities: Sequence[Capacity],
    eps: Sequence[float],
    stride: int,
    limit: AlertLimitSettings,
    batch_size: int = 64,
    progress: Callable[[], Any] = lambda: None,
) -> dict[str, Any]:
    """`bound_run` of one recorded trajectory: `chain` reads each frame once (its clean run), then the program
    runs over it; `chain_seconds`: the chain's wall time (s)."""
    t0 = time.perf_counter()
    est, prob = pose_estimates(chain, track.images, batch_size)
    chain_s = time.perf_counter() - t0
    out = bound_run(
        defended,
        track.name,
        CleanRun(est, prob, track.R_cam, track.u),
        track.truth,
        capacities,
        eps,
        stride,
        limit,
        progress,
    )
    return {**out, "chain_seconds": chain_s}


def over_al_rate(tracks: Sequence[dict[str, Any]], eps: str, attacker: str = "bound", seed: int = 0) -> Rate:
    """The share of modelled target frames, over the `bound_run` outputs `tracks` at `eps`, whose bound exceeds AL
    (upper / AL > 1), with its 95% interval from a bootstrap over trajectories (a trajectory's frames are
    correlated: they resample together)."""
    hits, groups = [], []
    for g, t in enumerate(tracks):
        ratio = [r for r in t["per_eps"][eps][attacker]["ratio"] if r is not None]
        hits += [r > 1.0 for r in ratio]
        groups += [g] * len(ratio)
    return bootstrap_rate(np.array(hits, bool), np.array(groups, int), seed=seed)


def worst_over_trajectories(tracks: Sequence[dict[str, Any]], eps: str) -> dict[str, Any]:
    """Per attacker at `eps` (a key of each track's per_eps) over the `bound_track` outputs `tracks`: the largest of
    each index (None where no trajectory has it), the trajectory of the largest upper / AL, the trajectories whose
    bound exceeds AL (on some target, and on an available one), and the share of exact replays."""
    out: dict[str, Any] = {}
    for name in ATTACKERS:
        rows = [(t["name"], t["per_eps"][eps][name]) for t in tracks]
        exact = [m["exact"] for _, m in rows if "exact" in m]
        found = [(m["max_error_al"], t) for t, m in rows if m["max_error_al"] is not None]
        out[name] = {
            key: _largest([m.get(key) if m.get(key) is not None else np.nan for _, m in rows])
            for key in (
                "max_error_al",
                "max_error_m",
                "max_achieved_m",
                "max_achieved_al",
                "max_error_pl",
                "max_achieved_pl",
            )
        }
        out[name].update(
            worst_trajectory=max(found)[1] if found else None,
            over_al=sum(bool(m.get("over_al")) for _, m in rows),
            over_al_available=sum(bool(m.get("over_al_available")) for _, m in rows),
            trajectories=len(rows),
            unmodelled=sum(m["unmodelled"] for _, m in rows),
            exact=float(np.mean(exact)) if exact else None,
        )
    return out


def first_over(per_eps: dict[str, dict[str, Any]], attacker: str = "bound") -> float | None:
    """The smallest eps (keys of `per_eps`, `worst_over_trajectories` outputs) at which `attacker`'s bound exceeds
    AL on some trajectory; None when it stays within AL at every eps."""
    over = [float(e) for e, row in per_eps.items() if (row[attacker]["max_error_al"] or 0.0) > 1.0]
    return min(over) if over else None


def certificate(
    model: Any, track: Track, capacities: Sequence[Capacity], eps: Sequence[float], frames: int
) -> dict[str, Any]:
    """Interval bound propagation's certified shift of the estimated position along the true line of sight
    (sum_i |los_i| x the certified shift on camera axis i, m; pipeline/pose/certify.py) on `frames` frames of
    `track` spread evenly over it, per eps beside the capacity F along the line of sight there (m): medians, their
    ratio, and `vacuous`: the certificate exceeds the true range on every frame (it cannot even keep the estimate in
    front of the camera). `seconds`: wall time."""
    import torch

    from pipeline.pose.certify import certified_shift

    t0 = time.perf_counter()
    ix = np.unique(np.linspace(0, len(track) - 1, max(1, min(frames, len(track)))).round().astype(int))
    x = track.frames(ix)
    t = np.asarray(track.labels[ix, :3], np.float64)
    rng = np.linalg.norm(t, axis=1)
    los = t / rng[:, None]
    out: dict[str, Any] = {"track": track.name, "frames": ix.tolist(), "per_eps": {}}
    for e in eps:
        with torch.no_grad():
            shift = certified_shift(model, x, float(e)).numpy()
        along = np.einsum("ni,ni->n", np.abs(los), shift)
        cap = capacity_at(capacities, float(e), rng)[:, 0]
        out["per_eps"][f"{float(e):g}"] = {
            "certified_along_median_m": float(np.median(along)),
            "certified_along_min_m": float(along.min()),
            "capacity_along_median_m": float(np.median(cap)),
            "ratio_median": float(np.median(along / cap)),
            "vacuous": bool((along > rng).all()),
        }
    out["seconds"] = time.perf_counter() - t0
    return out
