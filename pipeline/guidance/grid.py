"""The guidance grid of `rpod guidance`: which closed-loop runs to fly (`GridPlan`), flying them with a
shared image cache (`GridPilot`), and their results as the paper grid, the defended grid and the
in-loop attacker's runs.

Three chains fly: the paper grid on the "paper" chain (the paper's reproduction), the defended grid with its
undefended reference and the in-loop attacker on the "shipped" chain, and, as the comparison the integrity evidence
asks for, the in-loop attacker on the "standard" chain (the paper's pose model with its own detector and
calibrated defense); a pilot holds a camera per chain (one camera may serve several).

A grid cell is (eps, S = attack start range in metres, K = attacked frames, AttackWindow); runs use the
closed loop of pipeline/guidance/law.py. An in-loop cell is (eps, goal, S): the in-loop attacker
(pipeline/attackers/in_loop.py) attacks every frame from the first at range <= S to the end of the run.
Rates count only the runs that met the attack (a run that never reached S was not attacked).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from pipeline.geometry.camera import Intrinsics
from pipeline.guidance.law import (
    DOCKED,
    AttackWindow,
    CachedCamera,
    GuidanceSettings,
    RendezvousResult,
    arrival_step,
    run_rendezvous,
)
from pipeline.guidance.settings import ExecutionSettings


def horizon(arrival: int | None, max_steps: int, slack: int) -> int:
    """Steps of an attacked run: the no-attack run's arrival plus `slack`, at most `max_steps` (all of
    them when the no-attack run did not arrive)."""
    return max_steps if arrival is None else min(max_steps, arrival + slack)


def _count(x: np.ndarray | None, value: Any = True) -> int | None:
    return None if x is None else int((x == value).sum())


def docked_counts(cells: list[tuple[Any, ...]]) -> dict[str, list[int]]:
    """Per eps ("%g"): [runs docked, runs that met the attack, runs that never met it] of (eps, ..., result) cells."""
    out: dict[str, list[int]] = {}
    for e, *_, r in cells:
        k = out.setdefault(f"{e:g}", [0, 0, 0])
        met = r.attacked_frames > 0
        k[0] += int(met and r.outcome == DOCKED)
        k[1] += int(met)
        k[2] += int(not met)
    return out


def attack_denied(run: RendezvousResult, base: RendezvousResult, tolerance: float) -> bool:
    """Whether the attack kept an attacked run from docking: it met the attack, did not dock, and either its
    no-attack run (same chain, dynamics and defense) docked, or it ended more than `tolerance` (m) further from the
    target point than that run did. A chain that misses by 1.1 m without attack and by 1.2 m under it lost nothing
    to the attack. A denial of docking: a safe abort (a hold) and a timed-out run count as much as a collision;
    whether a run failed its mission (unsafe) is pipeline.evaluation.measures' docking outcome."""
    if run.attacked_frames == 0 or run.outcome == DOCKED:
        return False
    return base.outcome == DOCKED or run.miss > base.miss + tolerance


def defended_record(
    base: RendezvousResult, arrival: int | None, cells: list[tuple[Any, ...]], tolerance: float
) -> dict[str, Any]:
    """One (dynamics, defense) block of `defended_grid`: its no-attack run, every cell (`attack_denied`, with the
    docking `tolerance` in metres), and per eps the runs docked of those that met the attack (`docked`: [docked,
    met]), the runs the attack kept from docking (`denied`: [denied, met]) and the runs that never met it."""
    counts = docked_counts(cells)
    denied: dict[str, list[int]] = {}
    for e, *_, r in cells:
        if r.attacked_frames > 0:
            k = denied.setdefault(f"{e:g}", [0, 0])
            k[0] += int(attack_denied(r, base, tolerance))
            k[1] += 1
    return {
        "baseline": {
            "outcome": base.outcome,
            "miss_m": base.miss,
            "arrival_step": arrival,
            "flags": _count(base.flags),
        },
        "runs": [
            {
                "eps": e,
                "start_range": S,
                "length": k,
                "outcome": r.outcome,
                "miss_m": r.miss,
                "attacked_frames": r.attacked_frames,
                "steps": len(r.estimates),
                "flags": _count(r.flags),
                "hold_steps": _count(r.modes, "hold"),
                "attack_denied": attack_denied(r, base, tolerance),
            }
            for e, S, k, r in cells
        ],
        "docked": {e: v[:2] for e, v in counts.items()},
        "denied": denied,
        "not_met": {e: v[2] for e, v in counts.items()},
    }


