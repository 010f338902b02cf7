"""The worst case of the defended chain under an attacker's capacity (pipeline/defense/bound.py) and the
capacity overbound (pipeline/attacks/capacity.py), on toy filters: no network."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.attacks.capacity import Shifts, capacity_at, fit_capacity, measure_shifts, proportional_capacity
from pipeline.defense.bound import ACCEPT, ALARM, HUBER, REJECT, fault_axes, record, worst_case
from pipeline.defense.calibration import CleanRun
from pipeline.defense.gate import MotionSettings
from pipeline.defense.noise import NoiseModel
from pipeline.defense.settings import DefenseSettings
from pipeline.geometry.rotations import matrix_to_6d
from pipeline.geometry.trajectories import approach_trajectory, look_at

FLAT = NoiseModel((0.1, 0.1, 0.4), (0.0, 0.0, 0.0), 1.0, 0.0)  # range-free: the program is exact at once
SLOPED = NoiseModel((0.05, 0.05, 0.1), (0.002, 0.002, 0.01), 1.0, 0.0, bias_slope=(0.0, 0.0, 0.005))
MOTION = MotionSettings(cusum_threshold=5.0, trusted_start=5)
SETTINGS = DefenseSettings()


def toy(n: int, seed: int, noise: NoiseModel) -> tuple[np.ndarray, CleanRun]:
    """A projectile approach from 60 m to 10 m, the camera at the target with 1 deg jitter, estimates with
    the noise model's scatter along the camera axes: (true rel (n, 3) world m, the clean run)."""
    rng = np.random.default_rng(seed)
    rel = approach_trajectory(n, (10.0, -8.0), seed=seed).rel
    R_cam = look_at(rel) @ Rotation.from_rotvec(rng.normal(0, np.radians(1.0), (n, 3))).as_matrix()
    t = np.einsum("nji,nj->ni", R_cam, rel)
    t_pred = t + rng.normal(0, 1, (n, 3)) * np.array([noise.position_std(r) for r in np.linalg.norm(t, axis=1)])
    pose = np.hstack([t_pred, matrix_to_6d(np.swapaxes(R_cam, 1, 2))])
    return rel, CleanRun(pose, np.zeros(n), R_cam, np.vstack([np.zeros(3), np.diff(rel, axis=0)]))


def box(n: int, along: float, across: float) -> np.ndarray:
    return np.tile([along, across, across], (n, 1))


def in_axes(rel: np.ndarray, run: CleanRun, shift: np.ndarray) -> np.ndarray:
    """A camera-frame shift (N, 3) in the capacity axes [LOS, cross 1, cross 2] (N, 3)."""
    return np.einsum("njk,nji,ni->nk", fault_axes(rel), run.R_cam, shift)


def assert_passes(
    rel: np.ndarray, run: CleanRun, noise: NoiseModel, shift: np.ndarray, upto: int, motion: MotionSettings = MOTION
) -> None:
    """The shifted run through the real defense makes the clean run's accept / reject choices on frames
    <= upto and flags the same frames, with every accepted frame under the gate (unweighted ones under the
    soft gate) and every CUSUM statistic at most h."""
    clean, attacked = record(SETTINGS, motion, noise, run), record(SETTINGS, motion, noise, run, shift)
    choices = [np.where(r.kind[: upto + 1] == HUBER, ACCEPT, r.kind[: upto + 1]) for r in (clean, attacked)]
    assert np.array_equal(*choices)
    assert np.array_equal(attacked.trace.flag[: upto + 1], clean.trace.flag[: upto + 1])
    accepted = choices[1] == ACCEPT
    assert (attacked.nis[: upto + 1][accepted] <= motion.gate).all()
    assert (attacked.nis[: upto + 1][attacked.kind[: upto + 1] == ACCEPT] <= motion.soft_gate * motion.gate).all()
    assert (attacked.statistic[: upto + 1][accepted] <= motion.cusum_threshold).all()


