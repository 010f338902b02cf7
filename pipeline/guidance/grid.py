"""The guidance grid of `rpod guidance`: which closed-loop runs to fly (`GridPlan`), flying them with a
shared image cache (`GridPilot`), and their results as the paper grid and the defended grid.

A grid cell is (eps, S = attack start range in metres, K = attacked frames, AttackWindow); runs use the
closed loop of pipeline/guidance/law.py.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from pipeline.geometry.camera import Intrinsics
from pipeline.guidance.law import HELD, CachedCamera, GuidanceSettings, RendezvousResult, arrival_step, run_rendezvous


def horizon(arrival: int | None, max_steps: int, slack: int) -> int:
    """Steps of an attacked run: the no-attack run's arrival plus `slack`, at most `max_steps` (all of
    them when the no-attack run did not arrive)."""
    return max_steps if arrival is None else min(max_steps, arrival + slack)


def _count(x: np.ndarray | None, value: Any = True) -> int | None:
    return None if x is None else int((x == value).sum())


def defended_record(base: RendezvousResult, arrival: int | None, cells: list[tuple[Any, ...]]) -> dict[str, Any]:
    """One (dynamics, defense) block of `defended_grid`: its no-attack run, every cell, held runs per eps."""
    return {
        "baseline": {"outcome": base.outcome, "miss_m": base.miss, "arrival_step": arrival,
                     "flags": _count(base.flags)},
        "runs": [{"eps": e, "start_range": S, "length": k, "outcome": r.outcome, "miss_m": r.miss,
                  "attacked_frames": r.attacked_frames, "steps": len(r.estimates),
                  "flags": _count(r.flags), "hold_steps": _count(r.modes, "hold")}
                 for e, S, k, r in cells],
        "held": {f"{e:g}": [int(sum(r.outcome == HELD for e2, _, _, r in cells if e2 == e)),
                            int(sum(e2 == e for e2, *_ in cells))] for e in dict.fromkeys(c[0] for c in cells)}}


Run = tuple[str, str, "int | None"]
"""One closed-loop run of a `GridPlan`: (dynamics = settings.variant, defense, grid cell index or None
for that (dynamics, defense)'s no-attack baseline)."""


@dataclass(frozen=True)
class GridPlan:
    """The guidance grid: `settings`, the (eps, S, K, window) cells, `slack_steps`; the paper grid is
    flown under settings.variant undefended, the defended grid under every (`dynamics`, undefended and
    each of `defenses`) except that one (its runs are the paper grid's)."""

    settings: GuidanceSettings
    grid: tuple[tuple[Any, ...], ...]
    slack_steps: int
    dynamics: tuple[str, ...] = ()
    defenses: tuple[str, ...] = ()

    def _block(self, dyn: str, defense: str) -> list[Run]:
        return [(dyn, defense, None), *[(dyn, defense, i) for i in range(len(self.grid))]]

    def runs(self) -> list[Run]:
        """Every run: the paper grid (baseline first), then each defended (dynamics, defense) block."""
        out = self._block(self.settings.variant, "undefended")
        for dyn in self.dynamics:
            out += [r for d in ("undefended", *self.defenses) if (dyn, d) != (self.settings.variant, "undefended")
                    for r in self._block(dyn, d)]
        return out

    @property
    def paper_size(self) -> int:
        return len(self.grid) + 1


class GridPilot:
    """Flies single runs of a `GridPlan` with one `CachedCamera`: `fly(run)` -> (result, keys of the
    poses it rendered). An attacked run's length comes from its block's no-attack baseline (flown here
    first when this pilot has not flown it: runs are deterministic, so any pilot gets the same one);
    `attack_at(eps, i)` is the attack of run i of `plan.runs()` (seeded per run, so the outcome does not
    depend on which pilot flies it or in what order); `defense.new()` a fresh Defense per defended run."""

    def __init__(self, camera: CachedCamera, K: Intrinsics, plan: GridPlan,
                 attack_at: Callable[[float, int], Any], defense: Any = None) -> None:
        self.camera, self.K, self.plan, self.attack_at, self.defense = camera, K, plan, attack_at, defense
        self.index = {r: i for i, r in enumerate(plan.runs())}
        self.baselines: dict[tuple[str, str], RendezvousResult] = {}

    def fly(self, dyn: str, defense: str, cell: int | None) -> tuple[RendezvousResult, frozenset[bytes]]:
        from dataclasses import replace

        p = self.plan
        s, window = replace(p.settings, variant=dyn, defense=defense), None
        self.camera.attack = None
        if cell is not None:
            eps, _, k, window = p.grid[cell]
            arrival = arrival_step(self._baseline(dyn, defense), p.settings.goal, p.settings.tolerance)
            extra = 0 if defense == "undefended" else k   # a held chaser may arrive up to K steps late
            s = replace(s, max_steps=horizon(arrival, p.settings.max_steps, p.slack_steps + extra))
            self.camera.attack = self.attack_at(eps, self.index[(dyn, defense, cell)])
        self.camera.keys = set()
        result = run_rendezvous(self.camera.render, self.camera.estimate, self.K, s, window,
                                defense=None if defense == "undefended" else self.defense.new())
        if cell is None:
            self.baselines[(dyn, defense)] = result
        return result, frozenset(self.camera.keys)

    def _baseline(self, dyn: str, defense: str) -> RendezvousResult:
        if (dyn, defense) not in self.baselines:
            self.fly(dyn, defense, None)
        return self.baselines[(dyn, defense)]


def grid_counts(flown: list[tuple[RendezvousResult, frozenset[bytes]]], seen: frozenset[bytes] = frozenset()
                ) -> dict[str, int]:
    """Guidance steps, distinct rendered poses not in `seen`, attacked frames of these runs: the same
    counts whichever pilots flew them (a shared image cache renders each distinct pose once)."""
    keys = frozenset().union(*(k for _, k in flown)) - seen
    return {"steps": sum(len(r.estimates) for r, _ in flown), "renders": len(keys),
            "attacked": sum(r.attacked_frames for r, _ in flown)}


def paper_grid(plan: GridPlan, results: list[RendezvousResult]
               ) -> tuple[RendezvousResult, int | None, int, list[tuple[Any, ...]]]:
    """The paper grid's results (the first `plan.paper_size` of `plan.runs()`) -> (baseline, arrival,
    horizon of the attacked runs, [(eps, S, K, result)] in grid order)."""
    baseline = results[0]
    arrival = arrival_step(baseline, plan.settings.goal, plan.settings.tolerance)
    runs = [(eps, s, k, r) for (eps, s, k, _), r in zip(plan.grid, results[1:plan.paper_size])]
    return baseline, arrival, horizon(arrival, plan.settings.max_steps, plan.slack_steps), runs


def defended_grid(plan: GridPlan, results: list[RendezvousResult]) -> dict[str, Any]:
    """Every (dynamics, undefended / defense) block of `plan.runs()`'s `results` -> {"dynamics": {dyn:
    {defense: defended_record}}, "defenses", "example": the runs of the last dynamics at the strongest,
    longest, latest-starting cell that every variant flew under attack (a variant that never reached the
    attack's start range is no example of a defense), for a figure}."""
    n = len(plan.grid) + 1
    blocks = {run[:2]: results[i:i + n] for i, run in enumerate(plan.runs()) if run[2] is None}
    out: dict[str, Any] = {"dynamics": {}, "defenses": list(plan.defenses)}
    last = [blocks[(plan.dynamics[-1], d)][1:] for d in ("undefended", *plan.defenses)] if plan.dynamics else []
    attacked_by_all = [i for i in range(len(plan.grid)) if all(flown[i].attacked_frames > 0 for flown in last)]
    pick = max(attacked_by_all or range(len(plan.grid)),
               key=lambda i: (plan.grid[i][0], plan.grid[i][2], -plan.grid[i][1]), default=None)
    example: list[tuple[str, Any]] = []
    for dyn in plan.dynamics:
        out["dynamics"][dyn] = {}
        for defense in ("undefended", *plan.defenses):
            base, *flown = blocks[(dyn, defense)]
            cells = [(eps, s, k, r) for (eps, s, k, _), r in zip(plan.grid, flown)]
            arrival = arrival_step(base, plan.settings.goal, plan.settings.tolerance)
            out["dynamics"][dyn][defense] = defended_record(base, arrival, cells)
            if pick is not None and dyn == plan.dynamics[-1]:
                example.append((defense, flown[pick]))
    e, S, k, _ = plan.grid[pick] if pick is not None else (0.0, 0.0, 0, None)
    out["example"] = {"runs": example, "title": f"{plan.dynamics[-1]} dynamics, eps = {e:g}, S = {S:g} m, K = {k}"}
    return out