@dataclass(frozen=True)
class InLoopRun:
    """The run of a `GridPlan` that flies `plan.in_loop[index]` with the in-loop attacker."""

    index: int


CHAINS = ("paper", "shipped", "standard")  # the chain a run flies: the paper grid's, the one that ships, or the
# paper's model defended (the comparison of the in-loop attacker)

Run = tuple[str, str, str, "int | InLoopRun | None"]
"""One closed-loop run of a `GridPlan`: (chain: one of CHAINS, dynamics = settings.variant, defense,
grid cell index, an `InLoopRun`, or None for that (chain, dynamics, defense)'s no-attack baseline)."""


def variant_key(chain: str, defense: str) -> str:
    """The name a run's (chain, defense) is reported under: the defense on the shipped chain ("undefended",
    "hold", "recover"), "<chain> <defense>" on another (e.g. "standard recover")."""
    return defense if chain == "shipped" else f"{chain} {defense}"


@dataclass(frozen=True)
class GridPlan:
    """The guidance grid: `settings`, the (eps, S, K, window) cells, `slack_steps`; the paper grid is
    flown on the paper chain under settings.variant undefended, the defended grid on the shipped chain under
    every (`dynamics`, undefended and each of `defenses`). `in_loop`: the in-loop attacker's (eps, goal, S)
    cells, flown last on the shipped chain under every (dynamics of `in_loop_dynamics`, default every one of
    `dynamics`; undefended and each defense) and then on the standard chain under the same dynamics and each of
    `standard_defenses` (its no-attack run first). `execution`: how every true_state run executes its commands
    (pipeline/guidance/dynamics.py; None: exactly); the paper dynamics never take it."""

    settings: GuidanceSettings
    grid: tuple[tuple[Any, ...], ...]
    slack_steps: int
    dynamics: tuple[str, ...] = ()
    defenses: tuple[str, ...] = ()
    in_loop: tuple[tuple[float, str, float], ...] = ()
    execution: ExecutionSettings | None = None
    in_loop_dynamics: tuple[str, ...] = ()
    standard_defenses: tuple[str, ...] = ()

    def _block(self, chain: str, dyn: str, defense: str) -> list[Run]:
        return [(chain, dyn, defense, None), *[(chain, dyn, defense, i) for i in range(len(self.grid))]]

    def runs(self) -> list[Run]:
        """Every run: the paper grid (baseline first), then each defended (dynamics, defense) block,
        then the in-loop runs."""
        out = self._block("paper", self.settings.variant, "undefended")
        for dyn in self.dynamics:
            out += [r for d in ("undefended", *self.defenses) for r in self._block("shipped", dyn, d)]
        return out + self.in_loop_runs()

    def in_loop_runs(self) -> list[Run]:
        """The in-loop runs: per dynamics (`in_loop_dynamics`, else `dynamics`, else settings.variant), undefended and
        each defense, each cell, on the shipped chain; then, when there are cells, per dynamics and each of
        `standard_defenses` the standard chain's no-attack run and each cell (last, so the runs before keep their
        places and seeds)."""
        dynamics = self.in_loop_dynamics or self.dynamics or (self.settings.variant,)
        cells = [InLoopRun(i) for i in range(len(self.in_loop))]
        shipped = [("shipped", dyn, d, c) for dyn in dynamics for d in ("undefended", *self.defenses) for c in cells]
        standard = [("standard", dyn, d, c) for dyn in dynamics for d in self.standard_defenses for c in [None, *cells]]
        return shipped + (standard if cells else [])

    @property
    def paper_size(self) -> int:
        return len(self.grid) + 1


def baseline_steps(plan: GridPlan) -> int:
    """Closed-loop steps of the plan's no-attack runs, one per (chain, dynamics, defense) block: each lasts
    settings.max_steps steps unless it loses the target, so a grid costs at least these."""
    return sum(cell is None for *_, cell in plan.runs()) * plan.settings.max_steps


