"""The protection level (PL, metres): a bound on the trusted estimate's error, per frame (RAIM's slope
construction adapted to the motion filter of pipeline/defense/kalman.py).

Model (world axes, metres). The chaser commands its own relative motion: rel_k = rel_{k-1} + u_k + w_k,
u_k known, w_k the execution error (std `position_noise` per axis); the measurement of frame k is
z_k = rel_k + v_k + f_k, v_k ~ N(0, R_k) the pose model's noise (pipeline/defense/noise.py), f_k a
fault (an attack's bias). The filter predicts x_k^- = x_{k-1} + u_k, and on a frame it accepts updates
x_k = x_k^- + K_k nu_k with the innovation nu_k = z_k - x_k^- (a frame it leaves out coasts: x_k = x_k^-).
So the error e_k = x_k - rel_k obeys e_k = e_{k-1} - w_k + K_k nu_k: it is linear in (v, w, f) once
the filter's choices (which frames it accepts, the Huber weights in K_k) are fixed, and splits into
e = e^0 + e^f: e^0 the error the same filter would have without faults, e^f that of the faults:
    e^f_k = e^f_{k-1} + K_k nu^f_k,  nu^f_k = f_k - e^f_{k-1},  so  e^f_n = sum_{accepted j <= n} K_j nu^f_j,
given (A) no fault on the frame the filter started from nor on the `trusted_start` frames after its
first start (their W_j below are left out of the sums; see restarts below for later starts). A bias
present from the start is consistent with the commanded motion (no motion check can see it), and the
first frames, far out and with the largest gains, are where a slowly established bias grows fastest:
on 25 validation trajectories the fault bound of the first 20 frames alone is most of the PL at
the goal. The detector alone guards them.

Fault-free part: e^0_n ~ N(0, P_n) under the noise model, so |e^0_n| <= kappa sqrt(lambda_max(P_n))
with probability 1 - risk, kappa^2 the chi-square(3) quantile at 1 - `integrity_risk` (per frame).

Fault part: the sequential test (pipeline/defense/sequential.py) works along the camera axes c_{j,k}
(the columns of frame j's camera attitude R_j, camera -> world), where the noise model is diagonal:
write nu^f_j = R_j diag(sigma_j) rho_j with sigma_{j,k} = sqrt(c_{j,k}^T S_j c_{j,k}) the scale it
normalizes by. (B) The fault is undetected: the CUSUM's statistics driven by it stay under h, i.e.
every window of tested frames has |sum_a..b rho_{j,k}| <= c (b - a + 1) + h (the noise's share of the
statistics is what h's calibrated false-alarm rate pays for). Component i (world axis) of e^f_n is
sum_k sum_j W_j[i, k] rho_{j,k} with W_j = K_j R_j diag(sigma_j) (world axis i, camera axis k; the
camera turns slowly, so axis k is nearly the same direction from frame to frame). Split
the weights W_j[i, k] into their positive and negative parts W+ and W- (>= 0) and
write rho = c + d, with every window sum of d at most h. Layer-cake: a sequence W >= 0 is the integral
over levels t > 0 of the indicator of {j: W_j >= t}, a union of N(t) runs of consecutive frames, and
the integral of N(t) is TV+(W) = sum_j max(W_j - W_{j-1}, 0) (W_0 = 0). Each run's sum of d is a
window sum (<= h), so sum_j W_j d_j <= h TV+(W), and
    |e^f_{n,i}| <= sum_k [ c sum_j |W_j[i, k]| + h (TV+(W+) + TV+(W-)) ] =: b_i,
the same bound for -e^f (the window constraint is two-sided). Frames the test saw but the filter
left out have W = 0; frames the test did not see (the gate or the detector left them out) are not
in the sequence. An alarm restarts the test (pipeline/defense/sequential.py): the constraint holds
within each segment between alarms, the alarming frame is left out (W = 0), so the next segment's
first weight counts in full in TV+ and the bound is the sum of the segments' bounds. Hence
    PL_n = kappa sqrt(lambda_max(P_n)) + |b| (+ a restart's carried offset, below).
With exact commands and a small process noise the gains decay like 1/n until they settle near
q / sigma_R, so sum_j |W_j| grows like sigma_R ln n and then by about q per frame: the c term
is the slow ramp (under c q per frame) that no test of this filter can tell from the execution error,
and it is why the process noise must stay small. The h term is the transient the test lets through,
largest right after a start, where the gain is largest, and paid again after each alarm.

Alternatives measured on those validation trajectories: the bound of the plain CUSUM weights with a
linear-in-range noise model and no trusted start gave PLs of 60-100 m; a Gauss-Markov measurement-bias
state in the filter (a bounded drift state) enlarged them.

Restarts (`MotionFilter.reacquire`): the new state is the mean of M frames that agreed with the
median of the last 2 M accepted measurements within the gate. An accepted measurement's fault is
nu^f + e^f_{j-1}, at most sqrt(gate) sigma_S + |b| (per-frame gate, fault bound), and the candidates
lie within sqrt(gate lambda_max(C)) of that median (C: their mean's covariance plus one frame's R), so
the restarted filter carries offset |b| + sqrt(gate) (sigma_S + sqrt(lambda_max(C))) (conservatively
2 sqrt(gate lambda_max(C)) for the two gate terms, C >= S) into its new bound, and no trusted frames.
A first start (no history) rests on assumption (A).
"""
from __future__ import annotations

