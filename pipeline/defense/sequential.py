"""The sequential test on the motion filter's innovations: a two-sided CUSUM per world axis (Page 1954).

The chi-square gate (pipeline/defense/gate.py) judges each frame alone, so a bias that grows a little
each frame (a slow drift) can stay under it on every frame while the filter follows it. With the
chaser's commanded motion known exactly, the filter's state error under a fault is the gain-weighted
sum of the fault's innovations (pipeline/defense/protection.py), and a ramp shows as innovations
with a persistent mean. Page's CUSUM accumulates that mean: per world axis i, with the normalized
innovation r_i = y_i / sqrt(S_ii) (innovation y (m), its covariance S = P + R, world axes), which is
N(0, 1) on motion consistent with the model,

    g+_i <- max(0, g+_i + r_i - c),    g-_i <- max(0, g-_i - r_i - c),

and the test alarms when any statistic exceeds h; the caller then leaves the frame out and restarts
the test (`reset`): an alarm ends a segment, so a clean false alarm flags one frame instead of the
run of frames a slowly decaying statistic would (the clean pose errors are correlated, and alarm
episodes made the calibrated rate jump between neighbouring thresholds). c (the reference value, in standard deviations)
is the persistent shift the test is tuned against (half the shift it detects fastest); h (the
threshold) sets its false-alarm rate, calibrated on clean validation trajectories (`rpod calibrate`)
because the pose model's errors are correlated from frame to frame, which the white-noise model does
not see. Within a segment (between alarms), every window a..b of the frames the filter accepted
satisfies -c (b - a + 1) - h <= sum r_i <= c (b - a + 1) + h: the bound the protection level rests on.
"""

from __future__ import annotations

import math
from typing import Sequence


class Cusum:
    """Two-sided CUSUM on 3 normalized innovations per frame (world x, y, z); see the module docstring.
    `reference` c and `threshold` h in standard deviations (c >= 0, h > 0)."""

    def __init__(self, reference: float, threshold: float):
        if not (math.isfinite(reference) and reference >= 0):
            raise ValueError(f"defense.cusum_reference must be a finite number >= 0, got {reference}")
        if not threshold > 0:
            raise ValueError(f"defense.cusum_threshold must be > 0, got {threshold}")
        self.reference, self.threshold = float(reference), float(threshold)
        self.high, self.low = [0.0] * 3, [0.0] * 3

    def reset(self) -> None:
        self.high, self.low = [0.0] * 3, [0.0] * 3

    @property
    def statistic(self) -> float:
        """The largest of the six statistics (standard deviations)."""
        return max(max(self.high), max(self.low))

    @property
    def alarmed(self) -> bool:
        return self.statistic > self.threshold

    def after(self, r: Sequence[float]) -> tuple[list[float], list[float]]:
        """(g+, g-) after the normalized innovations `r` (3,), without pushing them."""
        c = self.reference
        return ([max(0.0, g + v - c) for g, v in zip(self.high, r)], [max(0.0, g - v - c) for g, v in zip(self.low, r)])

    def push(self, r: Sequence[float]) -> bool:
        """Add one frame's normalized innovations r (3,); returns whether the test alarms."""
        self.high, self.low = self.after(r)
        return self.alarmed
