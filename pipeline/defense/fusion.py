"""The defended chain: SHAP detector fused with the motion check, recovery and safe hold.

Per frame, `Defense.step` turns (camera-frame estimate, detector probability, camera attitude,
commanded displacement) into (flag, trusted estimate, mode, protection level, availability):
- flag: the detector's probability >= its threshold (`fusion` "paper", the paper's detector alone),
  the motion filter's checks: its per-frame gate or its sequential test (`fusion` "motion"), or
  any of them ("or", the default);
- a frame that neither check flags updates the motion filter and the trusted estimate is the
  filter's state (world frame, metres); a flagged frame is left out, the filter coasts on its
  prediction and the prediction is the trusted estimate (mode "coast"). The filter leaves out the
  frames its gate rejects and, unless fusion is "motion", the frames the detector flags, whatever
  the fusion: the trusted estimate stays sound under either check. A frame whose probability is
  at or above `update_below` (below the threshold; its level is calibrated on clean validation frames,
  `pipeline.defense.calibration.doubt_level`) is doubtful: not flagged, but not used either;
- a frame that passes the gate and the detector goes to the sequential test (a CUSUM on the
  innovations, pipeline/defense/sequential.py): a frame on which it alarms is flagged and coasts and
  the test restarts, so a slow drift that stays under the gate is flagged as it walks the state;
- PL (m): the protection level of the trusted estimate (pipeline/defense/protection.py; inf before
  the start, and on the trusted-start frames once the detector has flagged a frame of the run: they rest on
  the detector alone, assumption A), which grows with every restart of the test; available: the guidance may fly on the trusted
  estimate: mode track or coast and, with an alert limit AL(range) given, PL <= AL at the trusted
  estimate's range (the chaser's best knowledge of it; the offline integrity metrics,
  pipeline/defense/integrity.py, judge PL against AL at the true range);
- frames only the gate rejects are restart candidates: when the last M of them agree with one
  another (pipeline.defense.kalman.MotionFilter.reacquire), the filter restarts on them and the frame is
  not flagged by the motion check: it was the filter that was wrong (a state corrupted by attacked
  frames that slipped through), and a filter that never restarts would flag every clean frame after;
- after `hold_after` consecutive flags the estimate is declared lost (mode "hold"): guidance should
  hold position until `release_after` consecutive frames pass both checks.
Before the first unflagged frame there is no estimate to trust: such frames are in mode "hold" and
the filter starts on the first frame the detector does not flag. The start is on probation like the end of
a hold: the chain stays in mode "hold" until `release_after` frames in a row, the start frame among them,
passed every check, so a single frame the detector let through at acquisition cannot be flown on alone.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from pipeline.defense.gate import MotionSettings
from pipeline.defense.kalman import MotionFilter
from pipeline.defense.noise import NoiseModel
from pipeline.defense.settings import ATTACK, CLEAN, DefenseSettings

TRACK, COAST, HOLD = "track", "coast", "hold"
MODES = (TRACK, COAST, HOLD)


@dataclass(frozen=True)
class Decision:
    """One frame: flag (fused), shap_flag, motion_flag (the gate), trusted rel (world frame, m; NaN
    before the filter starts), mode (MODES), NIS of position and attitude (NaN when not tested),
    sequential_flag (the sequential test alarms), pl (m) and available (see the module docstring)."""

    flag: bool
    shap_flag: bool
    motion_flag: bool
    trusted: np.ndarray
    mode: str
    nis_position: float
    nis_attitude: float
    sequential_flag: bool = False
    pl: float = math.inf
    available: bool = False


AlertLimitFn = Callable[[float], float]
"""AL (m) at a range (m): the largest error the guidance absorbs there (pipeline/defense/integrity.py)."""


class Defense:
    """Stateful per-frame defense; one instance per trajectory or closed-loop run. `alert_limit`:
    AL(range) (m) for the availability (None: available wherever the PL is finite and flown)."""

    def __init__(
        self,
        settings: DefenseSettings,
        motion: MotionSettings,
        noise: NoiseModel,
        alert_limit: AlertLimitFn | None = None,
    ):
        self.settings = settings
        self.filter = MotionFilter(motion, noise)
        self.alert_limit = alert_limit
        self.flags_in_a_row = 0
        self.clean_in_a_row = 0
        self.holding = True

    def step(
        self,
        t_pred: np.ndarray,
        prob: float,
        R_cam: np.ndarray,
        u: np.ndarray | None = None,
        R_pred: np.ndarray | None = None,
    ) -> Decision:
        """One frame: t_pred camera-frame estimate (m), prob detector probability, R_cam camera ->
        world, u commanded displacement of rel since the previous frame (world, m), R_pred target ->
        camera estimate (optional; enables the attitude check)."""
        s = self.settings
        word = s.word(prob)
        shap_flag = word == ATTACK
        if shap_flag and s.fusion != "motion":  # the guard of the trusted start has flagged (assumption A)
            self.filter.doubt_start()
        if not self.filter.started:
            if shap_flag or not np.isfinite(t_pred).all():
                return Decision(True, shap_flag, False, np.full(3, np.nan), HOLD, np.nan, np.nan)
            self.filter.start_from(t_pred, R_cam, R_pred)
            self.clean_in_a_row = 1  # the start frame is the first of `release_after` clean frames (probation)
            self.holding = self.clean_in_a_row < s.release_after
            return self._decide(False, False, False, False, HOLD if self.holding else TRACK, np.nan, np.nan)
        check = self.filter.check(t_pred, R_cam, u, R_pred)
        motion_flag, sequential_flag = check.inconsistent, False
        suspect = word != CLEAN and s.fusion != "motion"  # the detector's word, where it counts
        finite = math.isfinite(check.nis_position)
        if not finite or (suspect and motion_flag):
            self.filter.coast()
        elif motion_flag:
            self.filter.coast(candidate=True)
            # the last frames agree with one another but not with the filter: the filter was wrong
            motion_flag = not self.filter.reacquire()
        elif suspect:
            self.filter.coast()
        elif self.filter.test_sequence():
            sequential_flag = True
            self.filter.coast()
        else:
            self.filter.accept()
        checks = {
            "paper": shap_flag,
            "motion": motion_flag or sequential_flag,
            "or": shap_flag or motion_flag or sequential_flag,
        }
        flag = checks[s.fusion] or not finite
        if flag:
            self.flags_in_a_row += 1
            self.clean_in_a_row = 0
            if self.flags_in_a_row >= s.hold_after:
                self.holding = True
        else:
            self.flags_in_a_row = 0
            self.clean_in_a_row += 1
            if self.holding and self.clean_in_a_row >= s.release_after:
                self.holding = False
        mode = HOLD if self.holding else (COAST if flag else TRACK)
        return self._decide(flag, shap_flag, motion_flag, sequential_flag, mode, check.nis_position, check.nis_attitude)

    def _decide(
        self,
        flag: bool,
        shap_flag: bool,
        motion_flag: bool,
        sequential_flag: bool,
        mode: str,
        nis_position: float,
        nis_attitude: float,
    ) -> Decision:
        """The Decision with the filter's state, its PL and the availability."""
        trusted, pl = self.filter.position, self.filter.protection_level
        available = mode != HOLD and pl < math.inf
        if available and self.alert_limit is not None:
            available = bool(pl <= self.alert_limit(math.sqrt(float(trusted @ trusted))))
        return Decision(
            bool(flag),
            bool(shap_flag),
            bool(motion_flag),
            trusted,
            mode,
            nis_position,
            nis_attitude,
            bool(sequential_flag),
            pl,
            bool(available),
        )


