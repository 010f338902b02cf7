"""The motion filter's linear algebra in plain floats: 3x3 nested-list helpers and two small Kalman filters.

Why plain floats (not numpy): see pipeline/defense/kalman.py (a small numpy call costs 5-10 us with the
caches cold after the pose network). `Kalman3`: the position filter on rel (world, m), moved by the
commanded displacement; `IsoKalman6`: the attitude error state [rotation vector, rate] with isotropic
covariances. Tested against the matrix equations in tests/test_motion.py.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from pipeline.geometry.rotations import Mat3


def inv3(S: Mat3) -> Mat3:
    """Inverse of a 3x3 matrix (nested list) by cofactors, in plain floats."""
    (a, b, c), (d, e, f), (g, h, i) = S
    A, B, C = e * i - f * h, f * g - d * i, d * h - e * g
    r = 1.0 / (a * A + b * B + c * C)
    return [
        [A * r, (c * h - b * i) * r, (b * f - c * e) * r],
        [B * r, (a * i - c * g) * r, (c * d - a * f) * r],
        [C * r, (b * g - a * h) * r, (a * e - b * d) * r],
    ]


def mm(A: Mat3, B: Mat3) -> Mat3:
    """A @ B for 3x3 nested lists."""
    (a0, a1, a2), (a3, a4, a5), (a6, a7, a8) = A
    (b0, b1, b2), (b3, b4, b5), (b6, b7, b8) = B
    return [
        [a0 * b0 + a1 * b3 + a2 * b6, a0 * b1 + a1 * b4 + a2 * b7, a0 * b2 + a1 * b5 + a2 * b8],
        [a3 * b0 + a4 * b3 + a5 * b6, a3 * b1 + a4 * b4 + a5 * b7, a3 * b2 + a4 * b5 + a5 * b8],
        [a6 * b0 + a7 * b3 + a8 * b6, a6 * b1 + a7 * b4 + a8 * b7, a6 * b2 + a7 * b5 + a8 * b8],
    ]


def mm_t(A: Mat3, B: Mat3) -> Mat3:
    """A @ B^T for 3x3 nested lists."""
    return [[a[0] * b[0] + a[1] * b[1] + a[2] * b[2] for b in B] for a in A]


def transpose(A: Mat3) -> Mat3:
    """Transpose of a 3x3 nested list."""
    return [list(col) for col in zip(*A)]


def add(A: Mat3, B: Mat3, k: float = 1.0) -> Mat3:
    """A + k B for 3x3 nested lists."""
    return [[a + k * b for a, b in zip(ra, rb)] for ra, rb in zip(A, B)]


def sym(A: Mat3) -> Mat3:
    """(A + A^T) / 2: block products round a covariance's halves apart, and a 3x3 block's
    asymmetry, left alone, grows from frame to frame (1e-16 to 1e-6 in 6000 frames, measured)."""
    return [[(A[i][j] + A[j][i]) * 0.5 for j in range(3)] for i in range(3)]


def mv(A: Mat3, v: Sequence[float]) -> list[float]:
    """A @ v for a 3x3 nested list and a 3-vector."""
    return [r[0] * v[0] + r[1] * v[1] + r[2] * v[2] for r in A]


def eye(k: float = 1.0) -> Mat3:
    return [[k, 0.0, 0.0], [0.0, k, 0.0], [0.0, 0.0, k]]


class Kalman3:
    """Linear Kalman filter on a level a (3): a_k = a_{k-1} + u_k (+ noise of std `q_level` per axis),
    measurement a. In plain floats (see the module docstring); `x` and `P` give numpy copies."""

    def __init__(self, q_level: float):
        self.q_level = q_level**2
        self.level = [0.0] * 3
        self.A = eye()

    @property
    def x(self) -> np.ndarray:
        return np.array(self.level)

    @property
    def P(self) -> np.ndarray:
        return np.array(self.A)

    def reset(self, level: Sequence[float], level_cov: Mat3) -> None:
        self.level = [float(v) for v in level]
        self.A = [[float(v) for v in row] for row in level_cov]

    def predict(self, u: Sequence[float] | None = None, var: float | None = None) -> None:
        """level += u; P += Q, Q = var I (m^2 per axis; None: q_level^2, the filter's own)."""
        if u is not None:
            self.level = [a + d for a, d in zip(self.level, u)]
        self.A = add(self.A, eye(self.q_level if var is None else var))

    def innovation_inverse(self, R: Mat3) -> Mat3:
        """S^-1 with S = P + R (3, 3)."""
        return inv3(add(self.A, R))

    def update(self, y: Sequence[float], R: Mat3, s_inv: Mat3 | None = None) -> Mat3:
        """Update with innovation y and measurement covariance R (`s_inv`: its `innovation_inverse`,
        when known): K = P S^-1, Joseph form P = (I - K) P (I - K)^T + K R K^T. Returns K."""
        s_inv = self.innovation_inverse(R) if s_inv is None else s_inv
        K = mm(self.A, s_inv)
        self.level = [a + d for a, d in zip(self.level, mv(K, y))]
        M = add(eye(), K, -1.0)
        self.A = sym(add(mm_t(mm(M, self.A), M), mm_t(mm(K, R), K)))
        return K


class IsoKalman6:
    """A Kalman filter on [level (3), rate of the level (3)] for the attitude error state, whose P, Q
    and measurement covariances are all multiples of I3 per 3x3 block (isotropic noise): three equal
    scalar filters on
    P = [[a, b], [b, c]] (x) I3, in plain floats. `level` (the rotation-vector error) and `rate`
    are 3-lists."""

    def __init__(self, q_level: float, q_rate: float):
        self.q_level, self.q_rate = q_level**2, q_rate**2
        self.level, self.rate = [0.0] * 3, [0.0] * 3
        self.p = (1.0, 0.0, 1.0)

    @property
    def x(self) -> np.ndarray:
        return np.array(self.level + self.rate)

    @property
    def P(self) -> np.ndarray:
        a, b, c = self.p
        return np.kron(np.array([[a, b], [b, c]]), np.eye(3))

    def reset(self, level_var: float, rate_std: float) -> None:
        """Zero state, level variance `level_var`, rate std `rate_std` (per axis)."""
        self.level, self.rate = [0.0] * 3, [0.0] * 3
        self.p = (level_var, 0.0, rate_std**2)

    def predict(self) -> None:
        self.level = [v + r for v, r in zip(self.level, self.rate)]
        a, b, c = self.p
        self.p = (a + b + b + c + self.q_level, b + c, c + self.q_rate)

    def take_level(self) -> list[float]:
        """The level (3,), set to zero: the caller moves it into its attitude estimate."""
        level, self.level = self.level, [0.0] * 3
        return level

    def nis(self, y: Sequence[float], r: float) -> float:
        """y^T S^-1 y with S = (a + r) I3, `r` the measurement variance per axis."""
        return (y[0] * y[0] + y[1] * y[1] + y[2] * y[2]) / (self.p[0] + r)

    def update(self, y: Sequence[float], r: float) -> list[float]:
        """Update with innovation y (3,) and measurement variance `r` (Joseph form, per axis);
        returns the level correction (3,)."""
        a, b, c = self.p
        ka, kb = a / (a + r), b / (a + r)
        d_level = [ka * v for v in y]
        self.level = [v + dv for v, dv in zip(self.level, d_level)]
        self.rate = [v + kb * w for v, w in zip(self.rate, y)]
        self.p = (
            (1 - ka) ** 2 * a + ka * ka * r,
            (1 - ka) * (b - kb * a) + ka * kb * r,
            kb * kb * a - 2 * kb * b + c + kb * kb * r,
        )
        return d_level
