"""The protection level (PL, metres): a bound on the trusted estimate's error, per frame (RAIM's slope
construction adapted to the motion filter of pipeline/defense/kalman.py).

Model (world axes, metres). The chaser commands its own relative motion: rel_k = rel_{k-1} + u_k + w_k,
u_k known, w_k the execution error (N(0, Q_k), Q_k = q_k^2 I, q_k = hypot(position_noise,
position_noise_scale |u_k|) per axis: pipeline/defense/gate.py `step_variance`); the measurement of frame k is
z_k = rel_k + v_k + f_k, v_k the pose model's noise (pipeline/defense/noise.py: covariance R_k), f_k a
fault (an attack's shift). The filter predicts x_k^- = x_{k-1} + u_k, and on a frame it accepts updates
x_k = x_k^- + K_k nu_k with the innovation nu_k = z_k - x_k^- (a frame it leaves out coasts: x_k = x_k^-).
So the error e_k = x_k - rel_k obeys e_k = e_{k-1} - w_k + K_k nu_k, whatever the gains (Huber weights
included), and from any frame T on
    e_n = e_T - sum_{T < k <= n} w_k + sum_{accepted T < j <= n} K_j nu_j,
with nu_j the whole innovation, noise and fault together: the quantity the checks see. T is the frame
the sums start from: the last of the `trusted_start` frames after the first start (assumption A: no
fault before it), or the start (restart) frame itself.

Innovation term. The sequential test (pipeline/defense/sequential.py) works along the camera axes
c_{j,k} (the columns of frame j's camera attitude R_j, camera -> world), where the noise model is
diagonal: nu_j = R_j diag(sigma_j) rho_j with sigma_{j,k} = sqrt(c_{j,k}^T S_j c_{j,k}) the scale it
normalizes by and rho_j the normalized innovations it pushes. (B) The test does not alarm: its
statistics stay under h, i.e. every window of tested frames has |sum_a..b rho_{j,k}| <= c (b - a + 1)
+ h. Component i (world axis) of the sum is sum_k sum_j W_j[i, k] rho_{j,k} with W_j = K_j R_j
diag(sigma_j) (world axis i, camera axis k; the camera turns slowly, so axis k is nearly the same
direction from frame to frame). Split the weights W_j[i, k] into their positive and negative parts W+
and W- (>= 0) and write rho = c + d, with every window sum of d at most h. Layer-cake: a sequence
W >= 0 is the integral over levels t > 0 of the indicator of {j: W_j >= t}, a union of N(t) runs of
consecutive frames, and the integral of N(t) is TV+(W) = sum_j max(W_j - W_{j-1}, 0) (W_0 = 0). Each
run's sum of d is a window sum (<= h), so sum_j W_j d_j <= h TV+(W), and
    |sum_j W_j rho_j|_i <= sum_k [ c sum_j |W_j[i, k]| + h (TV+(W+) + TV+(W-)) ] =: b_i,
the same bound for the other sign (the window constraint is two-sided). Frames the test saw but the
filter left out have W = 0; frames the test did not see (the gate or the detector left them out) are
not in the sequence. An alarm restarts the test (pipeline/defense/sequential.py): the constraint
holds within each segment between alarms, the alarming frame is left out (W = 0), so the next
segment's first weight counts in full in TV+ and the bound is the sum of the segments' bounds.

Noise term. e_T - sum w_k ~ N(0, P_T + B_T + sum_{T < k <= n} Q_k): the covariance of the filter at T (a
fault-free filter there, A; B_T the part of the pose errors it cannot average away, C) plus the execution
error's random walk since, each step's variance from the
size of its command (the filter is told the command; a step-independent part and a part proportional to the
step, as thrusters err); its norm is at most kappa sqrt(lambda_max(.)) with probability 1 - integrity_risk,
kappa^2 the chi-square(3) quantile. Hence, after T,
    PL_n = kappa sqrt(lambda_max(P_T + B_T + sum_k Q_k)) + |b| (+ a restart's carried offset, below),
and on the trusted frames before T, PL_n = kappa sqrt(lambda_max(P_n + B_n)) (the filter is fault-free there).

Why the whole innovation (the missed-detection allowance). An earlier form split e = e^0 + e^f (the same
filter without faults, and the faults' part) and bounded e^f by the window constraints as though the
test saw the fault alone, with kappa sqrt(lambda_max(P_n)) for e^0. The test sees noise plus fault, and
an attacker who knows the noise (white box: the clean estimates are the network's outputs) spends its
slack: shifts that cancel the noise's innovations (every measurement on the prediction) freeze the filter
at its error at T while the test sees nothing; the faults' part then obeys only |e^f| <= |b| +
|sum_j K_j nu^0_j|, whose last term has covariance sum_j K_j S_j K_j^T = P_T - P_n + sum Q_k (plain
updates), an allowance the split left out. Bounding the whole error through the whole innovations
needs no split and is tighter than adding that allowance: sqrt(P_T + sum Q_k) <= sqrt(P_n) +
sqrt(P_T - P_n + sum Q_k). pipeline/defense/bound.py solves for the worst such attacker.
With exact commands and a small process noise the gains decay like 1/n until they settle near
q / sigma_R, so sum_j |W_j| grows like sigma_R ln n and then by about q per frame: the c term
is the slow ramp (under c q per frame) that no test of this filter can tell from the execution error,
and it is why the process noise must stay small. The h term is the transient the test lets through,
largest right after a start, where the gain is largest, and paid again after each alarm.

Alternatives measured on 25 validation trajectories: the bound of the plain CUSUM weights with a
linear-in-range noise model and no trusted start gave PLs of 60-100 m; a Gauss-Markov measurement-bias
state in the filter (a bounded drift state) enlarged them; on those trajectories the fault bound of
the first 20 frames alone was most of the PL at the goal (hence the trusted start, A).

Restarts (`MotionFilter.reacquire`): the new state is the mean of M frames that agreed with the
median of the last 2 M accepted measurements within the gate. An accepted measurement's fault is
nu^f + e^f_{j-1}, at most sqrt(gate) sigma_S + |b| (per-frame gate, fault bound), and the candidates
lie within sqrt(gate lambda_max(C)) of that median (C: their mean's covariance plus one frame's R), so
the restarted filter carries offset |b| + sqrt(gate) (sigma_S + sqrt(lambda_max(C))) (conservatively
2 sqrt(gate lambda_max(C)) for the two gate terms, C >= S) into its new bound, and no trusted frames:
its T is the restart, P_T the restart's covariance.

Assumptions the PL rests on (each one a way for it to fail):
(A) No fault on the frame the filter first started from nor on the `trusted_start` frames after it: a
    bias present from the start is consistent with the commanded motion (no motion check can see it);
    the detector alone guards them. Once the detector has flagged any frame of the run (before the start
    included), that guard has seen an attack or erred, and the PL is inf on the trusted frames until T
    (`MotionFilter.doubt_start`): an attack at acquisition that the detector flags on most frames no longer
    starts the filter on the one frame it missed and flies on it. pipeline/defense/bound.py does not
    assume A and shows its cost.
(B) The checks themselves: every accepted frame went through the sequential test (its window
    constraint holds deterministically within a segment); the camera attitude of every frame is known.
(C) The noise term: e_T ~ N(0, P_T + B_T), i.e. the pose errors of the frames up to T are Gaussian with the
    (calibrated, inflated) noise model's covariance, a white part the filter averages (P_T) plus a part
    shared by those frames that no averaging removes (B_T = `correlated` x one measurement's largest
    variance per axis at T's range, isotropic). The pose network's errors are correlated from frame to
    frame (why h is calibrated, not derived): at seed 1 of the default profile the robust model's range
    error over the first 20 frames of one test approach (about 60 m) was -1.1 m on average with a
    frame-to-frame spread of 0.4 m, and with B = 0 its trusted error exceeded the PL on 24 clean frames
    in and just after the trusted window (validation: 2.2% of the frames with a PL). `correlated` is
    calibrated on the clean validation trajectories (pipeline/defense/calibration.py
    `protection_coverage`: the smallest share on a grid at which no validation frame's error exceeds its PL),
    so it covers those approaches, not the integrity risk: by exchangeability a new approach exceeds it
    somewhere with probability up to 1 / (validation approaches + 1). After T whiteness is not needed
    (the test bounds the innovations as they are). Reports give the clean errors' exceedances.
(D) The execution error w_k is white, N(0, Q_k) per frame and independent of e_T (a scale error drawn
    afresh each step, as pipeline/guidance/dynamics.py draws it, is covered: it is in q_k); a scale error
    held over the approach (a bias growing with the distance flown) and the unmodelled orbital motion are not.
(E) Risk per frame: kappa is the chi-square(3) quantile at 1 - integrity_risk for one frame. Over an
    approach of N frames the union bound gives at most N x integrity_risk (2e-3 for 200 frames at 1e-5);
    the frames' noise terms share one start error and a random walk, so the true per-approach risk is
    far below the union bound, but no tighter allocation is claimed.
(F) |x| <= kappa sqrt(lambda_max(C)) for x ~ N(0, C) uses the largest eigenvalue in every direction
    (conservative); the fault bound's norm |b| adds the per-axis bounds in quadrature over world axes.
"""

