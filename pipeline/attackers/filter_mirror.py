"""A differentiable copy of the defense's motion filter, for attackers that steer the trusted estimate.

`FilterMirror` replays `pipeline.defense.kalman.MotionFilter` in torch (float64), batched over
R independent runs of the attacker (restarts x lambdas), on the path the attacker wants: every
frame passes every check and updates the filter (`MotionFilter.check`, `test_sequence` then
`accept`, Huber weight above the soft gate included): the position state rel alone moved by the
commands, the attitude's rate model, and the sequential test's CUSUM statistics
(pipeline/defense/sequential.py). It starts from a copy of the defense's filter in the state the
frames before the burst left it (or, when that filter has not started, starts on the first frame
as `MotionFilter.start_from` does), so the trusted estimate it returns (rel, world frame, m) is
what the defense would fly on if it accepted the frames, with the gradient of that estimate, of
both gates' NIS and of the CUSUM statistic with respect to the pose estimates. Frames the real
defense flags coast instead; the attacker prices that with the margins and checks its result on
the real defense. The caller's filter is only read.
`FilterMirror.protection_level` replays the protection level's accumulators
(pipeline/defense/protection.py, `ProtectionLevel`) on that path, differentiably: the gain-weighted
camera axes W_j = K_j R_j diag(sigma_j) of every accepted frame (the trusted frames after a first start
left out, as `MotionFilter._bound` does) and the state covariance, so an attacker can ascend trusted
error / PL. A trusted start the detector has doubted (PL inf until the anchor, `MotionFilter.doubt_start`) is not
mirrored: there the mirror's PL is the finite one, and the real defense the attacker checks its result on has none.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from pipeline.defense.kalman import MotionFilter
from pipeline.defense.noise import NoiseModel
from pipeline.geometry.rotations import rotvec_t

DTYPE = torch.float64


def rotmat_t(w: Tensor) -> Tensor:
    """(R, 3) rotation vectors (rad) -> (R, 3, 3) matrices (Rodrigues), differentiable (as `rotmat_list`)."""
    th2 = (w * w).sum(1).clamp_min(1e-16)
    th = th2.sqrt()
    s, k = (torch.sin(th) / th)[:, None, None], ((1 - torch.cos(th)) / th2)[:, None, None]
    zero = torch.zeros_like(w[:, 0])
    W = torch.stack(
        [
            torch.stack([zero, -w[:, 2], w[:, 1]], 1),
            torch.stack([w[:, 2], zero, -w[:, 0]], 1),
            torch.stack([-w[:, 1], w[:, 0], zero], 1),
        ],
        1,
    )
    return torch.eye(3, dtype=w.dtype) + s * W + k * (W @ W)


def noise_terms_t(noise: NoiseModel, rng: Tensor) -> tuple[Tensor, Tensor]:
    """`NoiseModel.terms` in torch, differentiable in the range: rng (R, 1) m -> (bias (R, 3), std (R, 3)) m."""
    as_t = lambda a: torch.as_tensor(np.asarray(a, np.float64), dtype=rng.dtype)  # noqa: E731
    if not noise.knots:
        bias = as_t(noise.bias_intercept) + as_t(noise.bias_slope) * rng
        return bias, torch.clamp(as_t(noise.position_intercept) + as_t(noise.position_slope) * rng, min=noise.floor)
    x = as_t(noise.knots)
    k = torch.searchsorted(x, rng.detach().contiguous()).clamp(1, len(x) - 1)  # (R, 1)
    w = ((rng - x[k - 1]) / (x[k] - x[k - 1])).clamp(0.0, 1.0)

    def lerp(table: tuple) -> Tensor:
        v = as_t(table)  # (knots, 3)
        return v[k[:, 0] - 1] + w * (v[k[:, 0]] - v[k[:, 0] - 1])

    return lerp(noise.knot_bias), torch.clamp(lerp(noise.knot_std), min=noise.floor)


def attitude_std_t(noise: NoiseModel, rng: Tensor) -> Tensor:
    """`NoiseModel.attitude_std` in torch: rng (R,) or (R, 1) m -> the attitude std (radians), same shape."""
    if not noise.knots:
        return torch.deg2rad(torch.clamp(noise.attitude_intercept + noise.attitude_slope * rng, min=0.1))
    x = torch.as_tensor(noise.knots, dtype=rng.dtype)
    a = torch.as_tensor(noise.knot_attitude, dtype=rng.dtype)
    k = torch.searchsorted(x, rng.detach().contiguous()).clamp(1, len(x) - 1)
    w = ((rng - x[k - 1]) / (x[k] - x[k - 1])).clamp(0.0, 1.0)
    return torch.deg2rad(torch.clamp(a[k - 1] + w * (a[k] - a[k - 1]), min=0.1))


def _sym(A: Tensor) -> Tensor:
    return (A + A.transpose(1, 2)) / 2


class FilterMirror:
    """`motion` (read, never changed) replayed for `runs` runs; call `step` once per burst frame."""

    def __init__(self, motion: MotionFilter, runs: int):
        s, self.noise, self.runs = motion.settings, motion.noise, int(runs)
        self.gate, self.soft = float(motion.gate), float(s.soft_gate * motion.gate)
        self.q = motion.pos.q_level
        self.att_q, self.att_q_rate = motion.att.q_level, motion.att.q_rate
        self.att_rate_std = 3 * math.radians(s.attitude_rate_noise_deg)
        self.reference, self.threshold = motion.cusum.reference, motion.cusum.threshold
        self.started = motion.started
        self.trusted_start, self.trusted = s.trusted_start, motion._trusted
        pl = motion.protection
        self.kappa, self.offset, self.correlated = pl.kappa, pl.offset, pl.correlated
        # the correlated variance held from the anchor (m^2; assumption C); None before the anchor
        self.held = None if not self.started or pl.start is None else torch.full((self.runs,), pl.held, dtype=DTYPE)

        def rep(a: object) -> Tensor:
            return torch.as_tensor(np.asarray(a, np.float64)).expand(self.runs, *np.shape(a)).clone()

        self.high, self.low = rep(motion.cusum.high), rep(motion.cusum.low)
        self.total, self.rise, self.last = rep(pl.total), rep(pl.rise), rep(pl.last)
        if self.started:
            self.level, self.A = rep(motion.pos.level), rep(motion.pos.A)
            self.att_rate, self.R_tw = rep(motion.att.rate), rep(motion.R_tw)
            self.p = tuple(torch.full((self.runs,), float(v), dtype=DTYPE) for v in motion.att.p)

    def step(
        self, t: Tensor, R_pred: Tensor, R_cam: np.ndarray, u: np.ndarray | None
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """One accepted frame: t (R, 3) camera-frame estimates (m), R_pred (R, 3, 3) target -> camera,
        R_cam (3, 3) camera -> world, u (3,) commanded displacement (world, m) or None.
        Returns (trusted rel after the frame (R, 3), world, m; NIS of position (R,); NIS of attitude
        (R,); the largest CUSUM statistic after the frame (R,), standard deviations); NIS and CUSUM
        are 0 on the frame that starts the filter (it is not tested)."""
        t, R_pred = t.to(DTYPE), R_pred.to(DTYPE)
        R_cam_t = torch.as_tensor(np.asarray(R_cam, np.float64))
        R_meas = R_cam_t @ R_pred
        if not self.started:
            z, Rz = self._measurement(t, t.norm(dim=1), R_cam_t)
            self._start(z, Rz, R_meas)
            zero = torch.zeros(self.runs, dtype=DTYPE)
            return self.level, zero, zero, zero
        self._predict(u)
        rng = self.level.norm(dim=1)  # the noise model at the predicted range, as the filter
        z, Rz = self._measurement(t, rng, R_cam_t)
        nis_p, cusum = self._update_position(z - self.level, Rz, R_cam_t)
        nis_a = self._update_attitude(R_meas, rng)
        return self.level, nis_p, nis_a, cusum

    def _measurement(self, t: Tensor, rng: Tensor, R_cam: Tensor) -> tuple[Tensor, Tensor]:
        """(z (R, 3), Rz (R, 3, 3)): `MotionFilter.measurement`, bias removed, covariance in world axes."""
        bias, std = noise_terms_t(self.noise, rng[:, None])
        z = (t - bias) @ R_cam.T
        return z, R_cam @ torch.diag_embed(std**2) @ R_cam.T

    def _attitude_var(self, rng: Tensor) -> Tensor:
        return attitude_std_t(self.noise, rng) ** 2

    def _start(self, z: Tensor, Rz: Tensor, R_meas: Tensor) -> None:
        """`MotionFilter.start_from` on the first frame (attitude std at the range of z)."""
        rng = z.norm(dim=1)
        self.level, self.A = z, Rz
        self.att_rate, self.R_tw = torch.zeros_like(z), R_meas
        self.p = (self._attitude_var(rng), torch.zeros_like(rng), torch.full_like(rng, self.att_rate_std**2))
        self.high, self.low = torch.zeros_like(z), torch.zeros_like(z)
        self.total, self.rise, self.last = (torch.zeros(self.runs, 3, 3, dtype=DTYPE) for _ in range(3))
        self.offset, self.trusted = 0.0, self.trusted_start
        self.held = self.correlated * self._measurement_variance() if self.trusted == 0 else None
        self.started = True

    def _measurement_variance(self) -> Tensor:
        """(R,) one measurement's largest variance per camera axis at the state's range (m^2), as
        `MotionFilter.measurement_variance`."""
        return noise_terms_t(self.noise, self.level.norm(dim=1)[:, None])[1].amax(1) ** 2

    def _predict(self, u: np.ndarray | None) -> None:
        """`Kalman3.predict` and `IsoKalman6.predict` (the attitude rate moved into R_tw)."""
        if u is not None:
            self.level = self.level + torch.as_tensor(np.asarray(u, np.float64))
        self.A = self.A + self.q * torch.eye(3, dtype=DTYPE)
        a, b, c = self.p
        self.p = (a + 2 * b + c + self.att_q, b + c, c + self.att_q_rate)
        self.R_tw = self.R_tw @ rotmat_t(self.att_rate)

    def _update_position(self, y: Tensor, Rz: Tensor, R_cam: Tensor) -> tuple[Tensor, Tensor]:
        """NIS of the innovation y (R, 3) and the CUSUM after it (`Cusum.push` on the innovation along
        the camera axes over its standard deviations there), then `Kalman3.update` with the
        Huber-inflated covariance."""
        S = self.A + Rz
        nis = (y * torch.linalg.solve(S, y.unsqueeze(2)).squeeze(2)).sum(1)
        sigma = torch.diagonal(R_cam.T @ S @ R_cam, dim1=1, dim2=2).sqrt()
        r = (y @ R_cam) / sigma
        self.high = torch.clamp(self.high + r - self.reference, min=0.0)
        self.low = torch.clamp(self.low - r - self.reference, min=0.0)
        cusum = torch.maximum(self.high.amax(1), self.low.amax(1))
        R = Rz * torch.clamp(nis / self.soft, min=1.0)[:, None, None]
        K = self.A @ torch.linalg.inv(self.A + R)
        self._bound((K @ R_cam) * sigma[:, None, :])
        self.level = self.level + (K @ y.unsqueeze(2)).squeeze(2)
        M = torch.eye(3, dtype=DTYPE) - K
        self.A = _sym(M @ self.A @ M.transpose(1, 2) + K @ R @ K.transpose(1, 2))
        if self.trusted == 0 and self.held is None:  # the anchor: the last trusted frame was just accepted
            self.held = self.correlated * self._measurement_variance()
        return nis, cusum

    def _bound(self, W: Tensor) -> None:
        """`ProtectionLevel.add` of an accepted frame's weights W (R, 3, 3) (world rows, camera columns, m),
        unless it is one of the trusted frames after the first start."""
        if self.trusted > 0:
            self.trusted -= 1
            return
        pos, neg = W.clamp(min=0.0), (-W).clamp(min=0.0)
        self.rise = (
            self.rise
            + (pos - self.last.clamp(min=0.0)).clamp(min=0.0)
            + (neg - (-self.last).clamp(min=0.0)).clamp(min=0.0)
        )
        self.total = self.total + W.abs()
        self.last = W

    def protection_level(self) -> Tensor:
        """PL (R,) m of the current state: kappa sqrt(lambda_max(P) + B) + |b| + the carried offset
        (`ProtectionLevel.level`, B its correlated variance); inf before the start."""
        if not self.started:
            return torch.full((self.runs,), math.inf, dtype=DTYPE)
        b = (self.reference * self.total + self.threshold * self.rise).sum(2)  # (R, 3) world axes
        lam = torch.linalg.eigvalsh(_sym(self.A))[:, -1].clamp(min=0.0)
        held = self.correlated * self._measurement_variance() if self.held is None else self.held
        return self.kappa * (lam + held).sqrt() + b.norm(dim=1) + self.offset

    def _update_attitude(self, R_meas: Tensor, rng: Tensor) -> Tensor:
        """NIS of the attitude error, then `IsoKalman6.update` (Huber-inflated) moved into R_tw."""
        dth = rotvec_t(self.R_tw.transpose(1, 2) @ R_meas)
        var = self._attitude_var(rng)
        a, b, c = self.p
        nis = (dth * dth).sum(1) / (a + var)
        r = var * torch.clamp(nis / self.soft, min=1.0)
        ka, kb = a / (a + r), b / (a + r)
        self.att_rate = self.att_rate + kb[:, None] * dth
        self.p = (
            (1 - ka) ** 2 * a + ka * ka * r,
            (1 - ka) * (b - kb * a) + ka * kb * r,
            kb * kb * a - 2 * kb * b + c + kb * kb * r,
        )
        self.R_tw = self.R_tw @ rotmat_t(ka[:, None] * dth)
        return nis