def test_the_worst_sequence_replays_through_the_real_defense_to_the_programs_error() -> None:
    rel, run = toy(60, 0, FLAT)
    cap = box(60, 0.5, 0.1)
    w = worst_case(SETTINGS, MOTION, FLAT, run, rel, cap, np.full(60, 6.0), targets=[0, 3, 10, 25, 59])
    assert w.exact.all() and (w.iterations == 0).all()
    np.testing.assert_allclose(w.achieved, w.lower, atol=1e-6)
    assert (w.upper >= w.lower - 1e-6).all() and (w.upper <= np.sqrt(3) * w.lower + 1e-6).all()
    clean = np.linalg.norm(record(SETTINGS, MOTION, FLAT, run).trace.trusted - rel, axis=1)[w.targets]
    assert (w.achieved > clean + 0.2).all()  # the attack moves the trusted estimate
    for t, j in enumerate(w.targets):
        assert (np.abs(in_axes(rel, run, w.shift[t])) <= cap + 1e-9).all()  # never outside F
        assert not w.shift[t][j + 1 :].any()
        assert_passes(rel, run, FLAT, w.shift[t], j)
    np.testing.assert_allclose(w.ratio, w.upper / 6.0)


def test_the_start_frame_is_not_trusted_its_bound_is_the_clean_error_plus_the_capacity() -> None:
    """The filter starts on frame 0's measurement: its worst error is the clean error pushed out by F along
    each axis of the box, exactly (no trusted-start assumption)."""
    rel, run = toy(30, 1, FLAT)
    cap = box(30, 0.5, 0.1)
    w = worst_case(SETTINGS, MOTION, FLAT, run, rel, cap, np.full(30, 6.0), targets=[0])
    e = fault_axes(rel)[0].T @ (record(SETTINGS, MOTION, FLAT, run).trace.trusted[0] - rel[0])
    assert w.upper[0] == pytest.approx(np.linalg.norm(np.abs(e) + cap[0]), abs=1e-6)
    assert w.lower[0] == pytest.approx(w.achieved[0], abs=1e-6)


def test_a_looser_capacity_gives_a_larger_bound_and_none_gives_the_clean_error() -> None:
    rel, run = toy(50, 2, FLAT)
    targets = [5, 20, 49]
    runs = [
        worst_case(SETTINGS, MOTION, FLAT, run, rel, box(50, f, f / 4), np.full(50, 6.0), targets=targets)
        for f in (0.0, 0.2, 0.6)
    ]
    clean = np.linalg.norm(record(SETTINGS, MOTION, FLAT, run).trace.trusted - rel, axis=1)[targets]
    np.testing.assert_allclose(runs[0].achieved, clean, atol=1e-9)
    np.testing.assert_allclose(runs[0].upper, clean, atol=1e-5)
    for small, large in zip(runs, runs[1:]):
        assert (large.upper >= small.upper - 1e-6).all() and (large.achieved >= small.achieved - 1e-6).all()
    assert (runs[2].achieved > runs[1].achieved + 0.05).all()


def test_the_program_keeps_the_gate_rejections_and_the_alarms_of_the_clean_run() -> None:
    """A clean run with outliers the gate rejects and a ramp the sequential test alarms on: the worst sequence
    keeps every rejection and alarm where they were (the same restarts of the test) and replays exactly."""
    rel, run = toy(70, 3, FLAT)
    pose = run.pose.copy()
    pose[[12, 40], 2] += 6.0  # rejected by the gate
    pose[20:32, 2] += 0.35 * np.arange(12)  # a ramp: the sequential test alarms
    run = dataclasses.replace(run, pose=pose)
    clean = record(SETTINGS, MOTION, FLAT, run)
    assert (clean.kind == REJECT).sum() >= 2 and (clean.kind == ALARM).any()
    targets = [int(np.flatnonzero(clean.kind == ALARM)[-1]) + 2, 69]
    w = worst_case(SETTINGS, MOTION, FLAT, run, rel, box(70, 0.5, 0.1), np.full(70, 6.0), targets=targets)
    assert w.exact.all()
    for t, j in enumerate(targets):
        assert_passes(rel, run, FLAT, w.shift[t], j)


