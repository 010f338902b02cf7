"""The worst trusted error an attacker of a given capacity can cause without tripping a check (issue 40).

Setting (world axes, metres; the filter of pipeline/defense/kalman.py, the fused defense of
pipeline/defense/fusion.py). A white-box attacker knows one trajectory's clean run: every camera-frame
estimate t_j (so the pose network's noise realisation), the detector's probabilities, the camera
attitudes R_j (camera -> world), the commands, and hence every gain, innovation covariance and choice
the real filter makes. It adds to frame j's estimate a shift delta_j (world) = B_j a_j, B_j = [LOS,
cross1, cross2] (`fault_axes`: the true line of sight and two axes across it, world columns), within
the capacity box |a_{j,k}| <= F_{j,k} (m; pipeline/attacks/capacity.py gives F(eps, range)), from the
first frame on: the frames the protection level trusts (assumption A of protection.py) included.

Fixed structure. `record` runs the real defense over a run and notes, per frame, what the filter did
(`Recording`): before its start, start, accepted (plain or Huber-weighted update), rejected by the
gate, tested and alarmed by the sequential test, left out untested (the detector's doubt or flag), a
restart. With those choices fixed the filter is linear in the shifts (protection.py): the deviation
eps_j of the trusted error from the reference run's obeys
    eps_s = B_s da_s (the start takes frame s's measurement),
    eps_j = eps_{j-1} + K_j (B_j da_j - eps_{j-1}) on an accepted frame, eps_j = eps_{j-1} otherwise,
with K_j the gain the reference run used; the innovation is y_j = y_j^ref + B_j da_j - eps_{j-1}
(to first order in the range; below).
The checks, on that same structure (each a constraint on (da, eps), all from the first frame on):
- gate, on frames the reference accepted unweighted: NIS_j = y_j^T S_j^-1 y_j <= soft_gate x gate (the
  frame stays accepted and unweighted, so K_j stays the gain); on alarmed and untested checked frames:
  NIS_j <= gate; a second-order cone per frame, ||L_j^T y_j|| <= sqrt(bound) (L_j L_j^T = S_j^-1);
- Huber-weighted frames (the reference's NIS above the soft gate): y_j = y_j^ref (the weight, hence
  the gain, unchanged: the attacker gives up those frames, a restriction);
- gate-rejected frames: no shift, and the innovation keeps NIS >= gate through the half-space
  u0^T L_j^T y_j >= sqrt(gate) (u0 the direction of the reference's whitened innovation L_j^T y_j^ref),
  an inner approximation of the (non-convex) outside of the ellipsoid;
- the sequential test (pipeline/defense/sequential.py), exactly: on the normalized innovations r_{j,k}
  = c_{j,k}^T y_j / sigma_{j,k} the test actually pushes (noise plus shift: a white-box attacker uses
  the noise), statistics g+_{j,k} >= max(0, g+_{p,k} + r_{j,k} - c), g-_{j,k} >= max(0, g-_{p,k} -
  r_{j,k} - c), g <= h (p: the previous tested frame of the segment; such g exist iff Page's CUSUM
  stays <= h); on a frame where the reference alarmed, its alarming window keeps its sum above h
  (a half-space: the same alarm, the same restart of the test);
- the detector is blind: every frame keeps its clean probability (so its doubt and flags);
- restarts (`MotionFilter.reacquire`) are not modelled: a target frame after the reference's first
  restart is not solved (NaN).
Then the attacked run flags exactly the frames the reference flags: same modes, same hold, and the
same protection level (it depends on the gains alone).

The program, per target frame n and direction d: maximize d^T (e_n^ref + eps_n) over da, eps, g
subject to the above (frames <= n: a later check cannot undo an error already flown on), a
second-order cone program (one cone per gated frame), solved by Clarabel (an interior-point conic
solver; a program it stops on with a numerical error is solved again with its static regularization raised,
`RETRY_REGULARIZATION`; on a 200-frame toy run it took 0.06-0.3 s per program, 7 to 13 times less than HiGHS linear
programs refining an outer polytope of each ellipsoid by cutting planes, which need several solves
each). `worst_case` solves it for the six directions +-B_n[:, k] (the target frame's line of sight and
cross axes). Results:
- upper: sqrt(sum_k max(U_{+k}, U_{-k})^2), U_d the solver's dual bound on the max of d^T e_n: an upper
  bound of max |e_n| over the program's feasible set (its box in the target frame's axes; at most
  sqrt(3) times that max); where the replay needed re-solving (below), the larger of that bound around
  the clean run and around the final replay (both linearizations);
- lower: the attack: in the direction whose solution's |e_n| was largest, the same program with a
  relative `margin` (1%) of slack kept under every threshold (so that the replay passes where the real
  gains differ a little from the program's) solved again: its |e_n|, a feasible sequence's error, <= max;
- achieved: that sequence replayed through the real defense (`record`): its trusted error at n.
The noise model is taken at the predicted range, which the shifts move: the program keeps the first-order
effects of that range on the bias the model removes and on the sequential test's scales (`_range_terms`;
the eps_{j-1} terms above become J_j eps_{j-1}), not those on the gains and the gate's S_j, so the real
gains differ a little from the reference's; `worst_case` re-records the structure from the replay and
re-solves the best direction around it (the deviation form above, with the replay as reference) until
the replay reproduces the program's error within `tolerance` (`exact`), at most `iterations` times; a replay that
flags a frame the clean run did not flag is first shrunk toward the clean run (bisection on the real
defense) until it passes. The real chain's worst error can still exceed `upper` where the first-order
model misses (measured on the evaluation trajectories: benchmarks/integrity_bound.py).

What the result is: for the fixed structure, the exact maximum in each direction (to the solver's
tolerance) and [lower, upper] around the maximum of the norm; over every attack within F it is a lower
bound: an
attack that changes the filter's choices (accepts a frame the clean run rejected, alarms elsewhere,
triggers a restart), uses the Huber zone above the soft gate, or plays the detector is not searched.
The protection level (protection.py) is the analytic upper bound over structures; `achieved` above a
frame's PL is misleading information.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import clarabel
import numpy as np
from scipy import sparse

from pipeline.defense.calibration import CleanRun
from pipeline.defense.fusion import Defense, DefenseTrace, trace_of
from pipeline.defense.gate import MotionCheck, MotionSettings
from pipeline.defense.kalman import MotionFilter
from pipeline.defense.noise import NoiseModel
from pipeline.defense.settings import DefenseSettings
from pipeline.geometry.rotations import Mat3, sixd_to_matrix

NONE, START, ACCEPT, HUBER, REJECT, ALARM, SKIP, RESTART = range(8)
KINDS = ("none", "start", "accept", "huber", "reject", "alarm", "skip", "restart")
"""Per-frame choices of the filter (`Recording.kind`): before the start, start, accepted unweighted, accepted
Huber-weighted, rejected by the gate, alarmed by the sequential test, left out untested, restarted."""
_WIDTH = 12  # LP variables per frame: da (3), eps (3), g+ (3), g- (3)


class _Recorder(MotionFilter):
    """The real MotionFilter, noting per frame what it did (its methods run unchanged)."""

    def __init__(self, settings: MotionSettings, noise: NoiseModel, n: int):
        super().__init__(settings, noise)
        self.frame = -1
        self.kind = np.full(n, NONE)
        self.gain, self.s_inv, self.R_cam = np.zeros((n, 3, 3)), np.zeros((n, 3, 3)), np.zeros((n, 3, 3))
        self.innovation, self.sigma, self.r = np.zeros((n, 3)), np.ones((n, 3)), np.zeros((n, 3))
        self.nis = np.full(n, np.nan)
        self.statistic = np.zeros((n, 2, 3))  # CUSUM (g+, g-) after the frame's push, per camera axis
        self.ranged = np.zeros((n, 3))  # the vector (world, m) whose norm the noise model was taken at

    def start_from(self, t_pred: np.ndarray, R_cam: np.ndarray, R_pred: np.ndarray | None = None) -> None:
        self.R_cam[self.frame] = R_cam
        self.ranged[self.frame] = np.asarray(R_cam, np.float64) @ np.asarray(t_pred, np.float64)
        super().start_from(t_pred, R_cam, R_pred)

    def start(
        self,
        rel: np.ndarray,
        rel_cov: np.ndarray,
        R_tw: np.ndarray | None = None,
        offset: float = 0.0,
        trusted: int = 0,
    ) -> None:
        super().start(rel, rel_cov, R_tw, offset, trusted)
        self.kind[self.frame] = START if self.kind[self.frame] == NONE else RESTART  # reacquire checked it first

    def check(
        self, t_pred: np.ndarray, R_cam: np.ndarray, u: np.ndarray | None = None, R_pred: np.ndarray | None = None
    ) -> MotionCheck:
        out = super().check(t_pred, R_cam, u, R_pred)
        pending = self._pending[1]
        self.kind[self.frame] = REJECT if out.inconsistent else SKIP
        self.ranged[self.frame] = out.predicted
        if pending is not None:
            y, _, s_inv, _, r, sigma, R_cam = pending
            self.innovation[self.frame], self.s_inv[self.frame], self.r[self.frame] = y, s_inv, r
            self.sigma[self.frame], self.R_cam[self.frame], self.nis[self.frame] = sigma, R_cam, out.nis_position
        return out

    def test_sequence(self) -> bool:
        self.statistic[self.frame] = self.cusum.after(self._pending[1][4])
        alarm = super().test_sequence()
        if alarm:
            self.kind[self.frame] = ALARM
        return alarm

    def accept(self) -> None:
        huber = self._pending[0].nis_position > self.settings.soft_gate * self.gate
        super().accept()
        self.kind[self.frame] = HUBER if huber else ACCEPT

    def _bound(self, G: Mat3 | None, sigma: list[float]) -> None:
        if G is not None:
            self.gain[self.frame] = np.array(G) @ self.R_cam[self.frame].T
        super()._bound(G, sigma)


@dataclass(frozen=True, eq=False)
class Recording:
    """One run through the real defense and what its filter did, per frame (N frames): kind (N,) codes of
    `KINDS`; gain (N, 3, 3) the position gain K_j used (world, accepted frames; 0 elsewhere); s_inv (N, 3,
    3) S_j^-1 (1/m^2, checked frames); innovation (N, 3) y_j (world, m); sigma (N, 3) the sequential test's
    scales along the camera axes (m); r (N, 3) the normalized innovations it pushed; statistic (N, 2, 3) its
    (g+, g-) after the push; R_cam (N, 3, 3) camera -> world of the checked frames and the start; nis (N,)
    position NIS; ranged (N, 3) the vector (world, m) whose norm is the range the noise model was taken at
    (the predicted state on a checked frame, the estimate on the start frame); trace: the DefenseTrace."""

    kind: np.ndarray
    gain: np.ndarray
    s_inv: np.ndarray
    innovation: np.ndarray
    sigma: np.ndarray
    r: np.ndarray
    statistic: np.ndarray
    R_cam: np.ndarray
    nis: np.ndarray
    ranged: np.ndarray
    trace: DefenseTrace

    @property
    def start(self) -> int:
        """The frame the filter first started on (N when it never did)."""
        hit = np.flatnonzero(self.kind == START)
        return int(hit[0]) if hit.size else len(self.kind)

    @property
    def horizon(self) -> int:
        """The frames the program models: up to the first restart (N when none)."""
        hit = np.flatnonzero(self.kind == RESTART)
        return int(hit[0]) if hit.size else len(self.kind)


def record(
    settings: DefenseSettings,
    motion: MotionSettings,
    noise: NoiseModel,
    run: CleanRun,
    shift: np.ndarray | None = None,
    alert_limit: Callable[[float], float] | None = None,
) -> Recording:
    """`run` (pose (N, 9) camera frame m + 6-D, prob, R_cam, u) through a fresh real defense, each frame's
    estimate moved by `shift` (N, 3) (camera frame, m; None: clean), the detector's probabilities and the
    attitudes as recorded (a blind detector), `alert_limit` AL(range) for the availability; the trace
    and the filter's choices, gains and innovations (`Recording`)."""
    pose = np.asarray(run.pose, np.float64)
    n = len(pose)
    t = pose[:, :3] if shift is None else pose[:, :3] + np.asarray(shift, np.float64)
    if t.shape != (n, 3):
        raise ValueError(f"record: shift must be (N, 3) = ({n}, 3), got {np.shape(shift)}")
    R_pred = sixd_to_matrix(pose[:, 3:9])
    d = Defense(settings, motion, noise, alert_limit)
    rec = d.filter = _Recorder(motion, noise, n)
    out = []
    for i in range(n):
        rec.frame = i
        out.append(d.step(t[i], float(run.prob[i]), run.R_cam[i], run.u[i], R_pred[i]))
    return Recording(
        rec.kind,
        rec.gain,
        rec.s_inv,
        rec.innovation,
        rec.sigma,
        rec.r,
        rec.statistic,
        rec.R_cam,
        rec.nis,
        rec.ranged,
        trace_of(out),
    )


