"""The closed loop's mission outcomes (`rpod guidance`): where the shipped chain's runs dock, and the standard
chain's.

Every run of the shipped chain in a guidance grid (pipeline/guidance/grid.py `GridPlan`: the defended grid's
no-attack and attacked runs per dynamics and defense variant, and the in-loop attacker's runs), and every run of the
standard chain (its no-attack run and the in-loop attacker's, reported as "standard <defense>"), is judged by
`pipeline.evaluation.measures.docking`: range and lateral miss against the goal (m), collision, target lost, hold;
mission failure = a collision, a lost target, or a miss beyond the tolerance (a run that ends held far from the goal
is a safe abort; one whose holds spent the steps the approach needed timed out: pipeline/evaluation/measures.py).
Per (dynamics, defense variant): the no-attack run's outcome, per eps the attacked runs that met the attack, how
many failed and the largest miss, and the breaking point: the smallest eps at which an attacked run failed its
mission (0 when the no-attack run already fails), None when none failed. Only the runs that met the attack count (a
run that never reached the attack's start range was not attacked). A defended no-attack run that ends in a hold
says why (`final_hold`): its protection level and the PL's parts against the alert limit where the hold began,
and the PL at the end (after its anchor every PL term only grows until a restart: pipeline/defense/protection.py).
"""

from __future__ import annotations

import math
from typing import Any, Callable, Sequence

import numpy as np

from pipeline.evaluation.measures import breaking_point, docking
from pipeline.guidance.grid import GridPlan, InLoopRun, variant_key
from pipeline.guidance.law import PROTECTION, RendezvousResult


def final_hold(r: RendezvousResult) -> dict[str, Any] | None:
    """Where and why a defended run's last hold began (None when it does not end in a hold or has no record of its
    protection level): {"frame", "true_range_m", "frames_held", and at that frame each PROTECTION column as
    "<column>_m" (None where there is none: a hold on a flag has no PL), "pl_end_m": the PL at the last frame}."""
    if r.protection is None or r.held is None or not len(r.held) or not r.held[-1]:
        return None
    start = len(r.held) - int(np.argmin(r.held[::-1])) if not r.held.all() else 0

    def m(x: float) -> float | None:
        return None if not math.isfinite(x) else float(x)

    return {
        "frame": start,
        "true_range_m": float(np.linalg.norm(r.positions[start])),
        "frames_held": len(r.held) - start,
        **{f"{k}_m": m(v) for k, v in zip(PROTECTION, r.protection[start])},
        "pl_end_m": m(r.protection[-1][0]),
    }


def safety_index(
    r: RendezvousResult, limit: Callable[[np.ndarray], np.ndarray], flies_trusted: bool = True
) -> dict[str, float | None]:
    """What the guidance flew on, judged as the open-loop measures judge a trajectory (pipeline/evaluation/
    measures.py): over the frames whose command was computed from an estimate (`r.acted`; a held frame flies on
    nothing), the largest error of that estimate (m, against the true rel of the frame) over `limit` (the AL at the
    frame's true range, m: the persistent-bias AL) and, where the guidance flies on the trusted estimate
    (`flies_trusted`: detect-and-recover; detect-and-hold flies on the raw estimate, which the PL does not bound),
    over the frame's PL (frames without a PL left out) -> {"max_error_al", "max_error_pl", "frames_flown"} (None
    where no frame counts, or in a result made without `acted`). A max error / AL above 1 is the closed loop's HMI,
    a max error / PL above 1 its MI (the PL failed to bound what was flown)."""
    if r.acted is None:
        return {"max_error_al": None, "max_error_pl": None, "frames_flown": None}
    truth = r.positions[: len(r.acted)]
    error = np.linalg.norm(r.acted - truth, axis=1)
    flown = np.isfinite(error)
    al = np.asarray(limit(np.linalg.norm(truth, axis=1)), dtype=np.float64)
    pl = np.full(len(error), np.nan) if r.protection is None or not flies_trusted else r.protection[:, 0]
    with_pl = flown & np.isfinite(pl) & (pl > 0)

    def largest(x: np.ndarray, keep: np.ndarray) -> float | None:
        return float(x[keep].max()) if keep.any() else None

    return {
        "max_error_al": largest(error / al, flown),
        "max_error_pl": largest(error / np.where(with_pl, pl, 1.0), with_pl),
        "frames_flown": int(flown.sum()),
    }