class GridPilot:
    """Flies single runs of a `GridPlan` with a `CachedCamera` per chain (`cameras`: {"paper": ..., "shipped": ...},
    or one camera for both): `fly(run)` -> (result, keys of the poses it rendered). An attacked run's length comes
    from its block's no-attack baseline (flown here first when this pilot has not flown it: runs are
    deterministic, so any pilot gets the same one); `attack_at(chain, eps, i)` is the attack of run i of
    `plan.runs()` on that chain (seeded per run, so the outcome does not depend on which pilot flies it or in
    what order); `in_loop_at(eps, goal, i)` the in-loop attacker (pipeline.attackers.in_loop.InLoopAttacker) of
    run i, `defense.new()` a fresh Defense per defended run: each one for every chain, or a dict per chain as
    `cameras`."""

    def __init__(
        self,
        cameras: CachedCamera | dict[str, CachedCamera],
        K: Intrinsics,
        plan: GridPlan,
        attack_at: Callable[[str, float, int], Any] | None,
        defense: Any = None,
        in_loop_at: Callable[[float, str, int], Any] | dict[str, Callable[[float, str, int], Any]] | None = None,
    ) -> None:
        self.cameras = cameras if isinstance(cameras, dict) else dict.fromkeys(CHAINS, cameras)
        self.K, self.plan, self.attack_at = K, plan, attack_at
        self.defenses = defense if isinstance(defense, dict) else dict.fromkeys(CHAINS, defense)
        self.in_loop_at = in_loop_at if isinstance(in_loop_at, dict) else dict.fromkeys(CHAINS, in_loop_at)
        self.index = {r: i for i, r in enumerate(plan.runs())}
        self.baselines: dict[tuple[str, str, str], RendezvousResult] = {}

    def fly(
        self, chain: str, dyn: str, defense: str, cell: int | InLoopRun | None
    ) -> tuple[RendezvousResult, frozenset[bytes]]:
        from dataclasses import replace

        p, camera = self.plan, self.cameras[chain]
        execution = None if dyn == "paper" else p.execution  # the paper's dynamics: prediction = truth
        s, window, observe = replace(p.settings, variant=dyn, defense=defense, execution=execution), None, None
        camera.attack = None
        if cell is not None:
            arrival = arrival_step(self._baseline(chain, dyn, defense), p.settings.goal, p.settings.tolerance)
            i = self.index[(chain, dyn, defense, cell)]
            if isinstance(cell, InLoopRun):  # attacked to the end; a defended chaser may hold for slack more steps
                eps, goal, start = p.in_loop[cell.index]
                window, extra = AttackWindow(start, p.settings.max_steps), p.slack_steps
                camera.attack = attacker = self.in_loop_at[chain](eps, goal, i)
                observe = attacker.observe
            else:
                eps, _, k, window = p.grid[cell]
                extra = k  # a chaser that holds on flags may arrive up to K steps late
                camera.attack = self.attack_at(chain, eps, i)
            extra = 0 if defense == "undefended" else extra
            s = replace(s, max_steps=horizon(arrival, p.settings.max_steps, p.slack_steps + extra))
        camera.keys = set()
        result = run_rendezvous(
            camera.render,
            camera.estimate,
            self.K,
            s,
            window,
            defense=None if defense == "undefended" else self.defenses[chain].new(),
            observe=observe,
        )
        if cell is None:
            self.baselines[(chain, dyn, defense)] = result
        return result, frozenset(camera.keys)

    def _baseline(self, chain: str, dyn: str, defense: str) -> RendezvousResult:
        if (chain, dyn, defense) not in self.baselines:
            self.fly(chain, dyn, defense, None)
        return self.baselines[(chain, dyn, defense)]


def grid_counts(
    flown: list[tuple[RendezvousResult, frozenset[bytes]]], seen: frozenset[bytes] = frozenset()
) -> dict[str, int]:
    """Guidance steps, distinct rendered poses not in `seen`, attacked frames of these runs: the same
    counts whichever pilots flew them (a shared image cache renders each distinct pose once)."""
    keys = frozenset().union(*(k for _, k in flown)) - seen
    return {
        "steps": sum(len(r.estimates) for r, _ in flown),
        "renders": len(keys),
        "attacked": sum(r.attacked_frames for r, _ in flown),
    }


def paper_grid(
    plan: GridPlan, results: list[RendezvousResult]
) -> tuple[RendezvousResult, int | None, int, list[tuple[Any, ...]]]:
    """The paper grid's results (the first `plan.paper_size` of `plan.runs()`) -> (baseline, arrival,
    horizon of the attacked runs, [(eps, S, K, result)] in grid order)."""
    baseline = results[0]
    arrival = arrival_step(baseline, plan.settings.goal, plan.settings.tolerance)
    runs = [(eps, s, k, r) for (eps, s, k, _), r in zip(plan.grid, results[1 : plan.paper_size])]
    return baseline, arrival, horizon(arrival, plan.settings.max_steps, plan.slack_steps), runs


