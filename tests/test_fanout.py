"""The guidance grid and the attack sets on the engine: pilots that fly runs in any order, on any worker,
give the same runs, outcomes and counts as one in-process pilot (stand-in camera: no Blender, no
torch), and two Ray workers write the adversarial sets of one process (a tiny random pose model)."""

from __future__ import annotations

import sys

import numpy as np
import pytest
from faults import exits_once
from test_engine import two_nodes  # noqa: F401  (the two-node local cluster fixture)

from pipeline.geometry.camera import reference_intrinsics
from pipeline.guidance.grid import GridPilot, GridPlan, defended_grid, grid_counts, paper_grid
from pipeline.guidance.law import Estimate, GuidanceSettings
from stages.engine import pool as engine
from stages.engine.guidance_worker import Flight, flights

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


def attack_at(chain: str, eps: float, i: int):
    """A seeded random bias of about 10 * eps metres (twice that on the paper chain), drawn per run and per frame."""
    rng = np.random.default_rng(i)
    eps = 2 * eps if chain == "paper" else eps
    return lambda image: 10 * eps * rng.normal(size=3)


def defense():
    from pipeline.defense.chain import Defended
    from pipeline.defense.gate import MotionSettings
    from pipeline.defense.noise import NoiseModel
    from pipeline.defense.settings import DefenseSettings

    return Defended(
        DefenseSettings(hold_after=20),
        MotionSettings(false_alarm=0.005),
        NoiseModel((0.05, 0.05, 0.1), (0.004, 0.004, 0.015), 1.0, 0.02),
    )


class StubWorker:
    """An engine worker with one stand-in camera (as stages.engine.guidance_worker.GuidanceWorker, without
    Blender); its setup is the plan itself."""

    def __init__(self, plan: GridPlan) -> None:
        self.pilot = GridPilot(StubCamera(), K, plan, attack_at, defense())

    def run(self, job: Flight):
        return self.pilot.fly(job.chain, job.dynamics, job.defense, job.cell)

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
    paper_keys = frozenset().union(*(k for _, k in flown[: p.paper_size]))
    return (
        [(r.outcome, r.miss, r.positions.tolist()) for r in results],
        arrival,
        horizon,
        [(e, s, k, r.outcome) for e, s, k, r in runs],
        {k: v for k, v in defended.items() if k != "example"},
        [(name, r.positions.tolist()) for name, r in defended["example"]["runs"]],
        grid_counts(flown[: p.paper_size]),
        grid_counts(flown[p.paper_size :], paper_keys),
    )


def in_process(p: GridPlan) -> list:
    return engine.run(StubWorker, p, flights(p), engine.EngineSettings(1, None, 60.0, 0))


def test_runs_flown_by_separate_pilots_in_any_order_match_one_pilot():
    p = plan()
    one = in_process(p)
    outcomes = {r.outcome for r, _ in one}
    assert len(outcomes) > 1 and len(one) == 1 + 8 + 6 * 9  # attacks change outcomes: the test can fail
    runs = flights(p)
    order = np.random.default_rng(0).permutation(len(runs))
    apart = [None] * len(runs)
    for j, i in enumerate(order):  # three pilots, each starting cold, runs shuffled
        apart[i] = StubWorker(p).run(runs[i]) if j % 3 == 0 else None
    pilots = [StubWorker(p), StubWorker(p)]
    for j, i in enumerate(order):
        if apart[i] is None:
            apart[i] = pilots[j % 2].run(runs[i])
    assert summary(p, apart) == summary(p, one)


def test_counts_are_those_of_one_shared_camera():
    p = plan()
    worker = StubWorker(p)
    flown = [worker.run(r) for r in flights(p)]
    counts = grid_counts(flown)
    steps = sum(len(r.estimates) for r, _ in flown)
    assert counts["steps"] == steps and 0 < counts["renders"] < steps
    assert counts["attacked"] == sum(r.attacked.sum() for r, _ in flown) > 0
    paper = grid_counts(flown[: p.paper_size])
    rest = grid_counts(flown[p.paper_size :], frozenset().union(*(k for _, k in flown[: p.paper_size])))
    assert paper["renders"] + rest["renders"] == counts["renders"] and rest["renders"] > 0