def test_a_range_dependent_noise_model_is_followed_to_a_fixed_point_by_re_solving() -> None:
    """The noise model is taken at the predicted range, which the shifts move: the first replay differs from
    the program; re-solving around the replay reaches the replay's error within the tolerance."""
    rel, run = toy(60, 4, SLOPED)
    w = worst_case(SETTINGS, MOTION, SLOPED, run, rel, box(60, 0.5, 0.1), np.full(60, 6.0), targets=[20, 59])
    assert w.exact.all() and (w.iterations >= 1).all()
    np.testing.assert_allclose(w.achieved, w.lower, atol=1e-4)
    for t, j in enumerate(w.targets):
        assert_passes(rel, run, SLOPED, w.shift[t], j)


def test_the_white_box_attacker_exceeds_the_protection_level_where_it_trusts_the_start() -> None:
    """The PL leaves the first `trusted_start` frames out of its fault bound (assumption A): an attacker of
    modest capacity there drives the trusted error above the PL."""
    rel, run = toy(40, 5, FLAT)
    motion = dataclasses.replace(MOTION, trusted_start=20)
    w = worst_case(SETTINGS, motion, FLAT, run, rel, box(40, 1.0, 0.3), np.full(40, 6.0), targets=[1, 2, 3])
    assert (w.achieved > w.pl).any()


def test_worst_case_refuses_bad_input_with_one_line() -> None:
    rel, run = toy(20, 0, FLAT)
    with pytest.raises(ValueError, match=r"^worst_case needs truth \(N, 3\)"):
        worst_case(SETTINGS, MOTION, FLAT, run, rel, box(19, 0.5, 0.1), np.full(20, 6.0))
    with pytest.raises(ValueError, match="capacity must be finite and >= 0"):
        worst_case(SETTINGS, MOTION, FLAT, run, rel, -box(20, 0.5, 0.1), np.full(20, 6.0))
    with pytest.raises(ValueError, match=r"target frames must lie in \[0, 20\)"):
        worst_case(SETTINGS, MOTION, FLAT, run, rel, box(20, 0.5, 0.1), np.full(20, 6.0), targets=[20])


# ----------------------------------------------------------------------------- capacity
def test_shifts_split_along_and_across_the_line_of_sight() -> None:
    t = np.array([[0.0, 0.0, 20.0], [3.0, 0.0, 4.0]])
    s = measure_shifts(0.01, t, t, t + np.array([[0.1, -0.2, 0.5], [0.6, 0.0, 0.8]]))
    np.testing.assert_allclose(s.along, [0.5, 1.0])
    np.testing.assert_allclose(s.across, [np.hypot(0.1, 0.2), 0.0], atol=1e-12)
    np.testing.assert_allclose(s.range_m, [20.0, 5.0])
    R = Rotation.from_euler("z", [[0.0], [10.0]], degrees=True).as_matrix()
    s = measure_shifts(0.01, t, t, t, np.repeat(np.eye(3)[None], 2, 0), R)
    np.testing.assert_allclose(s.attitude_deg, [0.0, 10.0], atol=1e-9)


def test_the_capacity_is_a_quantile_plus_margin_per_bin_and_monotone_in_eps() -> None:
    rng = np.random.default_rng(0)
    r = rng.uniform(10, 60, 4000)
    shifts = [
        Shifts(e, r, k * 0.02 * r * rng.uniform(0, 1, 4000), k * 0.005 * r * rng.uniform(0, 1, 4000), np.zeros(4000))
        for e, k in ((0.01, 1.0), (0.05, 3.0))
    ]
    edges = [10, 20, 40, 60]
    caps = [fit_capacity(s, edges, quantile=0.99, margin=0.25) for s in shifts]
    low = caps[0]
    inside = (r >= 20) & (r < 40)
    assert low.along[1] == pytest.approx(1.25 * np.quantile(shifts[0].along[inside], 0.99))
    assert (low.count >= 20).all() and low.count.sum() == 4000
    F = low.at(np.array([15.0, 30.0, 60.0]))
    np.testing.assert_allclose(F, [[low.along[k], low.across[k], low.across[k]] for k in (0, 1, 2)])
    between = capacity_at(caps, 0.02, np.array([15.0, 55.0]))  # the next measured eps, 0.05
    np.testing.assert_allclose(between, caps[1].at(np.array([15.0, 55.0])))
    weaker = dataclasses.replace(caps[1], along=caps[1].along * 0.1)  # a larger eps that measured less
    assert capacity_at([low, weaker], 0.05, np.array([30.0]))[0, 0] == low.along[1]
    with pytest.raises(ValueError, match="above every measured eps"):
        capacity_at(caps, 0.1, np.array([30.0]))
    with pytest.raises(ValueError, match=r"within the measured bins \[10.0, 60.0\]"):
        low.at(np.array([61.0]))
    with pytest.raises(ValueError, match="range bin 10-20 m has 3 frames"):
        fit_capacity(Shifts(0.01, np.array([15.0, 16, 17, 30]), *np.ones((3, 4))), [10, 20, 40], min_count=1 + 3)


