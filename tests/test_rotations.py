import numpy as np

from pipeline.geometry.rotations import (
    euler_to_matrix,
    matrix_to_6d,
    matrix_to_quat,
    normalize_quat,
    quat_to_6d,
    quat_to_matrix,
    sixd_to_matrix,
    sixd_to_quat,
)
from pipeline.pose.metrics import attitude_error_deg, position_error


def random_quats(n, seed=0):
    return normalize_quat(np.random.default_rng(seed).normal(size=(n, 4)))


def test_quat_matrix_round_trip():
    q = random_quats(500)
    R = quat_to_matrix(q)
    assert np.allclose(R @ np.swapaxes(R, -1, -2), np.eye(3), atol=1e-12)
    assert np.allclose(np.linalg.det(R), 1.0)
    assert np.abs(matrix_to_quat(R) - q).max() < 1e-6


def test_quat_6d_matrix_round_trip():
    q = random_quats(500, seed=1)
    R = quat_to_matrix(q)
    r6 = quat_to_6d(q)
    assert r6.shape == (500, 6)
    assert np.abs(r6 - matrix_to_6d(R)).max() < 1e-12
    assert np.abs(sixd_to_matrix(r6) - R).max() < 1e-6
    assert np.abs(sixd_to_quat(r6) - q).max() < 1e-6


def test_6d_column_order_and_gram_schmidt():
    R = euler_to_matrix(np.array([10.0, -20.0, 30.0]))
    r6 = matrix_to_6d(R)
    assert np.allclose(r6[:3], R[:, 0]) and np.allclose(r6[3:], R[:, 1])
    noisy = 2.0 * r6 + np.array([0, 0, 0, 0.05, -0.02, 0.01])  # any 6-vector maps to a rotation
    Rn = sixd_to_matrix(noisy)
    assert np.allclose(Rn.T @ Rn, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(Rn), 1.0)
    assert np.allclose(Rn[:, 0], R[:, 0])


def test_quaternion_rotates_target_into_camera():
    q = np.array([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])  # 90 deg about z
    assert np.allclose(quat_to_matrix(q) @ [1, 0, 0], [0, 1, 0])


def test_errors():
    q = random_quats(10, seed=2)
    assert np.allclose(attitude_error_deg(q, -q), 0, atol=1e-5)  # q and -q are the same attitude
    q2 = matrix_to_quat(quat_to_matrix(q) @ euler_to_matrix(np.array([0, 0, 7.0])))
    assert np.allclose(attitude_error_deg(q2, q), 7.0, atol=1e-6)
    assert np.allclose(position_error(np.array([[3.0, 4, 0]]), np.zeros((1, 3))), 5.0)


def test_ray_rotation_takes_the_optical_axis_onto_the_ray_and_allocentric_round_trips():
    from pipeline.geometry.allocentric import ray_rotation, to_allocentric, to_egocentric

    rng = np.random.default_rng(0)
    t = np.concatenate([rng.normal(0, 5, (50, 2)), rng.uniform(10, 60, (50, 1))], 1)
    t[0] = (0.0, 0.0, 30.0)  # on the axis: identity
    Rr = ray_rotation(t)
    assert np.allclose(Rr @ np.array([0.0, 0.0, 1.0]), t / np.linalg.norm(t, axis=1, keepdims=True))
    assert np.allclose(Rr @ np.swapaxes(Rr, 1, 2), np.eye(3)) and np.allclose(np.linalg.det(Rr), 1.0)
    assert np.allclose(Rr[0], np.eye(3))
    R = sixd_to_matrix(rng.normal(size=(50, 6)))
    assert np.allclose(to_egocentric(to_allocentric(R, t), t), R)
    assert not np.allclose(to_allocentric(R[1:], t[1:]), R[1:])  # off the axis it differs