def _larger(a: float | None, b: float | None) -> float | None:
    """The larger of two figures, either None where there is none."""
    return a if b is None else b if a is None else max(a, b)


def _attack(plan: GridPlan, cell: int | InLoopRun | None) -> tuple[str, float | None]:
    """(what attacked the run, its eps): "none", "fgsm S=.. m K=..", or "in-loop <goal>" (S)."""
    if cell is None:
        return "none", None
    if isinstance(cell, InLoopRun):
        eps, goal, start = plan.in_loop[cell.index]
        return f"in-loop {goal} from {start:g} m", float(eps)
    eps, start, k, _ = plan.grid[cell]
    return f"grid S={start:g} m K={k}", float(eps)


def closed_loop_outcomes(
    plan: GridPlan,
    results: Sequence[RendezvousResult],
    collision_range: float,
    limit: Callable[[np.ndarray], np.ndarray],
) -> dict[str, Any]:
    """The docking of every shipped- and standard-chain run of `plan.runs()`'s `results` (module docstring) ->
    {"runs": one record per run (chain, dynamics, defense: pipeline.guidance.grid.variant_key, attack, eps, met: the
    run met the attack, `Docking.as_dict()` and its `safety_index` against `limit`, the AL (m) at a true range (m)),
    "variants": {dynamics: {defense: {"clean": the no-attack run's docking and safety index, "per_eps": {"%g":
    {"met", "failed", "largest_miss_m", "outcomes": {outcome: count}, "largest_error_al", "largest_error_pl"}},
    "breaking_eps"}}}, "tolerance_m", "collision_range_m"}."""
    s = plan.settings
    runs, variants = [], {}
    for (chain, dyn, defense, cell), r in zip(plan.runs(), results):
        if chain == "paper":
            continue
        d = docking(r, s.goal, s.tolerance, collision_range, s.max_step)
        index = safety_index(r, limit, flies_trusted=defense == "recover")
        attack, eps = _attack(plan, cell)
        met = cell is None or r.attacked_frames > 0
        defense = variant_key(chain, defense)
        runs.append(
            {
                "chain": chain,
                "dynamics": dyn,
                "defense": defense,
                "attack": attack,
                "eps": eps,
                "met": bool(met),
                "steps": len(r.estimates),
                **d.as_dict(),
                **index,
            }
        )
        v = variants.setdefault(dyn, {}).setdefault(defense, {"clean": None, "per_eps": {}, "records": []})
        if cell is None:
            v["clean"] = d.as_dict() | index | ({} if defense == "undefended" else {"final_hold": final_hold(r)})
            v["records"].append((0.0, d.failed))
        elif met:
            k = v["per_eps"].setdefault(f"{eps:g}", {"met": 0, "failed": 0, "largest_miss_m": 0.0, "outcomes": {}})
            k["met"] += 1
            k["failed"] += int(d.failed)
            k["largest_miss_m"] = max(k["largest_miss_m"], d.miss)
            k["outcomes"][d.outcome] = k["outcomes"].get(d.outcome, 0) + 1
            for key in ("error_al", "error_pl"):
                k[f"largest_{key}"] = _larger(k.get(f"largest_{key}"), index[f"max_{key}"])
            v["records"].append((eps, d.failed))
    for by_defense in variants.values():
        for v in by_defense.values():
            v["breaking_eps"] = breaking_point(v.pop("records"))
            v["per_eps"] = dict(sorted(v["per_eps"].items(), key=lambda kv: float(kv[0])))
    return {
        "runs": runs,
        "variants": variants,
        "tolerance_m": float(s.tolerance),
        "collision_range_m": float(collision_range),
    }
