"""A differentiable copy of the defense's motion filter, for attackers that steer the trusted estimate.

`FilterMirror` replays `pipeline.defense.kalman.MotionFilter` in torch (float64), batched over
R independent runs of the attacker (restarts x lambdas), on the path the attacker wants: every
frame passes both checks and updates the filter (`MotionFilter.check` then `accept`, Huber weight
above the soft gate included). It starts from a copy of the defense's filter in the state the
frames before the burst left it (or, when that filter has not started, starts on the first frame
as `MotionFilter.start_from` does), so the trusted estimate it returns (rel, world frame, m) is
what the defense would fly on if it accepted the frames, with the gradient of that estimate and
of both gates' NIS with respect to the pose estimates. Frames the real defense flags coast
instead; the attacker prices that with the NIS margins and checks its result on the real defense.
The caller's filter is only read.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from pipeline.defense.kalman import MotionFilter
from pipeline.geometry.rotations import rotvec_t

DTYPE = torch.float64


def rotmat_t(w: Tensor) -> Tensor:
    """(R, 3) rotation vectors (rad) -> (R, 3, 3) matrices (Rodrigues), differentiable (as `rotmat_list`)."""
    th2 = (w * w).sum(1).clamp_min(1e-16)
    th = th2.sqrt()
    s, k = (torch.sin(th) / th)[:, None, None], ((1 - torch.cos(th)) / th2)[:, None, None]
    zero = torch.zeros_like(w[:, 0])
    W = torch.stack([torch.stack([zero, -w[:, 2], w[:, 1]], 1), torch.stack([w[:, 2], zero, -w[:, 0]], 1),
                     torch.stack([-w[:, 1], w[:, 0], zero], 1)], 1)
    return torch.eye(3, dtype=w.dtype) + s * W + k * (W @ W)


def _sym(A: Tensor) -> Tensor:
    return (A + A.transpose(1, 2)) / 2


class FilterMirror:
    """`motion` (read, never changed) replayed for `runs` runs; call `step` once per burst frame."""

    def __init__(self, motion: MotionFilter, runs: int):
        s, self.noise, self.runs = motion.settings, motion.noise, int(runs)
        self.gate, self.soft = float(motion.gate), float(s.soft_gate * motion.gate)
        self.q, self.q_rate = motion.pos.q_level, motion.pos.q_rate
        self.att_q, self.att_q_rate = motion.att.q_level, motion.att.q_rate
        self.rate_std = 3 * s.velocity_noise, 3 * math.radians(s.attitude_rate_noise_deg)
        self.started = motion.started
        if self.started:
            def rep(a: object) -> Tensor:
                return torch.as_tensor(np.asarray(a, np.float64)).expand(self.runs, *np.shape(a)).clone()

            self.level, self.rate = rep(motion.pos.level), rep(motion.pos.rate)
            self.A, self.B, self.C = rep(motion.pos.A), rep(motion.pos.B), rep(motion.pos.C)
            self.att_rate, self.R_tw = rep(motion.att.rate), rep(motion.R_tw)
            self.p = tuple(torch.full((self.runs,), float(v), dtype=DTYPE) for v in motion.att.p)

    def step(self, t: Tensor, R_pred: Tensor, R_cam: np.ndarray, u: np.ndarray | None) -> tuple[Tensor, Tensor, Tensor]:
        """One accepted frame: t (R, 3) camera-frame estimates (m), R_pred (R, 3, 3) target -> camera,
        R_cam (3, 3) camera -> world, u (3,) commanded displacement (world, m) or None.
        Returns (trusted rel after the frame (R, 3), world, m; NIS of position (R,); NIS of attitude
        (R,)); both NIS are 0 on the frame that starts the filter (it is not tested)."""
        t, R_pred = t.to(DTYPE), R_pred.to(DTYPE)
        R_cam_t = torch.as_tensor(np.asarray(R_cam, np.float64))
        rng = t.norm(dim=1)
        z, Rz = self._measurement(t, rng, R_cam_t)
        R_meas = R_cam_t @ R_pred
        if not self.started:
            self._start(z, Rz, R_meas)
            zero = torch.zeros(self.runs, dtype=DTYPE)
            return self.level, zero, zero
        self._predict(u)
        nis_p = self._update_position(z - self.level, Rz)
        nis_a = self._update_attitude(R_meas, rng)
        return self.level, nis_p, nis_a

    def _measurement(self, t: Tensor, rng: Tensor, R_cam: Tensor) -> tuple[Tensor, Tensor]:
        """(z (R, 3), Rz (R, 3, 3)): `MotionFilter.measurement`, bias removed, covariance in world axes."""
        n = self.noise
        as_t = lambda a: torch.as_tensor(np.asarray(a, np.float64))  # noqa: E731
        bias = as_t(n.bias_intercept) + as_t(n.bias_slope) * rng[:, None]
        std = torch.clamp(as_t(n.position_intercept) + as_t(n.position_slope) * rng[:, None], min=n.floor)
        z = (t - bias) @ R_cam.T
        return z, R_cam @ torch.diag_embed(std ** 2) @ R_cam.T

    def _attitude_var(self, rng: Tensor) -> Tensor:
        n = self.noise
        return torch.deg2rad(torch.clamp(n.attitude_intercept + n.attitude_slope * rng, min=0.1)) ** 2

    def _start(self, z: Tensor, Rz: Tensor, R_meas: Tensor) -> None:
        """`MotionFilter.start_from` on the first frame (attitude std at the range of z)."""
        rng = z.norm(dim=1)
        self.level, self.rate, self.A = z, torch.zeros_like(z), Rz
        self.B = torch.zeros_like(Rz)
        self.C = torch.eye(3, dtype=DTYPE).expand_as(Rz) * self.rate_std[0] ** 2
        self.att_rate, self.R_tw = torch.zeros_like(z), R_meas
        self.p = (self._attitude_var(rng), torch.zeros_like(rng), torch.full_like(rng, self.rate_std[1] ** 2))
        self.started = True

    def _predict(self, u: np.ndarray | None) -> None:
        """`_Kalman6.predict` and `_IsoKalman6.predict` (the attitude rate moved into R_tw)."""
        eye = torch.eye(3, dtype=DTYPE)
        self.level = self.level + self.rate
        if u is not None:
            self.level = self.level + torch.as_tensor(np.asarray(u, np.float64))
        A, B, C = self.A, self.B, self.C
        self.A = A + B + B.transpose(1, 2) + C + self.q * eye
        self.B, self.C = B + C, C + self.q_rate * eye
        a, b, c = self.p
        self.p = (a + 2 * b + c + self.att_q, b + c, c + self.att_q_rate)
        self.R_tw = self.R_tw @ rotmat_t(self.att_rate)

    def _update_position(self, y: Tensor, Rz: Tensor) -> Tensor:
        """NIS of the innovation y (R, 3), then `_Kalman6.update` with the Huber-inflated covariance."""
        nis = (y * torch.linalg.solve(self.A + Rz, y.unsqueeze(2)).squeeze(2)).sum(1)
        R = Rz * torch.clamp(nis / self.soft, min=1.0)[:, None, None]
        s_inv = torch.linalg.inv(self.A + R)
        A, B, C = self.A, self.B, self.C
        Ka, Kb = A @ s_inv, B.transpose(1, 2) @ s_inv
        self.level = self.level + (Ka @ y.unsqueeze(2)).squeeze(2)
        self.rate = self.rate + (Kb @ y.unsqueeze(2)).squeeze(2)
        M, KaR, KbB = torch.eye(3, dtype=DTYPE) - Ka, Ka @ R, Kb @ B
        self.A = _sym(M @ A @ M.transpose(1, 2) + KaR @ Ka.transpose(1, 2))
        self.B = M @ (B - A @ Kb.transpose(1, 2)) + KaR @ Kb.transpose(1, 2)
        self.C = _sym(Kb @ (A + R) @ Kb.transpose(1, 2) - KbB - KbB.transpose(1, 2) + C)
        return nis

    def _update_attitude(self, R_meas: Tensor, rng: Tensor) -> Tensor:
        """NIS of the attitude error, then `_IsoKalman6.update` (Huber-inflated) moved into R_tw."""
        dth = rotvec_t(self.R_tw.transpose(1, 2) @ R_meas)
        var = self._attitude_var(rng)
        a, b, c = self.p
        nis = (dth * dth).sum(1) / (a + var)
        r = var * torch.clamp(nis / self.soft, min=1.0)
        ka, kb = a / (a + r), b / (a + r)
        self.att_rate = self.att_rate + kb[:, None] * dth
        self.p = ((1 - ka) ** 2 * a + ka * ka * r, (1 - ka) * (b - kb * a) + ka * kb * r,
                  kb * kb * a - 2 * kb * b + c + kb * kb * r)
        self.R_tw = self.R_tw @ rotmat_t(ka[:, None] * dth)
        return nis
