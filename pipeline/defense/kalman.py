"""Motion-consistency check of the pose estimates: a relative-motion Kalman filter, its gate and its
sequential test.

Frames (those of pipeline/geometry/trajectories.py). The filter works in the target-centred world frame:
`rel` is the target position relative to the chaser camera in world axes (metres). The chaser knows
its own camera attitude R_c (camera -> world) and the displacement of `rel` it commanded since the
previous frame (`u`, world axes, metres), so a camera-frame estimate t_pred becomes the world
measurement z = R_c t_pred, and the position state is rel alone: rel_k = rel_{k-1} + u_k + w_k, w_k
the command's execution error (std hypot(position_noise, position_noise_scale |u_k|) per axis: the filter
knows the command, so it knows the step's size; the truth's execution error, which the filter is never
told, is pipeline/guidance/dynamics.py's: set the two to its noise_std and scale_std, or position_noise
near zero where the commands are executed exactly). There is no free drift-velocity state: a chaser commands its own relative
motion, and a velocity state would let a slowly growing bias (a drift attack) be absorbed as motion
(Mo and Sinopoli 2010). The target attitude R_tw (target -> world, measured as R_c R_pred) follows a
rate model (the target's tumble is not commanded): error state [rotation vector (3, rad), rate (3,
rad per frame)] about the current attitude estimate, target frame.

Measurement noise: pipeline/defense/noise.py (`NoiseModel`, rotated into world axes with R_c every
frame). The gate and the filter's settings: pipeline/defense/gate.py (`MotionSettings`, `MotionCheck`);
the sequential test on the innovations: pipeline/defense/sequential.py; the protection level:
pipeline/defense/protection.py.

`MotionFilter.check` applies the gate; flagged frames coast (fault exclusion); frames that pass it
go to the sequential test (`test_sequence`) and, unless it alarms, update the filter with a Huber
weight; `reacquire` restarts a filter that was dragged away (see gate.py); `protection_level` is the
bound on the state's error.

Implementation: a short Kalman filter of our own (predict, innovation, Joseph-form update) rather
than filterpy: filterpy 2.0.0 is not among our dependencies, its KalmanFilter has no error-state
(rotation) update and no per-frame measurement covariance beyond passing R, and the few matrix
products here are tested directly (tests/test_motion.py). It runs once per camera frame right after
the pose network, whose convolutions leave the caches cold: there a small numpy call costs 5-10 us
(~1 us warm), so the per-frame path is plain floats on 3x3 nested lists, the attitude filter as three
equal scalar filters (its covariances are multiples of I3 per block: isotropic noise), closed-form
3x3 inverses reused between the gate and the update.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Sequence

import numpy as np
from scipy.stats import chi2

from pipeline.defense.gate import MotionCheck, MotionSettings
from pipeline.defense.linear import IsoKalman6, Kalman3, add, eye, mm, mm_t, mv, transpose
from pipeline.defense.noise import NoiseModel
from pipeline.defense.protection import ProtectionLevel, largest_eigenvalue
from pipeline.defense.sequential import Cusum
from pipeline.geometry.rotations import Mat3, float_lists, rotmat_list, rotvec_list


def _camera_normalized(y: Sequence[float], S: Mat3, R_cam: Mat3) -> tuple[list[float], list[float]]:
    """(r, sigma): the innovation y (world, m) along the camera axes (columns of R_cam, camera ->
    world) divided by its standard deviations there, sigma_k = sqrt(c_k^T S c_k) (m). The noise model
    is diagonal in the camera frame, so these are the axes the sequential test and the protection
    level's fault bound work in (pipeline/defense/protection.py)."""
    sigma, r = [], []
    for k in range(3):
        c = [R_cam[0][k], R_cam[1][k], R_cam[2][k]]
        sd = math.sqrt(sum(c[i] * sum(S[i][j] * c[j] for j in range(3)) for i in range(3)))
        sigma.append(sd)
        r.append((c[0] * y[0] + c[1] * y[1] + c[2] * y[2]) / sd)
    return r, sigma


