"""The pose model's measurement noise as the motion filter sees it (pipeline/defense/kalman.py).

Measurement noise is the pose model's own error, which grows with range and is larger along the
camera boresight: `NoiseModel` holds per-camera-axis standard deviations and biases a + b * range
(metres, range in metres), fitted by `fit_noise` on clean frames of validation data (never the test
split); `inflate` widens it (pipeline/defense/calibration.py chooses by how much, on clean validation
frames).
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass
from typing import Annotated

import numpy as np
from scipy.spatial.transform import Rotation

from pipeline.settings import In

Range = Annotated[float, In("(0, 100000]", "metres")]  # a range knot
Std = Annotated[float, In("(0, 100000]", "metres")]  # a position standard deviation at a knot


def check_positive(name: str, value: float) -> float:
    """`value` as a float, refused (naming it `name`) unless finite and > 0."""
    v = float(value)
    if not np.isfinite(v) or v <= 0:
        raise ValueError(f"{name} must be a finite number > 0, got {value}")
    return v


@dataclass(frozen=True)
class NoiseModel:
    """Pose-estimate noise: std per camera axis (x, y, z) = intercept + slope * range (metres), the
    attitude std (degrees) = intercept + slope * range, and the position bias per camera axis
    (metres) = bias_intercept + bias_slope * range, range in metres. With `knots` (increasing ranges,
    m) the position std and bias are instead interpolated linearly between their values at the knots
    (`knot_std`, `knot_bias`: one (x, y, z) triple per knot, m; `knot_attitude`: the attitude std per
    knot, degrees), constant beyond the end knots: the pose model's errors are not linear in range
    (the boresight bias changes sign along the approach)."""

    position_intercept: tuple[float, float, float]
    position_slope: tuple[float, float, float]
    attitude_intercept: float
    attitude_slope: float
    floor: Annotated[float, In("(0, 1000]", "metres")] = 0.02  # smallest position std used (a fit can go to 0)
    bias_intercept: tuple[float, float, float] = (0.0, 0.0, 0.0)
    bias_slope: tuple[float, float, float] = (0.0, 0.0, 0.0)
    knots: tuple[Range, ...] = ()
    knot_std: tuple[tuple[Std, Std, Std], ...] = ()
    knot_bias: tuple[tuple[float, float, float], ...] = ()
    knot_attitude: tuple[Annotated[float, In("(0, 180]", "degrees")], ...] = ()

    def __post_init__(self) -> None:
        for name, v in (
            ("position_intercept", self.position_intercept),
            ("position_slope", self.position_slope),
            ("bias_intercept", self.bias_intercept),
            ("bias_slope", self.bias_slope),
        ):
            if len(v) != 3 or not np.all(np.isfinite(v)):
                raise ValueError(f"noise model {name} must be 3 finite numbers, got {v}")
        if not np.isfinite(self.attitude_intercept) or not np.isfinite(self.attitude_slope):
            raise ValueError("noise model attitude intercept and slope must be finite")
        check_positive("noise model floor", self.floor)
        knots = tuple(float(v) for v in self.knots)
        std, bias = (tuple(tuple(float(x) for x in row) for row in t) for t in (self.knot_std, self.knot_bias))
        if knots:
            att = tuple(float(v) for v in self.knot_attitude)
            shaped = len(knots) >= 2 and all(len(t) == len(knots) and all(len(r) == 3 for r in t) for t in (std, bias))
            shaped = shaped and len(att) == len(knots)
            if (
                not shaped
                or not np.all(np.diff(knots) > 0)
                or not np.isfinite([*knots, *att, *np.ravel(std), *np.ravel(bias)]).all()
            ):
                raise ValueError(
                    "noise model knots must be >= 2 increasing finite ranges with one finite (x, y, z) "
                    "std and bias and one attitude std each"
                )
            object.__setattr__(self, "knot_attitude", att)
        object.__setattr__(self, "knots", knots)
        object.__setattr__(self, "knot_std", std)
        object.__setattr__(self, "knot_bias", bias)

    def terms(self, rng: float) -> tuple[list[float], list[float]]:
        """(bias (3,), std (3,)) in metres along the camera axes at range `rng` (m), as plain floats."""
        if not self.knots:
            a, b, sa, sb = self.bias_intercept, self.bias_slope, self.position_intercept, self.position_slope
            return ([a[i] + b[i] * rng for i in range(3)], [max(sa[i] + sb[i] * rng, self.floor) for i in range(3)])
        k, w = self._knot(rng)
        b0, b1, s0, s1 = self.knot_bias[k - 1], self.knot_bias[k], self.knot_std[k - 1], self.knot_std[k]
        return (
            [b0[i] + w * (b1[i] - b0[i]) for i in range(3)],
            [max(s0[i] + w * (s1[i] - s0[i]), self.floor) for i in range(3)],
        )

    def _knot(self, rng: float) -> tuple[int, float]:
        """(k, w): `rng` (m) lies a fraction w of the way from knot k - 1 to knot k (clamped to [0, 1])."""
        x = self.knots
        k = min(max(bisect.bisect_left(x, rng), 1), len(x) - 1)
        return k, min(max((rng - x[k - 1]) / (x[k] - x[k - 1]), 0.0), 1.0)

    def position_std(self, rng: float) -> np.ndarray:
        """(3,) std (m) along the camera x, y, z axes at range `rng` (m)."""
        return np.array(self.terms(rng)[1])

    def position_bias(self, rng: float) -> np.ndarray:
        """(3,) mean error (m) along the camera x, y, z axes at range `rng` (m)."""
        return np.array(self.terms(rng)[0])

    def attitude_std(self, rng: float) -> float:
        """Attitude std (radians) per axis at range `rng` (m), at least 0.1 degrees."""
        if not self.knots:
            return math.radians(max(self.attitude_intercept + self.attitude_slope * rng, 0.1))
        k, w = self._knot(rng)
        a = self.knot_attitude
        return math.radians(max(a[k - 1] + w * (a[k] - a[k - 1]), 0.1))

    def as_dict(self) -> dict[str, object]:
        return {
            "position_intercept": list(self.position_intercept),
            "position_slope": list(self.position_slope),
            "attitude_intercept": self.attitude_intercept,
            "attitude_slope": self.attitude_slope,
            "floor": self.floor,
            "bias_intercept": list(self.bias_intercept),
            "bias_slope": list(self.bias_slope),
            "knots": list(self.knots),
            "knot_std": [list(r) for r in self.knot_std],
            "knot_bias": [list(r) for r in self.knot_bias],
            "knot_attitude": list(self.knot_attitude),
        }


def inflate(noise: "NoiseModel", k: float, attitude: float | None = None) -> "NoiseModel":
    """The noise model with every position standard deviation (and the floor) times `k` > 0 and the
    attitude's times `attitude` (> 0; default k); biases kept."""
    import dataclasses

    check_positive("noise inflation", k)
    a = check_positive("attitude noise inflation", k if attitude is None else attitude)
    return dataclasses.replace(
        noise,
        position_intercept=tuple(k * v for v in noise.position_intercept),
        position_slope=tuple(k * v for v in noise.position_slope),
        attitude_intercept=a * noise.attitude_intercept,
        attitude_slope=a * noise.attitude_slope,
        floor=k * noise.floor,
        knot_std=tuple(tuple(k * v for v in row) for row in noise.knot_std),
        knot_attitude=tuple(a * v for v in noise.knot_attitude),
    )