def fault_axes(truth: np.ndarray) -> np.ndarray:
    """(N, 3, 3) per frame the world-frame columns [line of sight, cross 1, cross 2] for the true rel (N, 3)
    (world, m; the target relative to the chaser): LOS = rel / |rel|, cross 1 = LOS x e / |.| with e the
    world axis least aligned with the LOS, cross 2 = LOS x cross 1 (a right-handed orthonormal basis)."""
    rel = np.asarray(truth, np.float64)
    if rel.ndim != 2 or rel.shape[1] != 3 or not np.isfinite(rel).all() or (np.linalg.norm(rel, axis=1) == 0).any():
        raise ValueError(f"fault_axes needs finite, non-zero (N, 3) positions, got shape {rel.shape}")
    los = rel / np.linalg.norm(rel, axis=1, keepdims=True)
    e = np.eye(3)[np.argmin(np.abs(los), axis=1)]
    c1 = np.cross(los, e)
    c1 /= np.linalg.norm(c1, axis=1, keepdims=True)
    return np.stack([los, c1, np.cross(los, c1)], axis=2)


def same_flags(a: DefenseTrace, b: DefenseTrace, upto: int) -> bool:
    """Whether two traces of one run flag the same frames by every check and fly the same modes on frames
    0..upto (what comes after cannot undo an error flown on at frame `upto`)."""
    return all(
        np.array_equal(getattr(a, k)[: upto + 1], getattr(b, k)[: upto + 1])
        for k in ("flag", "shap_flag", "motion_flag", "sequential_flag", "mode")
    )