class MotionFilter:
    """Relative-motion filter with a chi-square innovation gate and a sequential test; call `check`,
    then for a frame that passed the gate (and the caller's other checks) `test_sequence`, then
    `accept` or `coast`, once per frame. The per-frame path works on floats and 3x3 nested lists;
    `position`, `attitude` and the checks' `predicted` are numpy arrays."""

    def __init__(self, settings: MotionSettings, noise: NoiseModel):
        self.settings = settings
        self.noise = noise
        self.gate = settings.gate
        self.pos = Kalman3(settings.position_noise)
        self.att = IsoKalman6(math.radians(settings.attitude_noise_deg), math.radians(settings.attitude_rate_noise_deg))
        self.cusum = Cusum(settings.cusum_reference, settings.cusum_threshold)
        self.protection = ProtectionLevel(
            settings.cusum_reference,
            settings.cusum_threshold,
            settings.integrity_risk,
            settings.position_noise,
            settings.correlated_error,
        )
        self.R_tw = eye()  # attitude estimate (target -> world), 3x3 nested list
        self.started = False
        self._pending: tuple[MotionCheck, tuple | None] | None = None  # last check, its update terms
        self._tested = False  # the pending frame went through the sequential test
        self._trusted = 0  # frames after the start the protection level assumes fault-free
        self._doubted = False  # the detector flagged a frame of the run: assumption A is in doubt
        self._moved = [0.0] * 3  # sum of the commanded displacements so far (world, m)
        self._var: float | None = None  # the last step's process noise per axis (m^2; None: position_noise^2)
        self._candidates: list[tuple[list[float], Mat3, Mat3 | None]] = []
        self._history: deque[list[float]] = deque(maxlen=2 * settings.reacquire_after)
        self._last: tuple[list[float], Mat3, Mat3 | None] | None = None
        df = 3 * (settings.reacquire_after - 1)
        self._agree = float(chi2.ppf(1.0 - settings.false_alarm, df))

    @property
    def position(self) -> np.ndarray:
        """Current estimate of rel (world frame, m)."""
        return np.array(self.pos.level)

    @property
    def attitude(self) -> np.ndarray:
        """Current estimate of the target attitude (target -> world rotation)."""
        return np.array(self.R_tw)

    @property
    def predicted_range(self) -> float:
        """|rel| of the current state (m): the range the noise model is taken at."""
        a = self.pos.level
        return math.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])

    @property
    def protection_level(self) -> float:
        """PL (m) of the current state (pipeline/defense/protection.py); inf before the start, and inf on the
        trusted frames once `doubt_start` was called (assumption A in doubt: no bound until the anchor)."""
        if not self.started or (self._trusted > 0 and self._doubted):
            return math.inf
        return self.protection.level(self.pos.A, self.measurement_variance)

    @property
    def measurement_variance(self) -> float:
        """One measurement's largest variance per camera axis at the state's range (m^2): what the protection
        level holds a share of (`MotionSettings.correlated_error`, assumption C of pipeline/defense/protection.py)."""
        return max(self.noise.terms(self.predicted_range)[1]) ** 2

    @property
    def pl_noise_term(self) -> float:
        """The protection level's noise term (m) of the current state (pipeline/defense/protection.py)."""
        return self.protection.noise_term(self.pos.A, self.measurement_variance)

    def start(
        self,
        rel: np.ndarray,
        rel_cov: np.ndarray,
        R_tw: np.ndarray | None = None,
        offset: float = 0.0,
        trusted: int = 0,
    ) -> None:
        """Start (or restart) at rel (world, m) with covariance rel_cov (3, 3, m^2), optionally an
        attitude; `offset` (m): the bias bound the new run carries, `trusted`: the frames after the
        start that the protection level assumes fault-free (see protection.py, assumption A)."""
        rel = np.asarray(rel, np.float64)
        self.pos.reset(rel.tolist(), np.asarray(rel_cov, np.float64).tolist())
        att_std = self.noise.attitude_std(float(np.linalg.norm(rel)))
        self.att.reset(att_std**2, 3 * math.radians(self.settings.attitude_rate_noise_deg))
        self.R_tw = eye() if R_tw is None else np.asarray(R_tw, np.float64).tolist()
        self.started = True
        self.cusum.reset()
        self.protection.reset(offset)
        self._trusted = int(trusted)
        if self._trusted == 0:
            self.protection.anchor(self.pos.A, self.measurement_variance)
        self._candidates = []
        self._history.clear()
        self._history.append([p - m for p, m in zip(self.pos.level, self._moved)])

    def doubt_start(self) -> None:
        """The detector flagged a frame of this run. Assumption A (pipeline/defense/protection.py: no fault on
        the first start and the trusted frames after it, the detector alone guards them) then rests on a guard
        that has seen an attack or erred, so the protection level claims no bound (inf) on the trusted frames
        until the anchor; from the anchor on, and after a restart (which trusts no frame), it is unchanged."""
        self._doubted = True

    def measurement(
        self, t_pred: np.ndarray, R_cam: np.ndarray, rng: float | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """(z world-frame measurement of rel (m), its covariance (3, 3)) from a camera-frame estimate,
        the noise model's bias removed; the noise model at range `rng` (m; default |t_pred|: `check`
        takes the predicted state's range, which a single estimate cannot move)."""
        t = np.asarray(t_pred, np.float64).tolist()
        rng = math.sqrt(t[0] * t[0] + t[1] * t[1] + t[2] * t[2]) if rng is None else float(rng)
        z, Rz = self._measurement(t, rng, np.asarray(R_cam, np.float64).tolist())
        return np.array(z), np.array(Rz)

    def _measurement(self, t: list[float], rng: float, R_cam: Mat3) -> tuple[list[float], Mat3]:
        """`measurement` from the estimate as floats, its range (m) and R_cam as nested lists."""
        bias, std = self.noise.terms(rng)
        z = mv(R_cam, [t[i] - bias[i] for i in range(3)])
        var = [v * v for v in std]
        return z, mm_t([[r * v for r, v in zip(row, var)] for row in R_cam], R_cam)

    def start_from(self, t_pred: np.ndarray, R_cam: np.ndarray, R_pred: np.ndarray | None = None) -> None:
        """Start from one trusted estimate (camera frame) with the noise model's covariance."""
        R_cam = np.asarray(R_cam, np.float64)
        z, Rz = self.measurement(t_pred, R_cam)
        self.start(z, Rz, None if R_pred is None else R_cam @ R_pred, trusted=self.settings.trusted_start)

    def check(
        self, t_pred: np.ndarray, R_cam: np.ndarray, u: np.ndarray | None = None, R_pred: np.ndarray | None = None
    ) -> MotionCheck:
        """Predict with the commanded displacement u (world, m) and test the estimate (t_pred camera
        frame, m; R_pred target -> camera, optional) against the prediction."""
        if not self.started:
            raise RuntimeError("MotionFilter.check before start")
        if u is not None:
            u = float_lists(u)
            self._moved = [m + d for m, d in zip(self._moved, u)]
        self._tested = False
        var = self._step_variance(u)
        self.pos.predict(u, var)
        self.protection.step(var)
        self.att.predict()
        self.R_tw = mm(self.R_tw, rotmat_list(self.att.take_level()))
        predicted = self.position
        t = float_lists(t_pred)
        rng = math.sqrt(t[0] * t[0] + t[1] * t[1] + t[2] * t[2])
        R_pred = None if R_pred is None else float_lists(R_pred)
        if not math.isfinite(rng) or (R_pred is not None and not math.isfinite(sum(map(sum, R_pred)))):
            return self._stash(MotionCheck(np.inf, np.inf, True, predicted), None)
        R_cam = float_lists(R_cam)
        rng = self.predicted_range
        z, Rz = self._measurement(t, rng, R_cam)
        R_meas = None if R_pred is None else mm(R_cam, R_pred)
        self._last = ([v - m for v, m in zip(z, self._moved)], Rz, R_meas)
        y = [v - p for v, p in zip(z, self.pos.level)]
        s_inv = self.pos.innovation_inverse(Rz)
        nis_p = sum(a * b for a, b in zip(y, mv(s_inv, y)))
        r, sigma = _camera_normalized(y, add(self.pos.A, Rz), R_cam)
        nis_a, att = np.nan, None
        if R_meas is not None:
            dth = rotvec_list(mm(transpose(self.R_tw), R_meas))
            var = self.noise.attitude_std(rng) ** 2
            nis_a = self.att.nis(dth, var)
            att = (dth, var)
        bad = nis_p > self.gate or (not math.isnan(nis_a) and nis_a > self.gate)
        return self._stash(MotionCheck(nis_p, nis_a, bool(bad), predicted), (y, Rz, s_inv, att, r, sigma, R_cam))

    def _step_variance(self, u: list[float] | None) -> float | None:
        """The process noise per axis (m^2) of the step u (None: the filter's own, position_noise^2); the last
        one is kept for `reacquire`."""
        if u is None or self.settings.position_noise_scale == 0:
            self._var = None
        else:
            self._var = self.settings.step_variance(math.sqrt(u[0] * u[0] + u[1] * u[1] + u[2] * u[2]))
        return self._var

    def _stash(self, check: MotionCheck, pending: tuple | None) -> MotionCheck:
        self._pending = (check, pending)
        return check

    def test_sequence(self) -> bool:
        """Push the last checked (finite) frame's normalized innovations into the sequential test;
        returns whether it alarms (the caller then coasts the frame). An alarm restarts the test: the
        frame is left out of the state, and the protection level's fault bound starts a new segment
        (pipeline/defense/protection.py), so a clean false alarm costs one frame, while a drift that
        keeps alarming pays for each new segment in its PL."""
        if self._pending is None or self._pending[1] is None:
            raise RuntimeError("MotionFilter.test_sequence needs a checked, finite frame")
        self._tested = True
        if not self.cusum.push(self._pending[1][4]):
            return False
        self.cusum.reset()  # a new segment of the test (and of the PL's fault bound) starts
        self.protection.add(None, self._pending[1][5])
        self._tested = False
        return True

    def accept(self) -> None:
        """Update the filter with the last checked frame (Huber-weighted above the soft gate); its
        gain joins the protection level's sums."""
        if self._pending is None or self._pending[1] is None:
            raise RuntimeError("MotionFilter.accept needs a checked, finite frame")
        check, (y, Rz, s_inv, att, _, sigma, R_cam) = self._pending  # type: ignore[misc]
        soft = self.settings.soft_gate * self.gate
        if check.nis_position > soft:  # Huber: the inflated covariance has its own S
            K = self.pos.update(y, [[v * (check.nis_position / soft) for v in row] for row in Rz])
        else:
            K = self.pos.update(y, Rz, s_inv)
        self._bound(mm(K, R_cam), sigma)
        if att is not None:
            dth, var = att
            self.att.update(dth, var * max(1.0, check.nis_attitude / soft))
            self.R_tw = mm(self.R_tw, rotmat_list(self.att.take_level()))
        self._pending = None
        self._history.append(self._last[0])
        self._candidates = []

    def coast(self, candidate: bool = False) -> None:
        """Leave the last checked frame out: the state stays at the prediction. With `candidate`
        (the gate or the sequential test rejected it but nothing else suspects it) the frame may
        restart the filter: see `reacquire`."""
        if self._tested and self._pending is not None and self._pending[1] is not None:
            self._bound(None, self._pending[1][5])  # a tested frame left out: weight 0
        if candidate and self._pending is not None and self._pending[1] is not None and self._last is not None:
            self._candidates = (self._candidates + [self._last])[-self.settings.reacquire_after :]
        else:
            self._candidates = []
        self._pending = None

    def _bound(self, G: Mat3 | None, sigma: list[float]) -> None:
        """Add a tested frame to the protection level's sums, unless it is one of the trusted frames
        after the first start (assumption A of pipeline/defense/protection.py); after the last of them
        the sums start, from the state's covariance then (the PL's noise term)."""
        if self._trusted > 0:
            self._trusted -= 1
            if self._trusted == 0:
                self.protection.anchor(self.pos.A, self.measurement_variance)
        else:
            self.protection.add(G, sigma)

    def reacquire(self) -> bool:
        """Restart the filter when the last `reacquire_after` (M) frames were all rejected as
        candidates, agree with one another (their positions, moved to the current frame by the
        commanded displacements, scatter about their weighted mean as the noise model says:
        chi-square with 3 (M - 1) dof at 1 - false_alarm) and agree with the median of the last
        2 M accepted measurements, moved likewise (the gate's NIS; skipped while fewer than M
        frames were accepted since the start). The filter's state was then
        wrong (dragged by attacked frames that slipped through), not the frames; a jump to a new,
        steady position (an attacker's consistent offset) disagrees with the accepted history and
        does not restart the filter. The restarted filter carries the old bias bound plus the
        agreement's tolerance into its protection level (pipeline/defense/protection.py). Returns
        whether it restarted."""
        M = self.settings.reacquire_after
        if len(self._candidates) < M:
            return False
        moved = np.array(self._moved)
        z = np.array([c[0] for c in self._candidates]) + moved
        W = [np.linalg.inv(np.array(c[1])) for c in self._candidates]
        cov = np.linalg.inv(sum(W))
        mean = cov @ sum(w @ zi for w, zi in zip(W, z))
        scatter = sum(float((zi - mean) @ w @ (zi - mean)) for w, zi in zip(W, z))
        if scatter > self._agree:
            return False
        if len(self._history) >= M:  # a history shorter than the candidates does not outvote them
            d = mean - (np.median(np.array(self._history), axis=0) + moved)
            if float(d @ np.linalg.inv(cov + np.array(self._candidates[-1][1])) @ d) > self.gate:
                return False
        candidates = self._candidates
        tolerance = 2.0 * math.sqrt(self.gate * largest_eigenvalue((cov + np.array(candidates[-1][1])).tolist()))
        self.start(
            mean,
            cov + np.eye(3) * M**2 * (self.settings.position_noise**2 if self._var is None else self._var),
            candidates[-1][2],
            offset=self.protection.bias() + tolerance,
        )
        self._history.extend(c[0] for c in candidates)
        return True