def test_a_proportional_placeholder_grows_with_range() -> None:
    cap = proportional_capacity(0.01, [10, 30, 60], 0.02, 0.005)
    np.testing.assert_allclose(cap.at(np.array([20.0, 50.0])), [[0.6, 0.15, 0.15], [1.2, 0.3, 0.3]])


def test_a_restart_of_the_filter_ends_the_modelled_horizon() -> None:
    """The filter starts on a frame 8 m off, rejects the clean frames after it and restarts on four of them:
    the program models the frames before the restart and leaves the targets from it on unsolved (NaN)."""
    rel, run = toy(30, 6, FLAT)
    pose = run.pose.copy()
    pose[0, 2] += 8.0
    run = dataclasses.replace(run, pose=pose)
    clean = record(SETTINGS, MOTION, FLAT, run)
    assert clean.start == 0 and clean.horizon == 4 and (clean.kind[1:4] == REJECT).all()
    w = worst_case(SETTINGS, MOTION, FLAT, run, rel, box(30, 0.5, 0.1), np.full(30, 6.0), targets=[0, 2, 4, 20])
    assert np.isfinite(w.achieved[:2]).all() and np.isnan(w.upper[2:]).all() and np.isnan(w.achieved[2:]).all()
    assert_passes(rel, run, FLAT, w.shift[1], 2)


def test_a_program_the_solver_stops_on_is_solved_again_with_more_regularization(monkeypatch) -> None:
    """Clarabel stopped with a numerical error on a standard-chain program (capacities of tens of metres): the
    program is solved again with its static regularization raised and gives the bound an unhindered solve gives;
    a program no setting solves stops with the frame named."""
    from types import SimpleNamespace

    import clarabel

    from pipeline.defense import bound

    rel, run = toy(40, 3, FLAT)
    args = (SETTINGS, MOTION, FLAT, run, rel, box(40, 0.5, 0.1), np.full(40, 6.0))
    clean = worst_case(*args, targets=[12, 39])
    real, seen = clarabel.DefaultSolver, []

    default = clarabel.DefaultSettings().static_regularization_constant

    class Stalling:
        """Clarabel, except that a solver built with the default regularization (mode "first") or any solver
        (mode "always") reports a numerical error."""

        def __init__(self, P, q, A, b, cones, settings) -> None:
            self.regularization = settings.static_regularization_constant
            seen.append(self.regularization)
            self.inner = real(P, q, A, b, cones, settings)

        def update(self, **kwargs) -> None:
            self.inner.update(**kwargs)

        def solve(self):
            sol = self.inner.solve()
            stalled = fails[0] == "always" or self.regularization == default
            status = clarabel.SolverStatus.NumericalError if stalled else sol.status
            return SimpleNamespace(x=sol.x, obj_val=sol.obj_val, obj_val_dual=sol.obj_val_dual, status=status)

    fails = ["first"]
    monkeypatch.setattr(bound.clarabel, "DefaultSolver", Stalling)
    retried = worst_case(*args, targets=[12, 39])
    np.testing.assert_allclose(retried.upper, clean.upper, rtol=1e-5)
    np.testing.assert_allclose(retried.achieved, clean.achieved, atol=1e-6)
    assert bound.RETRY_REGULARIZATION[0] in seen
    fails[0] = "always"
    with pytest.raises(RuntimeError, match="worst-case program of frame 12: NumericalError"):
        worst_case(*args, targets=[12])
