"""The motion filter's settings and its chi-square gate (the filter: pipeline/defense/kalman.py).

The gate: each frame's normalized innovation squared (NIS) of position (3 dof) and attitude (3
dof) is compared with the chi-square quantile at 1 - alpha / 2 each, so a frame consistent with the
model is flagged with probability at most `alpha` (the false-alarm rate, Bonferroni over the two
tests). A flagged frame is not used to update the filter (fault exclusion): the filter coasts on
its prediction, its covariance grows, and clean frames are accepted again once they fall inside
the widened gate, so an attack the gate caught cannot drag the state away. Frames that pass the
gate update the filter with a Huber weight (measurement covariance inflated by NIS / soft gate
above a soft gate), so an attacked frame that slips just under the gate moves the state little.
A filter whose state was nevertheless dragged away (or started on a bad frame) would reject every
clean frame after; `reacquire` restarts it on M rejected frames that agree with one another and
with the accepted history, never on a steady offset that jumped away from that history.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated

import numpy as np
from scipy.stats import chi2

from pipeline.defense.noise import check_positive
from pipeline.settings import In


@dataclass(frozen=True)
class MotionSettings:
    """Filter settings. position_noise and position_noise_scale: the execution error of the chaser's
    commanded displacement per frame, its std per axis hypot(position_noise, position_noise_scale |u|)
    (m; `step_variance`: a part independent of the step and a part proportional to the commanded step u, as
    thrusters err; the position state has no free velocity: the chaser commands its relative motion);
    attitude_noise_deg and attitude_rate_noise_deg: the target attitude's
    unmodelled rotation and rate change per frame (deg, deg/frame; the target's tumble is not
    commanded); false_alarm: the gate's false-alarm probability per frame on motion consistent with
    the model, in (0, 1); soft_gate: fraction of the gate's NIS above which an accepted frame is
    down-weighted; reacquire_after: M consecutive rejected frames that agree with one another (and
    that the detector did not flag) restart the filter on them; cusum_reference (c) and
    cusum_threshold (h): the sequential test's reference value and threshold in standard deviations
    (pipeline/defense/sequential.py; h is calibrated on validation trajectories); integrity_risk:
    the per-frame probability that the protection level's noise term is exceeded; trusted_start:
    frames after the filter's first start that the protection level assumes fault-free (its
    assumption A, pipeline/defense/protection.py: the detector alone guards them); correlated_error: the
    share of one measurement's variance that the frames share, which the filter's average cannot remove
    (assumption C there; calibrated on validation trajectories, pipeline/defense/calibration.py)."""

    position_noise: Annotated[float, In("(0, 1000]", "metres per frame")] = 0.005
    position_noise_scale: Annotated[float, In("[0, 1]", "fraction of the commanded step")] = 0.0
    attitude_noise_deg: Annotated[float, In("(0, 180]", "degrees per frame")] = 0.5
    attitude_rate_noise_deg: Annotated[float, In("(0, 180]", "degrees per frame per frame")] = 0.05
    false_alarm: Annotated[float, In("(0, 1)", "probability per frame")] = 0.001
    soft_gate: Annotated[float, In("(0, 1]", "fraction of the gate")] = 0.5
    reacquire_after: Annotated[int, In("[2, 10000000]", "frames")] = 4
    cusum_reference: Annotated[float, In("[0, 100]", "standard deviations")] = 1.0
    cusum_threshold: Annotated[float, In("(0, 1000000]", "standard deviations")] = 10.0
    integrity_risk: Annotated[float, In("(0, 1)", "probability per frame")] = 1e-5
    trusted_start: Annotated[int, In("[0, 10000000]", "frames")] = 20
    correlated_error: Annotated[float, In("[0, 1]", "share of one measurement's variance")] = 0.0

    def __post_init__(self) -> None:
        for name in ("position_noise", "attitude_noise_deg", "attitude_rate_noise_deg", "cusum_threshold"):
            check_positive(f"defense.{name}", getattr(self, name))
        if not (np.isfinite(self.position_noise_scale) and 0 <= self.position_noise_scale <= 1):
            raise ValueError(
                f"defense.position_noise_scale must be a fraction of the step in [0, 1], got {self.position_noise_scale}"
            )
        if not 0 < float(self.false_alarm) < 1:
            raise ValueError(f"defense.false_alarm is a gate probability and must be in (0, 1), got {self.false_alarm}")
        if not 0 < float(self.soft_gate) <= 1:
            raise ValueError(f"defense.soft_gate must be in (0, 1], got {self.soft_gate}")
        if int(self.reacquire_after) < 2:
            raise ValueError(f"defense.reacquire_after must be >= 2 frames, got {self.reacquire_after}")
        if not (np.isfinite(self.cusum_reference) and self.cusum_reference >= 0):
            raise ValueError(f"defense.cusum_reference must be a finite number >= 0, got {self.cusum_reference}")
        if int(self.trusted_start) != self.trusted_start or self.trusted_start < 0:
            raise ValueError(f"defense.trusted_start must be a whole number of frames >= 0, got {self.trusted_start}")
        if not (np.isfinite(self.correlated_error) and 0 <= self.correlated_error <= 1):
            raise ValueError(f"defense.correlated_error must be a share in [0, 1], got {self.correlated_error}")
        if not 0 < float(self.integrity_risk) < 1:
            raise ValueError(f"defense.integrity_risk must be a probability in (0, 1), got {self.integrity_risk}")

    def step_variance(self, step: float) -> float:
        """The execution error's variance per axis (m^2) of a commanded displacement of length `step` (m)."""
        return self.position_noise**2 + (self.position_noise_scale * float(step)) ** 2

    @property
    def gate(self) -> float:
        """NIS threshold of each 3-dof test (position, attitude): chi2 quantile at 1 - false_alarm / 2."""
        return float(chi2.ppf(1.0 - self.false_alarm / 2.0, 3))


@dataclass
class MotionCheck:
    """One frame's motion check: NIS of position and attitude (NaN before the filter starts) and the
    gate decision; `predicted` is the filter's prediction of rel (world frame, m) before this frame."""

    nis_position: float
    nis_attitude: float
    inconsistent: bool
    predicted: np.ndarray = field(repr=False)