def defended_grid(plan: GridPlan, results: list[RendezvousResult]) -> dict[str, Any]:
    """Every (dynamics, undefended / defense) block of the shipped chain in `plan.runs()`'s `results` -> {"dynamics": {dyn:
    {defense: defended_record}}, "defenses", "example": the runs of the last dynamics at the strongest,
    longest, latest-starting cell that every variant flew under attack (a variant that never reached the
    attack's start range is no example of a defense), for a figure}."""
    n = len(plan.grid) + 1
    blocks = {
        run[1:3]: results[i : i + n] for i, run in enumerate(plan.runs()) if run[0] == "shipped" and run[3] is None
    }
    out: dict[str, Any] = {"dynamics": {}, "defenses": list(plan.defenses)}
    last = [blocks[(plan.dynamics[-1], d)][1:] for d in ("undefended", *plan.defenses)] if plan.dynamics else []
    attacked_by_all = [i for i in range(len(plan.grid)) if all(flown[i].attacked_frames > 0 for flown in last)]
    pick = max(
        attacked_by_all or range(len(plan.grid)),
        key=lambda i: (plan.grid[i][0], plan.grid[i][2], -plan.grid[i][1]),
        default=None,
    )
    example: list[tuple[str, Any]] = []
    for dyn in plan.dynamics:
        out["dynamics"][dyn] = {}
        for defense in ("undefended", *plan.defenses):
            base, *flown = blocks[(dyn, defense)]
            cells = [(eps, s, k, r) for (eps, s, k, _), r in zip(plan.grid, flown)]
            arrival = arrival_step(base, plan.settings.goal, plan.settings.tolerance)
            out["dynamics"][dyn][defense] = defended_record(base, arrival, cells, plan.settings.tolerance)
            if pick is not None and dyn == plan.dynamics[-1]:
                example.append((defense, flown[pick]))
    e, S, k, _ = plan.grid[pick] if pick is not None else (0.0, 0.0, 0, None)
    out["example"] = {"runs": example, "title": f"{plan.dynamics[-1]} dynamics, eps = {e:g}, S = {S:g} m, K = {k}"}
    return out


def in_loop_grid(plan: GridPlan, results: list[RendezvousResult], collision_range: float) -> dict[str, Any]:
    """The in-loop runs of `plan.runs()`'s `results` -> {"runs": one record per attacked run (chain, dynamics, defense:
    its `variant_key`, eps, goal, S, outcome, collided: closest range < `collision_range` (m), closest range and miss (m),
    steps, attacked frames, flags, hold steps, ended in hold), "counts": per (dynamics, defense, eps)
    [collisions, not docked without a collision, docked, runs that met the attack,
    runs that never met it] over goals and start ranges}."""
    first = len(plan.runs()) - len(plan.in_loop_runs())
    runs, counts = [], {}
    for (chain, dyn, defense, cell), r in zip(plan.in_loop_runs(), results[first:]):
        if cell is None:  # another chain's no-attack run (closed_loop_outcomes judges it)
            continue
        eps, goal, start = plan.in_loop[cell.index]
        collided = r.closest_range < collision_range
        defense = variant_key(chain, defense)
        runs.append(
            {
                "chain": chain,
                "dynamics": dyn,
                "defense": defense,
                "eps": eps,
                "goal": goal,
                "start_range": start,
                "outcome": r.outcome,
                "collided": bool(collided),
                "closest_range_m": r.closest_range,
                "miss_m": r.miss,
                "steps": len(r.estimates),
                "attacked_frames": r.attacked_frames,
                "flags": _count(r.flags),
                "hold_steps": _count(r.modes, "hold"),
                "ended_in_hold": None if r.modes is None or not len(r.modes) else bool(r.modes[-1] == "hold"),
            }
        )
        k = counts.setdefault(dyn, {}).setdefault(defense, {}).setdefault(f"{eps:g}", [0, 0, 0, 0, 0])
        met = r.attacked_frames > 0
        k[0] += int(met and collided)
        k[1] += int(met and not collided and r.outcome != DOCKED)
        k[2] += int(met and not collided and r.outcome == DOCKED)
        k[3] += int(met)
        k[4] += int(not met)
    return {"runs": runs, "counts": counts, "collision_range_m": float(collision_range)}