def attack_sets(tmp_path, es: engine.EngineSettings) -> tuple:
    """`rpod attack`'s adversarial sets of 10 random images (batches of 4) by PGD with a random start,
    on a tiny random pose model -> (every array of adv.zarr, the pose outputs, the stored L-inf)."""
    import torch
    import zarr

    from pipeline.formats.models import save_pose
    from pipeline.pose.loss import PoseLoss
    from pipeline.pose.model import PoseNet
    from pipeline.seeds import seed_for
    from stages.attack import _attack_into
    from stages.config import params as params_mod
    from stages.config.schema import build
    from stages.engine.attack_worker import AttackSetup

    p = build(
        params_mod.compose(
            "smoke",
            [
                "render.width=32",
                "render.height=18",
                "train.width=0.125",
                "attack.method=pgd",
                "attack.steps=2",
                "attack.eps=[0.5,0.05]",
                "attack.batch_size=4",
            ],
        )
    )
    torch.manual_seed(0)
    save_pose(tmp_path / "pose.pt", PoseNet(0.125, float(p.train.dropout)).eval(), PoseLoss(), (18, 32), {})
    rng = np.random.default_rng(0)
    images = rng.integers(0, 256, (10, 18, 32, 3), dtype=np.uint8)
    y = torch.randn(10, 9, generator=torch.Generator().manual_seed(0))
    # one torch thread on both paths: convolution gradients are not bit-identical across thread counts
    setup = AttackSetup(
        params=p,
        pose_path=str(tmp_path / "pose.pt"),
        eps=(0.5, 0.05),
        batch=4,
        seed=seed_for(p.seed, "attack"),
        torch_threads=1,
    )
    threads = torch.get_num_threads()
    try:
        out = _attack_into(tmp_path / f"adv{es.workers}.zarr", setup, images, np.arange(10), y, 6, es, 1)
    finally:
        torch.set_num_threads(threads)
    root = zarr.open_group(str(tmp_path / f"adv{es.workers}.zarr"), mode="r")
    return (
        {name: root[name][:] for name in sorted(root.array_keys())},
        out["preds"],
        out["preds_float"],
        out["linf"],
        out["example"],
    ), (setup, images, y)


def test_attack_sets_are_seeded_per_batch(tmp_path):
    from stages.engine.attack_worker import AttackBatch, AttackWorker

    sets, (setup, images, y) = attack_sets(tmp_path, engine.EngineSettings(1, None, 60.0, 0))
    arrays, preds, _, linf, example = sets
    assert set(arrays) == {"eps_0.05", "eps_0.5", "source_index"} and arrays["eps_0.5"].shape == (10, 18, 32, 3)
    assert 0.4 < linf[0.5] <= 0.5 + 1 / 510 + 1e-6 and np.array_equal(example[0.5], arrays["eps_0.5"][6])
    assert not np.array_equal(preds["clean"], preds[0.5])
    alone = AttackWorker(setup).run(AttackBatch(4, images[4:8], y[4:8]))  # the second batch on a fresh worker, first
    assert all(np.array_equal(alone[e][0], arrays[f"eps_{e:g}"][4:8]) for e in (0.5, 0.05))


def _equal(a, b) -> bool:
    """Nested tuples / dicts of arrays and numbers, equal bit for bit."""
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_equal(a[k], b[k]) for k in a)
    if isinstance(a, (tuple, list)):
        return len(a) == len(b) and all(_equal(x, y) for x, y in zip(a, b))
    return np.array_equal(a, b)


@pytest.mark.slow
def test_two_ray_workers_fly_the_grid_and_attack_the_sets_of_one_process(two_nodes, tmp_path):
    import ray

    cluster, marker = two_nodes
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the stand-ins live in this test file
    p = plan()
    one = in_process(p)
    two = engine.run(exits_once(StubWorker, marker), p, flights(p), engine.EngineSettings(2, cluster.address, 60.0, 2))
    assert marker.exists()  # a worker died mid-run: its run was flown again
    assert summary(p, two) == summary(p, one)
    sets = attack_sets(tmp_path, engine.EngineSettings(1, None, 60.0, 0))[0]
    assert _equal(attack_sets(tmp_path, engine.EngineSettings(2, cluster.address, 60.0, 2))[0], sets)
