"""The guidance grid on the engine: pilots that fly runs in any order, on any worker, give the same runs,
outcomes and counts as one in-process pilot (stand-in camera: no Blender, no torch)."""
from __future__ import annotations

import sys

import numpy as np
import pytest

from pipeline.camera import reference_intrinsics
from pipeline.guidance import Estimate, GridPilot, GridPlan, GuidanceSettings, defended_grid, grid_counts, paper_grid
from stages import engine
from test_engine import two_nodes  # noqa: F401  (the two-node local cluster fixture)

K = reference_intrinsics().scaled(160, 90)


class StubCamera:
    """A CachedCamera stand-in: the 'image' is the true position; an estimate is the truth plus
    `attack(image)` on attacked frames, which the detector flags (probability 1)."""

    def __init__(self) -> None:
        self.attack, self.keys = None, set()

    def render(self, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        self.keys.add(np.round(np.concatenate([R.ravel(), t]), 9).tobytes())
        return t

    def estimate(self, image: np.ndarray, attacked: bool, pose: tuple) -> Estimate:
        return Estimate(image + self.attack(image), 1.0) if attacked else Estimate(image, 0.0)


def attack_at(eps: float, i: int):
    """A seeded random bias of about 10 * eps metres, drawn per run and per frame."""
    rng = np.random.default_rng(i)
    return lambda image: 10 * eps * rng.normal(size=3)


def defense():
    from pipeline.defense import DefenseSettings
    from pipeline.motion import MotionSettings, NoiseModel
    from stages.artifacts import DefenseModel

    return DefenseModel(DefenseSettings(hold_after=20), MotionSettings(false_alarm=0.005),
                        NoiseModel((0.05, 0.05, 0.1), (0.004, 0.004, 0.015), 1.0, 0.02), {})


class StubWorker:
    """An engine worker with one stand-in camera (as stages.guidance.GuidanceWorker, without Blender)."""

    def __init__(self, plan: GridPlan) -> None:
        self.pilot = GridPilot(StubCamera(), K, plan, attack_at, defense())

    def run(self, dyn: str, defense_name: str, cell: int | None):
        engine.exit_once_for_test()
        return self.pilot.fly(dyn, defense_name, cell)

    def close(self) -> None:
        pass


def plan() -> GridPlan:
    s = GuidanceSettings(max_steps=70)
    grid = tuple((eps, S, k, s.window(S, k)) for eps in (0.5, 0.1) for S in (40, 20) for k in (5, 15))
    return GridPlan(s, grid, 10, ("paper", "true_state"), ("hold", "recover"))


def summary(p: GridPlan, flown: list) -> tuple:
    """Everything the report is made of: paper grid, defended grid, counts (runs as plain numbers)."""
    results = [r for r, _ in flown]
    baseline, arrival, horizon, runs = paper_grid(p, results)
    defended = defended_grid(p, results)
    paper_keys = frozenset().union(*(k for _, k in flown[:p.paper_size]))
    return ([(r.outcome, r.miss, r.positions.tolist()) for r in results], arrival, horizon,
            [(e, s, k, r.outcome) for e, s, k, r in runs], {k: v for k, v in defended.items() if k != "example"},
            [(name, r.positions.tolist()) for name, r in defended["example"]["runs"]],
            grid_counts(flown[:p.paper_size]), grid_counts(flown[p.paper_size:], paper_keys))


def in_process(p: GridPlan) -> list:
    return engine.run(StubWorker, (p,), p.runs(), engine.EngineSettings(1, None, 60.0, 0))


def test_runs_flown_by_separate_pilots_in_any_order_match_one_pilot():
    p = plan()
    one = in_process(p)
    outcomes = {r.outcome for r, _ in one}
    assert len(outcomes) > 1 and len(one) == 1 + 8 + 5 * 9   # attacks change outcomes: the test can fail
    runs = p.runs()
    order = np.random.default_rng(0).permutation(len(runs))
    apart = [None] * len(runs)
    for j, i in enumerate(order):                   # three pilots, each starting cold, runs shuffled
        apart[i] = StubWorker(p).run(*runs[i]) if j % 3 == 0 else None
    pilots = [StubWorker(p), StubWorker(p)]
    for j, i in enumerate(order):
        if apart[i] is None:
            apart[i] = pilots[j % 2].run(*runs[i])
    assert summary(p, apart) == summary(p, one)


def test_counts_are_those_of_one_shared_camera():
    p = plan()
    worker = StubWorker(p)
    flown = [worker.run(*r) for r in p.runs()]
    counts = grid_counts(flown)
    steps = sum(len(r.estimates) for r, _ in flown)
    assert counts["steps"] == steps and 0 < counts["renders"] < steps
    assert counts["attacked"] == sum(r.attacked.sum() for r, _ in flown) > 0
    paper = grid_counts(flown[:p.paper_size])
    rest = grid_counts(flown[p.paper_size:], frozenset().union(*(k for _, k in flown[:p.paper_size])))
    assert paper["renders"] + rest["renders"] == counts["renders"] and rest["renders"] > 0


@pytest.mark.slow
def test_two_ray_workers_fly_the_grid_of_one_process(two_nodes):
    import ray

    cluster, marker = two_nodes
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])   # the stand-ins live in this test file
    p = plan()
    one = in_process(p)
    two = engine.run(StubWorker, (p,), p.runs(), engine.EngineSettings(2, cluster.address, 60.0, 2))
    assert marker.exists()                          # a worker died mid-run: its run was flown again
    assert summary(p, two) == summary(p, one)