from __future__ import annotations

import math
from typing import Sequence

from scipy.stats import chi2

from pipeline.defense.linear import add, eye

Mat3 = list[list[float]]


def largest_eigenvalue(A: Mat3) -> float:
    """lambda_max of a symmetric 3x3 matrix (nested lists), closed form (trigonometric), plain floats."""
    p1 = A[0][1] ** 2 + A[0][2] ** 2 + A[1][2] ** 2
    if p1 == 0.0:
        return max(A[0][0], A[1][1], A[2][2])
    q = (A[0][0] + A[1][1] + A[2][2]) / 3.0
    p = math.sqrt(((A[0][0] - q) ** 2 + (A[1][1] - q) ** 2 + (A[2][2] - q) ** 2 + 2.0 * p1) / 6.0)
    (a, b, c), (_, e, f), (_, _, i) = [
        [(v - (q if r == k else 0.0)) / p for k, v in enumerate(row)] for r, row in enumerate(A)
    ]
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
    """The PL's accumulators over one filter run (see the module docstring): `anchor(P, var)` once, at the frame
    T the sums start from, with the state covariance P_T (3x3, m^2) and one measurement's largest variance per
    axis there (m^2); `step` once per predicted frame (with its execution error's variance per axis, m^2, when
    it is not `process_noise`'s); `add` once per frame the sequential test saw after T (G = K R: the gain times
    the camera attitude, 3x3, world rows and camera columns, of an accepted frame; None for one it left out)
    with the test's scales sigma (3,) (m, camera axes); `level(P, var)` the PL (m), P the current state
    covariance (3x3, m^2), var one measurement's largest variance per axis at the current range (m^2, used
    before T). `process_noise`: the execution error's std per axis and frame (m); `correlated`: the share of
    one measurement's variance the filter cannot average away (assumption C, in [0, 1])."""

    def __init__(
        self,
        reference: float,
        threshold: float,
        integrity_risk: float,
        process_noise: float = 0.0,
        correlated: float = 0.0,
    ):
        self.reference, self.threshold = float(reference), float(threshold)
        self.kappa = kappa(integrity_risk)
        self.process_var = float(process_noise) ** 2
        if not 0.0 <= float(correlated) <= 1.0:
            raise ValueError(f"the correlated share of the measurement variance must be in [0, 1], got {correlated}")
        self.correlated = float(correlated)
        self.reset()

    def reset(self, offset: float = 0.0) -> None:
        """A new filter run, carrying `offset` (m) of bias bound from the previous one; its sums start at
        `anchor`."""
        self.offset = float(offset)
        self.start: Mat3 | None = None  # P_T, once the sums have started
        self.held = 0.0  # the correlated variance held from T on (m^2 per axis): correlated x var at T
        self.steps = 0  # frames predicted since T
        self.extra = 0.0  # the execution errors' variance since T beyond steps x process_var (m^2 per axis)
        self.total = [[0.0] * 3 for _ in range(3)]  # sum_j |W_j[i, k]|
        self.rise = [[0.0] * 3 for _ in range(3)]  # TV+(W+) + TV+(W-)
        self.last = [[0.0] * 3 for _ in range(3)]  # W_{j-1}[i, k] (signed)

    def anchor(self, P: Mat3, var: float = 0.0) -> None:
        """The sums start at this frame T, whose state covariance is P (3x3, m^2) and where one measurement's
        largest variance per axis is `var` (m^2): its correlated share is held in the noise term from here on."""
        self.start = [list(map(float, row)) for row in P]
        self.steps, self.extra = 0, 0.0
        self.held = self.correlated * float(var)

    def step(self, var: float | None = None) -> None:
        """One more frame predicted; its execution error (variance `var` per axis, m^2; None: the process noise's)
        joins the noise term once the sums started."""
        self.steps += 1
        if var is not None:
            self.extra += float(var) - self.process_var

    def add(self, G: Mat3 | None, sigma: Sequence[float]) -> None:
        for i in range(3):
            total, rise, last = self.total[i], self.rise[i], self.last[i]
            for k in range(3):
                w = 0.0 if G is None else G[i][k] * sigma[k]
                prev = last[k]
                rise[k] += max(max(w, 0.0) - max(prev, 0.0), 0.0) + max(max(-w, 0.0) - max(-prev, 0.0), 0.0)
                total[k] += abs(w)
                last[k] = w

    def bias(self, reference: float | None = None, threshold: float | None = None) -> float:
        """|b| + the carried offset (m): the most the tested innovations (noise and faults) can have moved the
        estimate since T without an alarm, plus what a restart carried. `reference`, `threshold`: c and h in
        place of the test's (0 leaves out the slow ramp c sum|W| or the transients h TV+: the PL's parts,
        pipeline/evaluation/availability.py)."""
        c = self.reference if reference is None else float(reference)
        h = self.threshold if threshold is None else float(threshold)
        b = [sum(c * t + h * r for t, r in zip(self.total[i], self.rise[i])) for i in range(3)]
        return math.sqrt(b[0] * b[0] + b[1] * b[1] + b[2] * b[2]) + self.offset

    def noise_term(self, P: Mat3, var: float = 0.0) -> float:
        """kappa sqrt(lambda_max(C)) (m), C = P_T + sum_k Q_k + B_T once the sums started, else P + B (3x3, m^2);
        B = `correlated` x one measurement's largest variance per axis (isotropic, m^2: `var` now, or at T)."""
        if self.start is None:
            C, held = P, self.correlated * float(var)
        else:
            C, held = add(self.start, eye(self.steps * self.process_var + self.extra)), self.held
        return self.kappa * math.sqrt(max(largest_eigenvalue(C), 0.0) + held)

    def level(self, P: Mat3, var: float = 0.0) -> float:
        """PL (m) = the noise term + bias (module docstring), P the current state covariance (3x3, m^2), `var`
        one measurement's largest variance per axis at the current range (m^2)."""
        return self.noise_term(P, var) + self.bias()