import math
from typing import Sequence

from scipy.stats import chi2

Mat3 = list[list[float]]


def largest_eigenvalue(A: Mat3) -> float:
    """lambda_max of a symmetric 3x3 matrix (nested lists), closed form (trigonometric), plain floats."""
    p1 = A[0][1] ** 2 + A[0][2] ** 2 + A[1][2] ** 2
    if p1 == 0.0:
        return max(A[0][0], A[1][1], A[2][2])
    q = (A[0][0] + A[1][1] + A[2][2]) / 3.0
    p = math.sqrt(((A[0][0] - q) ** 2 + (A[1][1] - q) ** 2 + (A[2][2] - q) ** 2 + 2.0 * p1) / 6.0)
    (a, b, c), (_, e, f), (_, _, i) = [[(v - (q if r == k else 0.0)) / p for k, v in enumerate(row)]
                                       for r, row in enumerate(A)]
    half_det = (a * (e * i - f * f) - b * (b * i - f * c) + c * (b * f - e * c)) / 2.0
    phi = math.acos(max(-1.0, min(1.0, half_det))) / 3.0
    return q + 2.0 * p * math.cos(phi)


def kappa(integrity_risk: float) -> float:
    """The multiplier of sqrt(lambda_max(P)) that bounds a 3-D Gaussian error's norm with probability
    1 - integrity_risk: sqrt of the chi-square(3) quantile."""
    if not 0 < integrity_risk < 1:
        raise ValueError(f"defense.integrity_risk must be a probability in (0, 1), got {integrity_risk}")
    return math.sqrt(float(chi2.ppf(1.0 - integrity_risk, 3)))


class ProtectionLevel:
    """The PL's accumulators over one filter run (see the module docstring): `add` once per frame the
    sequential test saw (G = K R: the gain times the camera attitude, 3x3, world rows and camera
    columns, of an accepted frame; None for one it left out) with the test's scales sigma (3,) (m,
    camera axes); `level(P)` the PL (m) for the state covariance P (3x3, m^2)."""

    def __init__(self, reference: float, threshold: float, integrity_risk: float):
        self.reference, self.threshold = float(reference), float(threshold)
        self.kappa = kappa(integrity_risk)
        self.reset()

    def reset(self, offset: float = 0.0) -> None:
        """A new filter run, carrying `offset` (m) of bias bound from the previous one."""
        self.offset = float(offset)
        self.total = [[0.0] * 3 for _ in range(3)]        # sum_j |W_j[i, k]|
        self.rise = [[0.0] * 3 for _ in range(3)]         # TV+(W+) + TV+(W-)
        self.last = [[0.0] * 3 for _ in range(3)]         # W_{j-1}[i, k] (signed)

    def add(self, G: Mat3 | None, sigma: Sequence[float]) -> None:
        for i in range(3):
            total, rise, last = self.total[i], self.rise[i], self.last[i]
            for k in range(3):
                w = 0.0 if G is None else G[i][k] * sigma[k]
                prev = last[k]
                rise[k] += max(max(w, 0.0) - max(prev, 0.0), 0.0) + max(max(-w, 0.0) - max(-prev, 0.0), 0.0)
                total[k] += abs(w)
                last[k] = w

    def bias(self) -> float:
        """|b| + the carried offset (m): the largest error an undetected fault can cause."""
        c, h = self.reference, self.threshold
        b = [sum(c * t + h * r for t, r in zip(self.total[i], self.rise[i])) for i in range(3)]
        return math.sqrt(b[0] * b[0] + b[1] * b[1] + b[2] * b[2]) + self.offset

    def level(self, P: Mat3) -> float:
        """PL (m) = kappa sqrt(lambda_max(P)) + bias."""
        return self.kappa * math.sqrt(max(largest_eigenvalue(P), 0.0)) + self.bias()