@dataclass(frozen=True)
class DefenseTrace:
    """A sequence through `run_defense`: flag, shap_flag, motion_flag (N,) bool; trusted (N, 3) world
    frame (m); mode (N,) str; nis_position, nis_attitude (N,); sequential_flag (N,) bool, pl (N,) m
    and available (N,) bool (None in traces made without them)."""

    flag: np.ndarray
    shap_flag: np.ndarray
    motion_flag: np.ndarray
    trusted: np.ndarray
    mode: np.ndarray
    nis_position: np.ndarray
    nis_attitude: np.ndarray
    sequential_flag: np.ndarray | None = None
    pl: np.ndarray | None = None
    available: np.ndarray | None = None


def run_defense(
    settings: DefenseSettings,
    motion: MotionSettings,
    noise: NoiseModel,
    t_pred: np.ndarray,
    prob: np.ndarray,
    R_cam: np.ndarray,
    u: np.ndarray | None = None,
    R_pred: np.ndarray | None = None,
    alert_limit: AlertLimitFn | None = None,
) -> DefenseTrace:
    """The defense over a recorded sequence (open loop, as in the integrated evaluation).

    t_pred (N, 3) camera-frame estimates (m); prob (N,) detector probabilities; R_cam (N, 3, 3)
    camera -> world; u (N, 3) displacement of rel from frame i-1 to i (world, m; row 0 unused), e.g.
    np.diff of the planned trajectory's rel, or None for a still chaser; R_pred (N, 3, 3) optional;
    alert_limit: AL(range) for the availability (see `Defense`).
    """
    t_pred, prob, R_cam = np.asarray(t_pred, np.float64), np.asarray(prob, np.float64), np.asarray(R_cam, np.float64)
    n = len(t_pred)
    if t_pred.shape != (n, 3) or prob.shape != (n,) or R_cam.shape != (n, 3, 3):
        raise ValueError(
            f"run_defense needs t_pred (N, 3), prob (N,), R_cam (N, 3, 3); got {t_pred.shape}, "
            f"{prob.shape}, {R_cam.shape}"
        )
    if u is not None and np.shape(u) != (n, 3):
        raise ValueError(f"run_defense: u must be (N, 3) = ({n}, 3), got {np.shape(u)}")
    if R_pred is not None and np.shape(R_pred) != (n, 3, 3):
        raise ValueError(f"run_defense: R_pred must be (N, 3, 3), got {np.shape(R_pred)}")
    d = Defense(settings, motion, noise, alert_limit)
    out = [
        d.step(t_pred[i], prob[i], R_cam[i], None if u is None else u[i], None if R_pred is None else R_pred[i])
        for i in range(n)
    ]
    return trace_of(out)


def trace_of(decisions: list[Decision]) -> DefenseTrace:
    """The DefenseTrace of a run's decisions, in order."""
    n = len(decisions)

    def col(name: str) -> np.ndarray:
        return np.array([getattr(o, name) for o in decisions])

    return DefenseTrace(
        col("flag").astype(bool),
        col("shap_flag").astype(bool),
        col("motion_flag").astype(bool),
        col("trusted").reshape(n, 3),
        col("mode"),
        col("nis_position").astype(float),
        col("nis_attitude").astype(float),
        col("sequential_flag").astype(bool),
        col("pl").astype(float),
        col("available").astype(bool),
    )
