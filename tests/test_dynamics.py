"""The executed motion (pipeline/guidance/dynamics.py): execution error reaches the truth and never the
filter (its prediction is the last state moved by the command alone), in the closed loop and on open-loop
trajectories; the Clohessy-Wiltshire step matches the equations of motion; a loop that flies on its
estimates still docks with the error on (no Blender, no torch)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from pipeline.defense.fusion import Defense
from pipeline.defense.gate import MotionSettings
from pipeline.defense.noise import NoiseModel
from pipeline.defense.settings import DefenseSettings
from pipeline.geometry.camera import reference_intrinsics
from pipeline.geometry.trajectories import approach_trajectory
from pipeline.guidance.dynamics import Executor, cw_matrices, execute_plan
from pipeline.guidance.grid import GridPilot, GridPlan
from pipeline.guidance.law import GuidanceSettings, run_rendezvous
from pipeline.guidance.settings import ExecutionSettings

K = reference_intrinsics().scaled(160, 90)
NOISE = NoiseModel((0.05, 0.05, 0.1), (0.002, 0.002, 0.01), 1.0, 0.0)
EXACT = ExecutionSettings(scale_std=0.0, noise_std=0.0, mean_motion=0.0)


def blank(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    return np.zeros((K.height, K.width, 3), np.uint8)


def perfect(image, attacked, pose):
    return pose[1]


def _spied_defense(motion: MotionSettings) -> tuple[Defense, list[tuple[np.ndarray, np.ndarray, np.ndarray]]]:
    """A defense whose filter records (state before, command u, prediction) at every check."""
    d = Defense(DefenseSettings(), motion, NOISE)
    seen, check = [], d.filter.check

    def spy(t_pred, R_cam, u=None, R_pred=None):
        before = d.filter.position.copy()
        out = check(t_pred, R_cam, u, R_pred)
        seen.append((before, np.zeros(3) if u is None else np.asarray(u, np.float64), out.predicted))
        return out

    d.filter.check = spy
    return d, seen


@pytest.mark.parametrize("execution", [None, ExecutionSettings(scale_std=0.05, noise_std=0.03, seed=3)])
def test_execution_error_reaches_the_truth_and_not_the_filter(execution) -> None:
    """Closed loop, recover defense, a perfect estimator: the filter's prediction is its last state plus
    the command, exactly, with or without execution error; the truth moved by the command exactly
    without it, and by centimetres more with it (the filter never sees that part)."""
    s = GuidanceSettings(
        start=(-4.0, 3.0, 60.0), variant="true_state", defense="recover", max_steps=60, execution=execution
    )
    defense, seen = _spied_defense(MotionSettings(position_noise=0.03))
    r = run_rendezvous(blank, perfect, K, s, defense=defense)
    assert len(seen) == len(r.estimates) - 1 and r.held[0] and not r.held[1:].any()  # the start on probation
    for before, u, predicted in seen:
        np.testing.assert_allclose(predicted, before + u, atol=1e-12)
    commanded = np.array([u for _, u, _ in seen])  # u of frame k: rel's commanded step k-1 -> k
    flown = np.diff(r.positions[: len(seen) + 1], axis=0)
    gap = np.linalg.norm(flown - commanded, axis=1)
    if execution is None:
        assert gap.max() < 1e-12
    else:
        assert np.median(gap) > 0.02 and gap.max() < 0.5
    assert r.miss <= s.tolerance and r.outcome == "docked"  # the loop flies on its estimates: it docks


def test_the_paper_dynamics_take_no_execution_and_a_grid_flies_it_only_on_true_state() -> None:
    with pytest.raises(ValueError, match="prediction = truth"):
        GuidanceSettings(variant="paper", execution=ExecutionSettings())
    plan = GridPlan(
        GuidanceSettings(max_steps=55),
        (),
        5,
        ("paper", "true_state"),
        (),
        execution=ExecutionSettings(scale_std=0.05, noise_std=0.03),
    )
    pilot = GridPilot(_Camera(), K, plan, None)
    paper, _ = pilot.fly("shipped", "paper", "undefended", None)
    true, _ = pilot.fly("shipped", "true_state", "undefended", None)
    assert np.allclose(np.abs(np.diff(paper.positions, axis=0)).max(1)[:40], 1.0)  # exact 1 m steps
    assert np.abs(np.abs(np.diff(true.positions, axis=0))[:40, 2] - 1.0).max() > 0.01


class _Camera:
    """A CachedCamera stand-in for GridPilot: renders nothing, estimates the truth."""

    attack, keys = None, set()

    def render(self, R, t):
        return t

    def estimate(self, t, attacked, pose):
        return pose[1]


def test_executor_without_errors_moves_by_the_command_and_holds_station() -> None:
    ex = Executor(EXACT)
    rel = np.array([3.0, -2.0, 40.0])
    np.testing.assert_allclose(ex.step(rel, np.array([0.5, -1.0, 1.0])), rel - [0.5, -1.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(Executor(ExecutionSettings()).step(rel, np.zeros(3)), rel)  # a hold keeps station


def test_execution_errors_are_seeded_scaled_per_axis_and_sized_as_stated() -> None:
    """1 m steps along the boresight: the error's spread per step is step_std (2.2 cm with the defaults),
    the same seed draws the same errors, another seed others."""
    s = ExecutionSettings(mean_motion=0.0)
    rel, cmd = np.array([0.0, 0.0, 50.0]), np.array([0.0, 0.0, 1.0])
    errs = np.array([Executor(dataclasses.replace(s, seed=k)).step(rel, cmd) - (rel - cmd) for k in range(400)])
    assert abs(errs[:, 2].std() / s.step_std(1.0) - 1) < 0.15
    assert abs(errs[:, 0].std() / s.noise_std - 1) < 0.15  # across the command: the fixed part only
    np.testing.assert_array_equal(Executor(s).step(rel, cmd), Executor(s).step(rel, cmd))
    assert abs(s.step_std(1.0) - np.hypot(0.02, 0.01)) < 1e-12


def test_cw_matrices_follow_the_equations_of_motion() -> None:
    """Phi_rr p0 + Phi_rv v0 equals a numerical integration of the Clohessy-Wiltshire equations."""
    n, dt = 0.0011, 120.0
    p0, v0 = np.array([5.0, -30.0, 2.0]), np.array([0.01, 0.2, -0.02])

    def cw(_, s):
        x, y, z, vx, vy, vz = s
        return [vx, vy, vz, 3 * n * n * x + 2 * n * vy, -2 * n * vx, -n * n * z]

    ref = solve_ivp(cw, (0, dt), np.r_[p0, v0], rtol=1e-11, atol=1e-12).y[:3, -1]
    rr, rv = cw_matrices(n, dt)
    np.testing.assert_allclose(rr @ p0 + rv @ v0, ref, atol=1e-7)
    rr0, rv0 = cw_matrices(0.0, dt)
    np.testing.assert_allclose(rr0 @ p0 + rv0 @ v0, p0 + dt * v0)


def test_a_prograde_hop_on_the_v_bar_rises_and_an_r_bar_hold_stays() -> None:
    """V-bar approach (world z along the orbital velocity, y nadir): a 1 m hop toward the target in 10 s
    lifts the chaser by 2 (1 - cos n dt) / n * v (Coriolis), i.e. the target appears 1.1 cm lower: rel_y > 0."""
    s = ExecutionSettings(scale_std=0.0, noise_std=0.0, mean_motion=0.0011, frame_interval=10.0)
    nxt = Executor(s).step(np.array([0.0, 0.0, 60.0]), np.array([0.0, 0.0, 1.0]))
    lift = 2 * (1 - np.cos(0.011)) / 0.0011 * 0.1
    assert abs(nxt[1] - lift) < 1e-6 and abs(nxt[2] - (60 - (4 * np.sin(0.011) - 3 * 0.011) / 0.0011 * 0.1)) < 1e-9
    assert 0.01 < lift < 0.012


def test_open_loop_trajectories_fly_the_plan_with_errors_and_record_the_commands() -> None:
    """approach_trajectory with execute: labels and camera follow the flown rel, `commands` are the planned
    steps (what the chain is told); without errors the flown rel is the plan."""
    s = ExecutionSettings(seed=5)
    plain = approach_trajectory(60, (10.0, -15.0), seed=2)
    flown = approach_trajectory(60, (10.0, -15.0), seed=2, execute=lambda rel: execute_plan(rel, s))
    assert plain.commands is None
    np.testing.assert_allclose(flown.commands[1:], np.diff(plain.rel, axis=0))
    drift = np.linalg.norm(flown.rel - plain.rel, axis=1)
    assert drift[0] == 0 and 0.05 < drift[-1] < 2.0  # a random walk of centimetres per step
    np.testing.assert_allclose(np.einsum("nji,nj->ni", flown.R_cam, flown.rel), flown.t, atol=1e-9)
    np.testing.assert_allclose(execute_plan(plain.rel, EXACT), plain.rel, atol=1e-9)


@pytest.mark.parametrize(
    "change, word",
    [
        ({"scale_std": -0.1}, "scale_std"),
        ({"noise_std": float("nan")}, "noise_std"),
        ({"frame_interval": 0.0}, "frame_interval"),
        ({"approach": "hbar"}, "approach"),
    ],
)
def test_bad_execution_settings_are_one_line(change: dict, word: str) -> None:
    with pytest.raises(ValueError, match=word):
        ExecutionSettings(**change)
    with pytest.raises(ValueError, match="execute_plan"):
        execute_plan(np.zeros((4, 2)), ExecutionSettings())


def test_eval_render_writes_the_planned_commands_and_flies_the_poses_with_their_error() -> None:
    """The eval_render path (stages/eval_render.py, stages/artifacts/readers.py): the trajectories are flown with
    guidance.execution's error, poses.parquet holds the flown truth (rel, labels) and the planned steps as cmd_*,
    and what the chain is told (`chaser_motion`) are those commands, not the flown steps."""
    from stages.artifacts.readers import chaser_motion
    from stages.config import params as params_mod
    from stages.engine.trajectory_sets import poses_table, trajectories

    p = params_mod.build(params_mod.compose("smoke"))
    base = params_mod.evaluation_seed(p)
    flown, planned = trajectories(p, base, 2, flown=True), trajectories(p, base, 2)
    poses = poses_table(flown)
    _, u = chaser_motion(poses)
    for f, q in zip(flown, planned):
        rows = (poses["trajectory"] == f.sequence).to_numpy()
        rel = poses.loc[rows, ["rel_x", "rel_y", "rel_z"]].to_numpy()
        assert np.allclose(u[rows][1:], np.diff(q.rel, axis=0)) and not u[rows][0].any()  # the planned steps
        assert np.allclose(rel, f.rel) and not np.allclose(rel, q.rel, atol=1e-3)  # the truth is flown
        assert np.allclose(rel[0], q.rel[0]) and np.allclose(
            np.linalg.norm(poses.loc[rows, ["tx", "ty", "tz"]], axis=1), np.linalg.norm(rel, axis=1)
        )
    assert not np.allclose(flown[0].rel - planned[0].rel, flown[1].rel - planned[1].rel)  # each its own draws