def fit_noise(
    t_true: np.ndarray,
    t_pred: np.ndarray,
    R_true: np.ndarray | None = None,
    R_pred: np.ndarray | None = None,
    bins: int = 8,
) -> NoiseModel:
    """Fit a `NoiseModel` to clean validation estimates.

    t_true, t_pred: (N, 3) camera-frame positions (m); R_true, R_pred: optional (N, 3, 3) target ->
    camera rotations. The frames are binned by true range into `bins` equal-count bins; in each bin
    the median error (the bias) and the robust std of the error (1.4826 * median absolute deviation
    from the bin median, per camera axis) are taken: the model interpolates them between the bins'
    mean ranges (`NoiseModel.knots`); lines a + b * range fitted to both by least squares over the
    bins summarise them (and give the attitude std). Without rotations the attitude std is a
    constant 5 degrees.
    """
    t_true, t_pred, bins = _checked_fit_input(t_true, t_pred, bins)
    rng = np.linalg.norm(t_true, axis=1)
    err = t_pred - t_true
    att = None
    if R_true is not None and R_pred is not None:
        rel = np.swapaxes(np.asarray(R_true), -1, -2) @ np.asarray(R_pred)
        att = np.degrees(Rotation.from_matrix(rel).as_rotvec())  # (N, 3) degrees, target frame
    order = np.argsort(rng)
    centres, pos_std, att_std, bias = [], [], [], []
    for idx in np.array_split(order, bins):
        centres.append(rng[idx].mean())
        e = err[idx]
        bias.append(np.median(e, 0))
        pos_std.append(1.4826 * np.median(np.abs(e - bias[-1]), 0))
        if att is not None:
            a = att[idx]
            att_std.append(float(np.mean(1.4826 * np.median(np.abs(a - np.median(a, 0)), 0))))
    A = np.column_stack([np.ones(bins), centres])
    coef = np.linalg.lstsq(A, np.asarray(pos_std), rcond=None)[0]  # (2, 3)
    bcoef = np.linalg.lstsq(A, np.asarray(bias), rcond=None)[0]
    if att is not None:
        a0, a1 = np.linalg.lstsq(A, np.asarray(att_std), rcond=None)[0]
    else:
        a0, a1 = 5.0, 0.0
    return NoiseModel(
        tuple(map(float, coef[0])),
        tuple(map(float, coef[1])),
        float(a0),
        float(a1),
        bias_intercept=tuple(map(float, bcoef[0])),
        bias_slope=tuple(map(float, bcoef[1])),
        knots=tuple(map(float, centres)),
        knot_std=tuple(tuple(map(float, v)) for v in pos_std),
        knot_bias=tuple(tuple(map(float, v)) for v in bias),
        knot_attitude=tuple(map(float, att_std)) if att is not None else (5.0,) * bins,
    )


def _checked_fit_input(t_true: np.ndarray, t_pred: np.ndarray, bins: int) -> tuple[np.ndarray, np.ndarray, int]:
    """`fit_noise`'s positions (N, 3) (camera frame, m) as float64 and its bin count as an int; a ValueError for
    mismatched shapes, NaN or inf, or fewer than 4 frames per bin (at least 2 bins)."""
    t_true, t_pred = np.asarray(t_true, np.float64), np.asarray(t_pred, np.float64)
    if t_true.ndim != 2 or t_true.shape[1] != 3 or t_true.shape != t_pred.shape:
        raise ValueError(f"fit_noise needs (N, 3) true and predicted positions, got {t_true.shape} and {t_pred.shape}")
    if not (np.isfinite(t_true).all() and np.isfinite(t_pred).all()):
        raise ValueError("fit_noise: positions contain NaN or inf")
    bins = int(bins)
    if bins < 2 or len(t_true) < 4 * bins:
        raise ValueError(
            f"fit_noise needs at least {4 * max(bins, 2)} frames for {max(bins, 2)} range bins, got {len(t_true)}"
        )
    return t_true, t_pred, bins
