"""The in-loop attacker through the real closed loop (GridPilot -> run_rendezvous -> InLoopAttacker): on an
undefended toy chain it puts the chaser on a collision course; it never steps the live defense; runs that
never met the attack do not count. Toy chain: each image channel's mean encodes one axis of the
camera-frame position, so an eps of 0.05 moves the estimate by up to 10 m (no Blender, tiny tensors)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from torch import nn

from pipeline.attackers.in_loop import InLoopAttacker, InLoopSettings, axes
from pipeline.defense.fusion import Defense
from pipeline.defense.gate import MotionSettings
from pipeline.defense.noise import NoiseModel
from pipeline.defense.settings import DefenseSettings
from pipeline.geometry.camera import reference_intrinsics
from pipeline.geometry.rotations import sixd_to_matrix
from pipeline.geometry.trajectories import look_at
from pipeline.guidance.grid import GridPilot, GridPlan, docked_counts, in_loop_grid
from pipeline.guidance.law import Estimate, GuidanceSettings, LoopState, RendezvousResult, segment_range

K = reference_intrinsics().scaled(160, 90)
SCALE = 200.0  # metres per unit of channel mean: t = SCALE * mean - SCALE / 2


class ToyChain(nn.Module):
    """images (B, 3, 4, 4) -> (pose (B, 9): position from the channel means and a fixed attitude, logit (B,))."""

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        t = SCALE * x.mean(dim=(2, 3)) - SCALE / 2
        r6 = torch.tensor([1.0, 0.0, 0.0, 0.0, 1.0, 0.0]).expand(len(x), 6)
        return torch.cat([t, r6], 1), -5.0 + 0.0 * x.sum(dim=(1, 2, 3))


class ToyCamera:
    """A CachedCamera stand-in: renders the camera-frame position into the channel means (8-bit), reads
    it back through the toy chain; attacked frames go through `attack(x, y)` first."""

    def __init__(self, chain: ToyChain) -> None:
        self.chain, self.attack, self.keys = chain, None, set()

    def render(self, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        level = np.clip(np.round((np.asarray(t) / SCALE + 0.5) * 255), 0, 255)
        return torch.as_tensor(np.broadcast_to(level[:, None, None], (3, 4, 4)).copy(), dtype=torch.float32)[None] / 255

    def estimate(self, x: torch.Tensor, attacked: bool, pose: tuple) -> Estimate:
        if attacked:
            x = self.attack(x, None)
        with torch.no_grad():
            p, logit = self.chain(x)
        p = p[0].double().numpy()
        return Estimate(p[:3], float(torch.sigmoid(logit[0])), sixd_to_matrix(p[3:]))


def _fly(goal: str, eps: float = 0.05, start: float = 20.0) -> tuple[GridPlan, list[RendezvousResult], list]:
    chain = ToyChain()
    plan = GridPlan(GuidanceSettings(max_steps=100), (), 10, ("paper",), (), ((eps, goal, start),))
    attackers = []

    def in_loop_at(e: float, g: str, i: int) -> InLoopAttacker:
        attackers.append(InLoopAttacker(chain, e, InLoopSettings(goal=g, steps=5), seed=i))
        return attackers[-1]

    pilot = GridPilot(ToyCamera(chain), K, plan, None, None, in_loop_at)
    return plan, [pilot.fly(*run)[0] for run in plan.runs()], attackers


def test_the_in_loop_attacker_puts_the_undefended_chaser_on_a_collision_course() -> None:
    plan, results, attackers = _fly("collide")
    _, baseline, attacked = results  # the paper chain's baseline, then the shipped chain's runs
    assert baseline.outcome == "docked" and baseline.closest_range > 9
    out = in_loop_grid(plan, results, collision_range=5.0)
    (run,) = out["runs"]
    assert run["collided"] and run["closest_range_m"] < 5.0 and run["attacked_frames"] > 0
    assert out["counts"]["paper"]["undefended"]["0.05"] == [1, 0, 0, 1, 0]
    assert attackers[0].wanted, "the attacker aimed at least once"


def test_the_miss_variant_loses_the_rendezvous() -> None:
    plan, results, _ = _fly("miss")
    (run,) = in_loop_grid(plan, results, collision_range=5.0)["runs"]
    assert run["outcome"] != "docked" and run["miss_m"] > 1.0


def test_a_run_that_never_meets_the_attack_is_not_counted() -> None:
    plan, results, _ = _fly("collide", start=10.0 - 1e-3)  # S below the goal range: never reached
    assert results[-1].attacked_frames == 0
    assert in_loop_grid(plan, results, collision_range=5.0)["counts"]["paper"]["undefended"]["0.05"] == [0, 0, 0, 0, 1]
    docked = RendezvousResult(np.zeros((2, 3)), np.zeros((1, 3)), np.array([True]), "docked", 0.0, 0)
    assert docked_counts([(0.5, 40, 5, results[-1]), (0.5, 40, 5, docked)]) == {"0.5": [1, 1, 1]}


def test_aiming_reads_the_defense_and_leaves_it_as_it_was() -> None:
    noise = NoiseModel((0.05, 0.05, 0.1), (0.004, 0.004, 0.015), 1.0, 0.02)
    defense = Defense(DefenseSettings(threshold=0.5), MotionSettings(false_alarm=0.01), noise)
    rel = np.array([1.0, -2.0, 30.0])
    R_c = look_at(rel)
    t = R_c.T @ rel
    defense.step(t, 0.0, R_c, None, np.eye(3))
    defense.step(t, 0.0, R_c, np.zeros(3), np.eye(3))
    before = (defense.filter.position.copy(), defense.flags_in_a_row, defense.clean_in_a_row)
    attacker = InLoopAttacker(ToyChain(), 0.05, InLoopSettings(goal="collide"))
    settings = dataclasses.replace(GuidanceSettings(), defense="recover")
    attacker.observe(LoopState(2, rel, R_c, np.zeros(3), defense, settings))
    wanted = attacker.aim(t, 0.0, np.eye(3))
    assert (
        np.array_equal(defense.filter.position, before[0])
        and (defense.flags_in_a_row, defense.clean_in_a_row) == before[1:]
    )
    # under the gate: a push, but far smaller than the undefended attacker's metres
    assert 0 < np.linalg.norm(wanted - t) < 5


def test_axes_and_segment_range() -> None:
    d = axes(np.array([3.0, 0.0, 4.0]))
    assert np.allclose(np.linalg.norm(d, axis=1), 1) and np.allclose(d[:3] @ d[:3].T, np.eye(3), atol=1e-12)
    assert np.allclose(d[0], [0.6, 0, 0.8]) and np.allclose(d[3], -d[0])
    assert segment_range(np.array([0.0, 0.0, 10.0]), np.array([0.0, 0.0, -10.0])) == 0.0  # jumped past the target
    assert segment_range(np.array([0.0, 3.0, 10.0]), np.array([0.0, 3.0, 12.0])) == pytest.approx(np.hypot(3, 10))


@pytest.mark.parametrize(
    "change, word",
    [
        ({"goal": "ram"}, "goal"),
        ({"steps": 0}, "steps"),
        ({"gate_fraction": 0.0}, "gate_fraction"),
        ({"magnitudes": (1.0, -2.0)}, "magnitudes"),
    ],
)
def test_bad_in_loop_settings_are_one_line(change: dict, word: str) -> None:
    with pytest.raises(ValueError, match=word) as e:
        InLoopSettings(**change)
    assert "\n" not in str(e.value)


def _run(outcome: str, miss: float, attacked: bool = True) -> RendezvousResult:
    return RendezvousResult(np.zeros((2, 3)), np.zeros((1, 3)), np.array([attacked]), outcome, miss, 0)


@pytest.mark.parametrize(
    "base, run, denied",
    [
        (_run("docked", 0.2, False), _run("attack succeeded", 1.2), True),  # it docked without attack
        (_run("missed without attack", 1.1, False), _run("attack succeeded", 1.2), False),  # it missed as much anyway
        (_run("missed without attack", 1.1, False), _run("attack succeeded", 3.0), True),  # > 1 m further
        (_run("docked", 0.2, False), _run("docked", 0.9), False),  # docked
        (_run("docked", 0.2, False), _run("missed without attack", 4.0, False), False),  # never met
    ],
)
def test_only_the_docking_the_attack_denied_counts(base, run, denied) -> None:
    from pipeline.guidance.grid import attack_denied, defended_record

    assert attack_denied(run, base, tolerance=1.0) is denied
    record = defended_record(base, None, [(0.05, 40, 5, run)], tolerance=1.0)
    assert record["runs"][0]["attack_denied"] is denied
    assert record["denied"] == ({"0.05": [int(denied), 1]} if run.attacked_frames else {})
    assert record["docked"]["0.05"] == [
        int(run.outcome == "docked" and bool(run.attacked_frames)),
        int(bool(run.attacked_frames)),
    ]


def test_the_standard_chain_flies_the_in_loop_cells_last_on_its_own_camera_attacker_and_key() -> None:
    """The standard chain's runs (its no-attack run, then each in-loop cell) come after every other run, so the runs
    before keep their places (and seeds); the pilot flies them on the standard chain's camera and in-loop attacker;
    in_loop_grid and closed_loop_outcomes report them under "standard <defense>", the no-attack run as its clean
    record."""
    from functools import partial

    from pipeline.defense.integrity import AlertLimitSettings, alert_limit
    from pipeline.evaluation.closed_loop import closed_loop_outcomes

    cells = ((0.05, "collide", 20.0),)
    plain = GridPlan(GuidanceSettings(max_steps=100), (), 10, ("paper",), (), cells)
    plan = dataclasses.replace(plain, standard_defenses=("undefended",))
    assert plan.runs()[: len(plain.runs())] == plain.runs()
    assert plan.runs()[len(plain.runs()) :] == [
        ("standard", "paper", "undefended", None),
        ("standard", "paper", "undefended", plan.in_loop_runs()[-1][3]),
    ]
    called = []

    def in_loop_on(name: str, chain: ToyChain):
        def at(e: float, g: str, i: int) -> InLoopAttacker:
            called.append((name, i))
            return InLoopAttacker(chain, e, InLoopSettings(goal=g, steps=5), seed=i)

        return at

    chain = ToyChain()
    cameras = {"paper": ToyCamera(chain), "shipped": ToyCamera(chain), "standard": ToyCamera(chain)}
    attackers = {"shipped": in_loop_on("shipped", chain), "standard": in_loop_on("standard", chain)}
    pilot = GridPilot(cameras, K, plan, None, None, attackers)
    results = [pilot.fly(*run)[0] for run in plan.runs()]
    assert called == [("shipped", 2), ("standard", 4)]  # each run's attacker on its own chain, seeded by its place
    assert results[4].attacked_frames > 0 and results[3].attacked_frames == 0
    out = in_loop_grid(plan, results, collision_range=5.0)
    assert [(r["chain"], r["defense"]) for r in out["runs"]] == [
        ("shipped", "undefended"),
        ("standard", "standard undefended"),
    ]
    assert set(out["counts"]["paper"]) == {"undefended", "standard undefended"}
    judged = closed_loop_outcomes(
        plan, results, 5.0, partial(alert_limit, settings=AlertLimitSettings(kind="persistent"))
    )
    standard = judged["variants"]["paper"]["standard undefended"]
    assert standard["clean"]["outcome"] == "docked" and standard["per_eps"]["0.05"]["met"] == 1
    assert [r["chain"] for r in judged["runs"]] == ["shipped", "shipped", "standard", "standard"]