def _range_terms(ref: Recording, noise: NoiseModel, step: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """First-order effects of the range r = |ranged_j| at which the noise model is taken, per frame (N, 3, 3):
    J: the model removes its bias b(r) (camera axes, m), so a state deviation eps moves a checked frame's
    innovation by -J_j eps, J_j = I + R_j b'(r) rhat^T, and a start frame's shift delta moves the start by
    J_s delta, J_s = I - R_s b'(r) rhat^T; G: the sequential test divides by sigma_k = sqrt(c_k^T (P + R_j
    diag(s(r)^2) R_j^T) c_k), so eps moves its normalized innovation r_k by -G_j[k] . eps more, G_j[k] =
    r_k s_k s'_k / sigma_k^2 rhat (s the model's std, camera axes, m). Derivatives by central differences of
    `step` m; rhat = ranged / r."""
    n = len(ref.kind)
    J, G = np.repeat(np.eye(3)[None], n, axis=0), np.zeros((n, 3, 3))
    for j in np.flatnonzero(np.isin(ref.kind, (START, ACCEPT, HUBER, REJECT, ALARM, SKIP))):
        r = float(np.linalg.norm(ref.ranged[j]))
        if r <= step:
            continue
        (b_hi, s_hi), (b_lo, s_lo) = noise.terms(r + step), noise.terms(r - step)
        rhat = ref.ranged[j] / r
        term = np.outer(ref.R_cam[j] @ ((np.array(b_hi) - np.array(b_lo)) / (2 * step)), rhat)
        J[j] = np.eye(3) - term if ref.kind[j] == START else np.eye(3) + term
        std, slope = np.array(noise.terms(r)[1]), (np.array(s_hi) - np.array(s_lo)) / (2 * step)
        G[j] = np.outer(ref.r[j] * std * slope / ref.sigma[j] ** 2, rhat)
    return J, G


class _Rows:
    """Constraint rows added in frame order (so a target frame's program is a prefix): row i is
    sum_c coef[c] x_c (+ s) = rhs, tagged with the frame it belongs to."""

    def __init__(self) -> None:
        self.tag: list[int] = []
        self.rhs: list[float] = []
        self.entries: tuple[list[int], list[int], list[float]] = ([], [], [])

    def add(self, frame: int, coef: dict[int, float], rhs: float) -> None:
        i = len(self.rhs)
        for c, v in coef.items():
            self.entries[0].append(i)
            self.entries[1].append(c)
            self.entries[2].append(v)
        self.tag.append(frame)
        self.rhs.append(float(rhs))

    def freeze(self, columns: int) -> None:
        """CSR matrix `A`, `b` and the prefix ends `ends` (rows of frames <= n: A[:ends[n]])."""
        i, c, v = self.entries
        self.A = sparse.csr_matrix((v, (i, c)), shape=(len(self.rhs), columns))
        self.b = np.array(self.rhs)
        self.ends = np.searchsorted(np.array(self.tag, int), np.arange(columns // _WIDTH), side="right")


class _Program:
    """The linear model and checks of one `Recording` (the reference) as the rows of a second-order cone
    program, frame-major so that the program of target frame n is a prefix (module docstring): equalities
    (`eqs`), inequalities coef x <= rhs (`rows`), and per checked frame the ellipsoid ||u_j|| <= sqrt(bound)
    of its whitened innovation u_j = L_j^T y_j (`cones`: 4 rows each, b - A x = (sqrt(bound), u_j)).
    `da_bounds` (N, 3, 2): bounds of the shift's deviation from the reference (capacity axes, m)."""

    def __init__(
        self,
        ref: Recording,
        axes: np.ndarray,
        da_bounds: np.ndarray,
        motion: MotionSettings,
        noise: NoiseModel,
        margin: float,
    ):
        self.ref, self.axes, self.n = ref, axes, len(ref.kind)
        self.J, self.G = _range_terms(ref, noise)
        gate, soft = motion.gate, motion.soft_gate * motion.gate
        c, h = motion.cusum_reference, motion.cusum_threshold
        n, kind = self.n, ref.kind
        lo, hi = np.zeros((n, _WIDTH)), np.zeros((n, _WIDTH))
        self.eqs, self.rows, self.cones = _Rows(), _Rows(), _Rows()
        prev: int | None = None  # last tested frame of the CUSUM segment
        started = False
        for j in range(min(ref.horizon, n)):
            k = kind[j]
            if k == NONE or (k != START and not started):
                continue
            lo[j, 3:6], hi[j, 3:6] = -np.inf, np.inf
            if k in (START, ACCEPT, HUBER, ALARM):
                lo[j, :3], hi[j, :3] = da_bounds[j, :, 0], da_bounds[j, :, 1]
            if k == START:  # eps_s = J_s B_s da_s
                started, prev = True, None
                self._start(j)
                continue
            self._update(j, k)
            if not np.isfinite(ref.nis[j]):
                continue
            self._gate(j, k, gate, soft, margin)
            if k in (ACCEPT, HUBER):  # tested, no alarm: g <= h
                self._no_alarm(j, prev, c, h, margin, hi[j])
                prev = j
            elif k == ALARM:
                self._alarm(j, prev, c, h, margin)
                prev = None
        self.lo, self.hi = lo.ravel(), hi.ravel()
        for rows in (self.eqs, self.rows, self.cones):
            rows.freeze(_WIDTH * n)

    def _start(self, j: int) -> None:
        """The start frame j: eps_j = J_j B_j da_j (world, m)."""
        JB = self.J[j] @ self.axes[j]
        for i in range(3):
            self.eqs.add(j, {self.col(j, 3 + i): 1.0, **{self.col(j, m): -JB[i, m] for m in range(3)}}, 0.0)

    def _update(self, j: int, k: int) -> None:
        """Frame j after the start: eps_j - (I - K J) eps_{j-1} - K B da_j = 0, K the reference's gain on an
        accepted frame, 0 otherwise (world, m)."""
        K = self.ref.gain[j] if k in (ACCEPT, HUBER) else np.zeros((3, 3))
        KB, KJ = K @ self.axes[j], K @ self.J[j]
        for i in range(3):
            row = {self.col(j, 3 + i): 1.0}
            for m in range(3):
                row[self.col(j - 1, 3 + m)] = KJ[i, m] - (i == m)
                row[self.col(j, m)] = -KB[i, m]
            self.eqs.add(j, row, 0.0)

    def _gate(self, j: int, k: int, gate: float, soft: float, margin: float) -> None:
        """The gate's constraint on the checked frame j's whitened innovation u_j = L_j^T y_j: y_j = y_j^ref
        (Huber-weighted), outside the gate by a half-space (rejected), or inside the (soft) gate's ball."""
        ref = self.ref
        L = np.linalg.cholesky(0.5 * (ref.s_inv[j] + ref.s_inv[j].T))
        u_ref = L.T @ ref.innovation[j]
        if k == HUBER:  # y_j = y_j^ref
            for i in range(3):
                self.eqs.add(j, self._dy({}, j, np.eye(3)[i]), 0.0)
        elif k == REJECT:  # u0^T L^T y_j >= sqrt(gate)
            u0 = u_ref / np.linalg.norm(u_ref)
            need = min(math.sqrt(gate * (1 + margin)), float(np.linalg.norm(u_ref)))
            self.rows.add(j, self._dy({}, j, -(L @ u0)), float(u0 @ u_ref) - need)
        else:  # ACCEPT, ALARM, SKIP: ||u_j|| <= sqrt(bound)
            bound = soft if k == ACCEPT else gate
            self.cones.add(j, {}, math.sqrt(max(bound * (1 - margin), float(u_ref @ u_ref))))
            for i in range(3):
                self.cones.add(j, self._dy({}, j, -L[:, i]), u_ref[i])

    def _no_alarm(self, j: int, prev: int | None, c: float, h: float, margin: float, hi: np.ndarray) -> None:
        """The tested frame j raises no alarm: g+-_{j,k} >= g+-_{prev,k} +- r_{j,k} - c and g <= h, its upper
        bounds set in `hi` (_WIDTH,), frame j's row of the variables' upper bounds."""
        for side, sgn in ((0, 1.0), (1, -1.0)):
            for i in range(3):
                g = self.col(j, 6 + 3 * side + i)
                row = {g: -1.0} if prev is None else {g: -1.0, self.col(prev, 6 + 3 * side + i): 1.0}
                self.rows.add(j, self._dr(row, j, i, sgn), c - sgn * self.ref.r[j, i])
                hi[6 + 3 * side + i] = max(h * (1 - margin), self.ref.statistic[j, side, i])

    @staticmethod
    def col(j: int, i: int) -> int:
        return _WIDTH * j + i

    def _dy(self, row: dict[int, float], j: int, w: np.ndarray) -> dict[int, float]:
        """row + w^T dy_j with dy_j = B_j da_j - J_j eps_{j-1} (the innovation's deviation, world, m)."""
        wb, wj = w @ self.axes[j], w @ self.J[j]
        for m in range(3):
            row[self.col(j, m)] = row.get(self.col(j, m), 0.0) + wb[m]
            row[self.col(j - 1, 3 + m)] = row.get(self.col(j - 1, 3 + m), 0.0) - wj[m]
        return row

    def _dr(self, row: dict[int, float], j: int, axis: int, sgn: float) -> dict[int, float]:
        """row + sgn dr_{j,axis}, the deviation of the normalized innovation the sequential test pushes:
        dr = c_k^T dy_j / sigma_k - G_j[k] . eps_{j-1} (`_range_terms`)."""
        self._dy(row, j, sgn * self.ref.R_cam[j][:, axis] / self.ref.sigma[j, axis])
        for m in range(3):
            row[self.col(j - 1, 3 + m)] = row.get(self.col(j - 1, 3 + m), 0.0) - sgn * self.G[j, axis, m]
        return row

    def _alarm(self, j: int, prev: int | None, c: float, h: float, margin: float) -> None:
        """The reference's alarm at frame j stays: its largest statistic's window (from the frame after the
        segment's last zero of that statistic) keeps sum (s r - c) >= h."""
        ref = self.ref
        side, axis = np.unravel_index(int(np.argmax(ref.statistic[j])), (2, 3))
        sgn = 1.0 if side == 0 else -1.0
        frames, p = [j], prev
        while p is not None and ref.statistic[p, side, axis] > 0:  # back through the segment's tested frames
            frames.append(p)
            p -= 1
            while p >= 0 and ref.kind[p] in (REJECT, SKIP):
                p -= 1
            p = p if p >= 0 and ref.kind[p] in (ACCEPT, HUBER) else None
        total = sum(sgn * ref.r[q, axis] - c for q in frames)
        row: dict[int, float] = {}
        for q in frames:
            self._dr(row, q, axis, -sgn)
        self.rows.add(j, row, total - min(h * (1 + margin), total))

    def maximize(self, n: int, directions: Sequence[np.ndarray]) -> list[tuple[float, np.ndarray, np.ndarray]]:
        """Per direction d (3,) (world): (upper, eps_n, da) of max d^T eps_n over the frames <= n: the solver's
        dual bound on it (m), and its primal point's eps_n (3,) (world, m) and shift deviations da (N, 3)
        (capacity axes, m; zero after n). One program, its objective updated per direction."""
        m = _WIDTH * (n + 1)
        lo, hi = self.lo[:m], self.hi[:m]
        free = lo < hi
        blocks = [(r.A[: r.ends[n], :m], r.b[: r.ends[n]]) for r in (self.eqs, self.rows)]
        upper, lower = free & np.isfinite(hi), free & np.isfinite(lo)
        eye = sparse.identity(m, format="csr")
        blocks.append((sparse.vstack([eye[upper], -eye[lower]]), np.r_[hi[upper], -lo[lower]]))
        blocks.append((self.cones.A[: self.cones.ends[n], :m], self.cones.b[: self.cones.ends[n]]))
        A = sparse.vstack([a for a, _ in blocks], format="csc")
        b = np.concatenate([v for _, v in blocks]) - A[:, ~free] @ lo[~free]
        cones = [
            clarabel.ZeroConeT(blocks[0][0].shape[0]),
            clarabel.NonnegativeConeT(blocks[1][0].shape[0] + blocks[2][0].shape[0]),
        ]
        cones += [clarabel.SecondOrderConeT(4)] * (blocks[3][0].shape[0] // 4)
        A = A[:, free]
        P = sparse.csc_matrix((A.shape[1], A.shape[1]))
        solver, out = None, []
        for d in directions:
            q = np.zeros(m)
            q[self.col(n, 3) : self.col(n, 6)] = -np.asarray(d, np.float64)
            if solver is None:
                solver = clarabel.DefaultSolver(P, q[free], A, b, cones, _settings(None))
            else:
                solver.update(q=q[free])
            sol = solver.solve()
            for regularization in RETRY_REGULARIZATION:
                if sol.status in SOLVED:
                    break
                sol = clarabel.DefaultSolver(P, q[free], A, b, cones, _settings(regularization)).solve()
            if sol.status not in SOLVED:
                raise RuntimeError(f"worst-case program of frame {n}: {sol.status}")
            x = lo.copy()
            x[free] = sol.x
            da = np.zeros((self.n, 3))
            da[: n + 1] = x.reshape(n + 1, _WIDTH)[:, :3]
            out.append((max(-sol.obj_val, -sol.obj_val_dual), x[self.col(n, 3) : self.col(n, 6)], da))
        return out


SOLVED = (clarabel.SolverStatus.Solved, clarabel.SolverStatus.AlmostSolved)
# Clarabel's static regularization (its default 1e-8) raised, in turn, for a program it stops on with a numerical
# error: met on the standard chain's programs (capacities of tens of metres beside centimetre-level noise), where
# 1e-7 solved every direction to the objective the stalled run had reached.
RETRY_REGULARIZATION = (1e-7, 1e-6)


def _settings(regularization: float | None) -> Any:
    """Clarabel's default settings, quiet, with `regularization` as the static regularization constant (None:
    the default)."""
    settings = clarabel.DefaultSettings()
    settings.verbose = False
    if regularization is not None:
        settings.static_regularization_constant = regularization
    return settings


def _box_bound(program: _Program, j: int, e_ref: np.ndarray, axes: np.ndarray) -> tuple[float, np.ndarray]:
    """(sqrt(sum_k max(U_{+k}, U_{-k})^2) (m), the direction among the six whose solution has the largest
    |e_j|): U_d the dual bound on max d^T e_j over `program` for d = +-axes[:, k], e_j = e_ref + eps_j."""
    directions = [sgn * axes[:, k] for k in range(3) for sgn in (1.0, -1.0)]
    bounds, best = [], (-1.0, directions[0])
    for d, (upper, eps, _) in zip(directions, program.maximize(j, directions)):
        bounds.append(max(upper + float(d @ e_ref), 0.0))
        if np.linalg.norm(e_ref + eps) > best[0]:
            best = (float(np.linalg.norm(e_ref + eps)), d)
    return math.sqrt(sum(max(bounds[2 * k], bounds[2 * k + 1]) ** 2 for k in range(3))), best[1]


@dataclass(frozen=True, eq=False)
class WorstCase:
    """`worst_case` over T target frames of one run: targets (T,) frame indices; upper, lower, achieved (T,)
    trusted error (m): the program's upper bound, a feasible sequence's error, that sequence's error in the
    real defense (module docstring); alert (T,) AL (m); pl (T,) the replay's protection level (m); available
    (T,) the replay's availability; exact (T,) the replay reproduced the program within the tolerance;
    iterations (T,) programs solved around a replay; shift (T, N, 3) the worst sequence per target, camera
    frame (m: what the pose network must be made to output, added to its clean estimate), which passes every
    check on the frames up to its target (the clean run's flags and modes; shrunk toward the clean run where
    a replay did not); seconds: wall time of the whole call."""

    targets: np.ndarray
    upper: np.ndarray
    lower: np.ndarray
    achieved: np.ndarray
    alert: np.ndarray
    pl: np.ndarray
    available: np.ndarray
    exact: np.ndarray
    iterations: np.ndarray
    shift: np.ndarray
    seconds: float

    @property
    def ratio(self) -> np.ndarray:
        """(T,) upper / AL: the bound's safety index against the alert limit."""
        return self.upper / self.alert

    @property
    def pl_index(self) -> np.ndarray:
        """(T,) achieved / PL: above 1, the protection level missed a real attack (misleading information)."""
        return self.achieved / self.pl


def worst_case(
    settings: DefenseSettings,
    motion: MotionSettings,
    noise: NoiseModel,
    run: CleanRun,
    truth: np.ndarray,
    capacity: np.ndarray,
    alert: np.ndarray,
    targets: Sequence[int] | None = None,
    tolerance: float = 1e-4,
    iterations: int = 5,
    margin: float = 0.01,
    alert_limit: Callable[[float], float] | None = None,
) -> WorstCase:
    """The worst trusted error at each target frame over shift sequences within `capacity` that pass every
    check of the defense (module docstring: the program, what it assumes, exact vs bound).

    run: the clean run (pose (N, 9) camera frame m + 6-D, prob (N,), R_cam (N, 3, 3) camera -> world, u
    (N, 3) commands, world m); truth (N, 3) the true rel (world, m); capacity (N, 3) the box half-widths F
    per frame along [line of sight, cross 1, cross 2] (`fault_axes`, m); alert (N,) AL per frame (m);
    targets: frame indices (default every frame); tolerance (m): the replay's agreement with the program;
    iterations: re-solves around a replay; margin: relative slack the attack keeps under every threshold
    (gate, CUSUM; not the upper bound's program) so that its replay passes where the real gains differ a
    little from the program's; alert_limit: AL(range) for the replay's availability (the defense's own,
    optional)."""
    start_time = time.perf_counter()
    truth, capacity, alert, targets = _checked(run, truth, capacity, alert, targets)
    n = len(run.pose)
    axes = fault_axes(truth)
    box = np.stack([-capacity, capacity], axis=2)
    clean = record(settings, motion, noise, run, alert_limit=alert_limit)
    program, attack = (_Program(clean, axes, box, motion, noise, m) for m in (0.0, margin))
    search = _Search(settings, motion, noise, run, truth, axes, box, clean, alert_limit, margin, tolerance, iterations)
    T = len(targets)
    out = {k: np.full(T, np.nan) for k in ("upper", "lower", "achieved", "pl")}
    flags = {k: np.zeros(T, bool) for k in ("available", "exact")}
    its, shift = np.zeros(T, int), np.zeros((T, n, 3))
    for t, j in enumerate(targets):
        if j < clean.start or j >= clean.horizon:
            continue
        upper, lower, achieved, rec, a, it = search.target(j, program, attack)
        out["upper"][t], out["lower"][t] = upper, lower
        out["achieved"][t], out["pl"][t] = achieved, rec.trace.pl[j]
        flags["available"][t] = bool(rec.trace.available[j])
        flags["exact"][t] = abs(achieved - out["lower"][t]) <= tolerance
        its[t], shift[t, : j + 1] = it, search.camera(a)
    return WorstCase(
        targets,
        out["upper"],
        out["lower"],
        out["achieved"],
        alert[targets],
        out["pl"],
        flags["available"],
        flags["exact"],
        its,
        shift,
        time.perf_counter() - start_time,
    )


def _checked(
    run: CleanRun, truth: np.ndarray, capacity: np.ndarray, alert: np.ndarray, targets: Sequence[int] | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`worst_case`'s truth (N, 3) (world, m), capacity (N, 3) (m), alert (N,) (m) as float64 arrays and its
    target frames (default every frame), or a ValueError naming what is wrong."""
    truth = np.asarray(truth, np.float64)
    n = len(run.pose)
    capacity, alert = np.asarray(capacity, np.float64), np.asarray(alert, np.float64)
    if truth.shape != (n, 3) or capacity.shape != (n, 3) or alert.shape != (n,):
        raise ValueError(
            f"worst_case needs truth (N, 3), capacity (N, 3), alert (N,) for N = {n} frames, got "
            f"{truth.shape}, {capacity.shape}, {alert.shape}"
        )
    if not (np.isfinite(capacity).all() and (capacity >= 0).all()):
        raise ValueError("worst_case: capacity must be finite and >= 0 (m)")
    targets = np.arange(n) if targets is None else np.asarray(targets, int)
    if targets.size and (targets.min() < 0 or targets.max() >= n):
        raise ValueError(f"worst_case: target frames must lie in [0, {n}), got {targets.min()}..{targets.max()}")
    return truth, capacity, alert, targets


@dataclass(frozen=True, eq=False)
class _Search:
    """What `worst_case` searches with around one clean run (its arguments): truth (N, 3) the true rel (world,
    m), axes (N, 3, 3) `fault_axes`, box (N, 3, 2) the capacity box (capacity axes, m), clean the clean run's
    `Recording`."""

    settings: DefenseSettings
    motion: MotionSettings
    noise: NoiseModel
    run: CleanRun
    truth: np.ndarray
    axes: np.ndarray
    box: np.ndarray
    clean: Recording
    alert_limit: Callable[[float], float] | None
    margin: float
    tolerance: float
    iterations: int

    def camera(self, a: np.ndarray) -> np.ndarray:
        """Shifts a (m, 3) of the first m frames (capacity axes) in the camera frame."""
        return np.einsum("nji,njk,nk->ni", self.run.R_cam[: len(a)], self.axes[: len(a)], a)

    def replay(self, a: np.ndarray) -> Recording:
        """The first len(a) frames through the real defense, shifted by a (capacity axes)."""
        m, run = len(a), self.run
        return record(
            self.settings,
            self.motion,
            self.noise,
            CleanRun(run.pose[:m], run.prob[:m], run.R_cam[:m], run.u[:m]),
            self.camera(a),
            self.alert_limit,
        )

    def target(
        self, j: int, program: _Program, attack: _Program
    ) -> tuple[float, float, float, Recording, np.ndarray, int]:
        """(upper, lower, achieved (m): module docstring; the final replay, its shifts a (j + 1, 3) (capacity
        axes, m), the programs solved around a replay) at target frame j."""
        e_ref = self.clean.trace.trusted[j] - self.truth[j]
        upper, d = _box_bound(program, j, e_ref, self.axes[j])
        _, eps, da = attack.maximize(j, [d])[0]  # the attack: that direction, with the margin
        lower, a = float(np.linalg.norm(e_ref + eps)), da[: j + 1]  # frames after j: not replayed
        rec, a, lower, achieved, it = self._refine(j, d, a, lower)
        if it:  # the bound around the final replay's gains too
            final = _Program(rec, self.axes[: j + 1], self.box[: j + 1] - a[:, :, None], self.motion, self.noise, 0.0)
            upper = max(upper, _box_bound(final, j, rec.trace.trusted[j] - self.truth[j], self.axes[j])[0])
        return upper, lower, achieved, rec, a, it

    def _refine(
        self, j: int, d: np.ndarray, a: np.ndarray, lower: float
    ) -> tuple[Recording, np.ndarray, float, float, int]:
        """Replay the shifts a (j + 1, 3) (capacity axes, m), shrunk until they pass, and re-solve direction d
        around the replay until it reproduces the program's error `lower` (m) within the tolerance, at most
        `iterations` times: (the final replay, its shifts, lower, its achieved error (m), re-solves)."""
        rec, it = self.replay(a), 0
        while True:
            if not same_flags(rec.trace, self.clean.trace, j):  # shrink toward the clean run until it passes
                a = self._shrink(j, a)
                rec = self.replay(a)
            achieved = float(np.linalg.norm(rec.trace.trusted[j] - self.truth[j]))
            if abs(achieved - lower) <= self.tolerance or it == self.iterations or rec.horizon <= j:
                break
            it += 1  # re-solve around the replay (its own gains)
            box = self.box[: j + 1] - a[:, :, None]
            around = _Program(rec, self.axes[: j + 1], box, self.motion, self.noise, self.margin)
            _, eps, da = around.maximize(j, [d])[0]
            lower = float(np.linalg.norm(rec.trace.trusted[j] - self.truth[j] + eps))
            a = a + da
            rec = self.replay(a)
        return rec, a, lower, achieved, it

    def _shrink(self, j: int, a: np.ndarray) -> np.ndarray:
        """The shifts a scaled toward the clean run by bisection (8 halvings) to the largest tried factor whose
        replay flags the clean run's frames up to j."""
        lo, hi = 0.0, 1.0
        for _ in range(8):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if same_flags(self.replay(mid * a).trace, self.clean.trace, j) else (lo, mid)
        return lo * a
