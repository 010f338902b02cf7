"""Motion-consistency filter: gate calibration on simulated clean motion, steps, noise fit, bad input."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pipeline.defense.gate import MotionSettings
from pipeline.defense.kalman import MotionFilter
from pipeline.defense.noise import NoiseModel, fit_noise
from pipeline.geometry.trajectories import approach_trajectory, look_at
from pipeline.stats import rate

NOISE = NoiseModel((0.05, 0.05, 0.1), (0.004, 0.004, 0.015), 1.0, 0.02)


def simulate(settings: MotionSettings, n: int, seed: int, start_xy=(20.0, -15.0)):
    """Clean motion that follows the filter's model exactly: the planned projectile approach's
    commands executed with an error of the configured size; estimates with the noise model's errors
    along the camera axes. -> (rel (n, 3), t_pred, R_cam, u, R_pred)."""
    rng = np.random.default_rng(seed)
    plan = approach_trajectory(n, start_xy, seed=seed).rel
    u = np.vstack([np.zeros(3), np.diff(plan, axis=0)])
    rel = np.zeros((n, 3))
    rel[0] = plan[0]
    for k in range(1, n):
        rel[k] = rel[k - 1] + u[k] + rng.normal(0, settings.position_noise, 3)
    R_cam = look_at(rel) @ Rotation.from_rotvec(rng.normal(0, np.radians(1.0), (n, 3))).as_matrix()
    t = np.einsum("nji,nj->ni", R_cam, rel)
    t_pred = t + rng.normal(0, 1, (n, 3)) * np.array([NOISE.position_std(r) for r in np.linalg.norm(t, axis=1)])
    R_tw, w = [np.eye(3)], np.zeros(3)  # target attitude: the rate model's random walk
    for _ in range(1, n):
        R_tw.append(
            R_tw[-1] @ Rotation.from_rotvec(w + rng.normal(0, np.radians(settings.attitude_noise_deg), 3)).as_matrix()
        )
        w = w + rng.normal(0, np.radians(settings.attitude_rate_noise_deg), 3)
    R_true = np.swapaxes(R_cam, 1, 2) @ np.array(R_tw)
    att = rng.normal(0, 1, (n, 3)) * np.array([NOISE.attitude_std(r) for r in np.linalg.norm(t, axis=1)])[:, None]
    R_pred = R_true @ Rotation.from_rotvec(att).as_matrix()
    return rel, t_pred, R_cam, u, R_pred


def run(settings: MotionSettings, t_pred, R_cam, u, R_pred=None, exclude: bool = True):
    f = MotionFilter(settings, NOISE)
    f.start_from(t_pred[0], R_cam[0], None if R_pred is None else R_pred[0])
    out = []
    for k in range(1, len(t_pred)):
        c = f.check(t_pred[k], R_cam[k], u[k], None if R_pred is None else R_pred[k])
        (f.coast if c.inconsistent and exclude else f.accept)()
        out.append(c)
    return f, out


@pytest.mark.parametrize("alpha", [0.01, 0.05])
def test_gate_has_the_configured_false_alarm_rate_on_clean_motion(alpha):
    s = MotionSettings(false_alarm=alpha, soft_gate=1.0)  # plain Kalman update: NIS is chi-square(3)
    flags = []
    for seed in range(20):
        _, t_pred, R_cam, u, R_pred = simulate(s, 300, seed)
        flags += [c.inconsistent for c in run(s, t_pred, R_cam, u, R_pred, exclude=False)[1][20:]]
    r = rate(np.array(flags))
    assert r.n > 5000
    # two 3-dof tests at alpha / 2 each: the rate is alpha minus the (tiny) overlap
    assert r.lo <= alpha * (1 - alpha / 4) <= r.hi, r.pct(2)


def test_default_robust_update_keeps_false_alarms_at_or_below_the_rate():
    s = MotionSettings(false_alarm=0.01)
    flags = []
    for seed in range(10):
        _, t_pred, R_cam, u, R_pred = simulate(s, 300, 100 + seed)
        flags += [c.inconsistent for c in run(s, t_pred, R_cam, u, R_pred)[1][20:]]
    assert rate(np.array(flags)).lo <= 0.01


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_a_three_metre_step_is_flagged_and_does_not_corrupt_the_state(axis):
    s = MotionSettings(false_alarm=0.005)
    rel, t_pred, R_cam, u, R_pred = simulate(s, 200, 7)
    step = np.zeros(3)
    step[axis] = 3.0
    hit = 120  # range about 30 m
    t_pred = t_pred.copy()
    t_pred[hit] += step
    f, out = run(s, t_pred, R_cam, u, R_pred)
    assert out[hit - 1].inconsistent
    assert np.linalg.norm(f.position - rel[-1]) < 0.5
    assert sum(c.inconsistent for c in out[hit:]) <= 3  # the clean frames after the step pass again


def test_fault_exclusion_survives_a_five_frame_attack_that_moves_the_estimates():
    s = MotionSettings(false_alarm=0.005)
    rel, t_pred, R_cam, u, R_pred = simulate(s, 200, 11)
    t_pred = t_pred.copy()
    t_pred[100:105] += np.array([1.5, -1.0, 3.0])
    f, out = run(s, t_pred, R_cam, u, R_pred)
    assert all(c.inconsistent for c in out[99:104])
    assert not any(c.inconsistent for c in out[105:])


def test_attitude_jump_is_flagged():
    s = MotionSettings(false_alarm=0.005)
    _, t_pred, R_cam, u, R_pred = simulate(s, 120, 3)
    R_pred = R_pred.copy()
    R_pred[80] = R_pred[80] @ Rotation.from_euler("z", 30, degrees=True).as_matrix()
    _, out = run(s, t_pred, R_cam, u, R_pred)
    assert out[79].inconsistent and out[79].nis_attitude > s.gate


def test_fit_noise_recovers_a_linear_noise_model():
    rng = np.random.default_rng(0)
    n = 20000
    rng_m = rng.uniform(10, 60, n)
    t = np.column_stack([rng.normal(0, 2, n), rng.normal(0, 2, n), rng_m])
    r = np.linalg.norm(t, axis=1)
    t_pred = t + rng.normal(0, 1, (n, 3)) * np.array([NOISE.position_std(x) for x in r])
    R_true = Rotation.random(n, random_state=1).as_matrix()
    att = rng.normal(0, 1, (n, 3)) * np.radians(NOISE.attitude_intercept + NOISE.attitude_slope * r)[:, None]
    t_pred = t_pred + np.outer(r, [0.0, 0.01, -0.02]) + [0.1, 0.0, 0.3]  # a range-dependent bias
    fit = fit_noise(t, t_pred, R_true, R_true @ Rotation.from_rotvec(att).as_matrix())
    for x in (15.0, 35.0, 55.0):
        assert np.allclose(fit.position_std(x), NOISE.position_std(x), rtol=0.1)
        assert np.allclose(fit.position_bias(x), [0.1, 0.01 * x, 0.3 - 0.02 * x], atol=0.05)
        assert fit.attitude_std(x) == pytest.approx(NOISE.attitude_std(x), rel=0.1)


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"position_noise": 0.0}, "defense.position_noise must be a finite number > 0"),
        ({"cusum_threshold": -1.0}, "defense.cusum_threshold must be a finite number > 0"),
        ({"cusum_reference": float("nan")}, "defense.cusum_reference must be a finite number >= 0"),
        ({"integrity_risk": 1.0}, r"defense.integrity_risk must be a probability in \(0, 1\)"),
        ({"attitude_noise_deg": float("nan")}, "defense.attitude_noise_deg must be a finite number > 0"),
        ({"attitude_rate_noise_deg": 0}, "defense.attitude_rate_noise_deg must be a finite number > 0"),
        ({"false_alarm": 0.0}, r"defense.false_alarm is a gate probability and must be in \(0, 1\)"),
        ({"false_alarm": 1.0}, r"defense.false_alarm is a gate probability and must be in \(0, 1\)"),
        ({"soft_gate": 0.0}, r"defense.soft_gate must be in \(0, 1\]"),
    ],
)
def test_bad_settings_name_the_parameter(changes, message):
    with pytest.raises(ValueError, match=message):
        MotionSettings(**changes)


def test_bad_noise_fit_input_is_refused():
    with pytest.raises(ValueError, match="NaN"):
        fit_noise(np.full((100, 3), np.nan), np.zeros((100, 3)))
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        fit_noise(np.zeros((100, 2)), np.zeros((100, 2)))
    with pytest.raises(ValueError, match="at least 32 frames"):
        fit_noise(np.ones((10, 3)), np.ones((10, 3)))


def test_a_nan_estimate_is_flagged_and_the_filter_coasts():
    s = MotionSettings()
    _, t_pred, R_cam, u, _ = simulate(s, 50, 5)
    f, _ = run(s, t_pred[:30], R_cam, u)
    before = f.position
    c = f.check(np.array([np.nan, 0.0, 20.0]), R_cam[30], u[30])
    assert c.inconsistent and np.allclose(c.predicted, before + u[30], atol=1e-9)
    f.coast()


def test_rotation_vector_helpers_match_scipy():
    from pipeline.geometry.rotations import matrix_to_rotvec, rotvec_to_matrix

    rng = np.random.default_rng(0)
    w = np.vstack(
        [rng.normal(0, 1, (200, 3)), rng.normal(0, 1e-9, (5, 3)), np.pi * np.eye(3) * (1 - 1e-7), [[0.0, 0.0, 0.0]]]
    )
    for v in w:
        R = Rotation.from_rotvec(v).as_matrix()
        assert np.allclose(rotvec_to_matrix(v), R, atol=1e-9)
        back = matrix_to_rotvec(R)
        assert np.allclose(Rotation.from_rotvec(back).as_matrix(), R, atol=1e-6)
        assert np.linalg.norm(back) <= np.pi + 1e-9


def test_inflate_scales_every_std_and_keeps_the_bias():
    from pipeline.defense.noise import NoiseModel, inflate

    n = NoiseModel((0.1, 0.2, 0.3), (0.01, 0.01, 0.02), 1.0, 0.05, floor=0.02, bias_intercept=(0.0, 0.0, 0.4))
    m = inflate(n, 2.0)
    assert np.allclose(m.position_std(30.0), 2 * n.position_std(30.0))
    assert m.attitude_std(30.0) == pytest.approx(2 * n.attitude_std(30.0))
    assert np.allclose(m.position_bias(30.0), n.position_bias(30.0))
    with pytest.raises(ValueError, match="inflation"):
        inflate(n, 0.0)


def test_first_meeting_meets_the_target_or_says_it_cannot():
    from pipeline.defense.calibration import first_meeting

    k, rates = first_meeting(lambda k: 0.05 / k, target=0.02, grid=(1.0, 2.0, 3.0, 4.0))
    assert k == 3.0 and list(rates) == [1.0, 2.0, 3.0]  # stops at the first factor that meets it
    k, rates = first_meeting(lambda k: 0.5, target=0.02, grid=(1.0, 2.0))
    assert k == 2.0 and rates == {1.0: 0.5, 2.0: 0.5}  # none meets it: the largest, with every rate


def _spd(rng, scale):
    a = rng.normal(0, scale, (3, 3))
    return a @ a.T + np.eye(3) * scale**2


def test_float_filters_follow_the_matrix_equations():
    """The per-frame filters (plain floats on 3x3 lists, scalar attitude filters) against the Kalman
    equations written on numpy matrices: predict, then the Joseph-form update. The position filter's
    state is rel alone (F = I, moved by the command u); the attitude's is [level, rate]."""
    from pipeline.defense.linear import IsoKalman6, Kalman3

    rng = np.random.default_rng(4)
    for iso in (False, True):
        d = 6 if iso else 3
        F, H = np.eye(d), np.hstack([np.eye(3), np.zeros((3, d - 3))])
        F[:3, 3:] = np.eye(3) if iso else F[:3, 3:]
        q = np.array([0.05] * 3 + [0.01] * 3)[:d] ** 2
        kf = IsoKalman6(0.05, 0.01) if iso else Kalman3(0.05)
        cov = np.eye(3) * 0.3 if iso else _spd(rng, 0.5)
        x, P = np.r_[rng.normal(0, 5, 3) * (not iso), np.zeros(d - 3)], np.zeros((d, d))
        P[:3, :3] = cov
        P[3:, 3:] = np.eye(d - 3) * 0.03**2
        kf.reset(0.3, 0.03) if iso else kf.reset(x.tolist(), cov.tolist())
        for _ in range(6):
            u = np.zeros(3) if iso else rng.normal(0, 0.1, 3)
            x, P = F @ x + np.r_[u, np.zeros(d - 3)], F @ P @ F.T + np.diag(q)
            kf.predict() if iso else kf.predict(u.tolist())
            R = np.eye(3) * rng.uniform(0.01, 0.2) if iso else _spd(rng, 0.2)
            y = rng.normal(0, 0.3, 3)
            K = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
            M = np.eye(d) - K @ H
            x, P = x + K @ y, M @ P @ M.T + K @ R @ K.T
            gain = kf.update(y.tolist(), R[0, 0]) if iso else kf.update(y.tolist(), R.tolist())
            if not iso:
                np.testing.assert_allclose(gain, K, rtol=1e-10, atol=1e-12)
            np.testing.assert_allclose(kf.x, x, rtol=1e-10, atol=1e-12)
            np.testing.assert_allclose(kf.P, P, rtol=1e-10, atol=1e-12)


def test_covariance_stays_symmetric_over_a_long_run():
    """8000 frames of a still camera watching a steady approach: rounding must not drive the
    position covariance's blocks apart (an unsymmetrised block version diverged by frame 7500)."""
    f = MotionFilter(MotionSettings(), NOISE)
    rel, u = np.array([3.0, -2.0, 40.0]), np.array([0.0, 0.0, -0.005])
    R_cam = look_at(rel)
    f.start_from(R_cam.T @ rel, R_cam)
    for _ in range(8000):
        rel = rel + u
        c = f.check(R_cam.T @ rel, R_cam, u, R_cam.T)
        assert not c.inconsistent
        f.accept()
    P = f.pos.P
    assert np.abs(P - P.T).max() <= 1e-12 * np.abs(P).max()
    assert 1e-4 < np.trace(P[:3, :3]) < 1.0
