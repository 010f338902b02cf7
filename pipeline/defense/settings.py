"""The defended chain's settings (pipeline/defense/fusion.py): which checks flag a frame, when the estimate is
declared lost and released, and the detector's threshold and doubt level. The motion filter's own settings are
pipeline/defense/gate.py's `MotionSettings`. Declared here, beside nothing heavier than the checks, so the params
schema (stages/config) composes them without taking the chain's code."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Literal, Optional

from pipeline.settings import In

FUSIONS = ("paper", "motion", "or")
ATTACK, DOUBT, CLEAN = "attack", "doubt", "clean"  # the detector's word on a frame (`DefenseSettings.word`)


@dataclass(frozen=True)
class DefenseSettings:
    """fusion: which checks flag a frame (FUSIONS); hold_after: K consecutive flags that declare the
    estimate lost; release_after: consecutive clean frames that end a hold; threshold: the
    detector's probability threshold (its checkpoint's, chosen on validation data); update_below:
    frames whose detector probability is at or above this (but below the threshold) are not flagged
    but do not update the motion filter either (None: the threshold)."""

    fusion: Literal[FUSIONS] = "or"
    hold_after: Annotated[int, In("[1, 10000000]", "frames")] = 5
    release_after: Annotated[int, In("[1, 10000000]", "frames")] = 2
    threshold: Annotated[float, In("(0, 1)", "probability")] = 0.5
    update_below: Optional[Annotated[float, In("(0, 1)", "probability")]] = None

    def __post_init__(self) -> None:
        if self.fusion not in FUSIONS:
            raise ValueError(f"unknown defense.fusion {self.fusion!r}; choose one of {', '.join(FUSIONS)}")
        if int(self.hold_after) < 1:
            raise ValueError(
                f"defense.hold_after (K consecutive flags before a hold) must be >= 1, got {self.hold_after}"
            )
        if int(self.release_after) < 1:
            raise ValueError(f"defense.release_after must be >= 1, got {self.release_after}")
        if not 0 < float(self.threshold) < 1:
            raise ValueError(f"detector threshold must be in (0, 1), got {self.threshold}")
        if self.update_below is not None and not 0 < float(self.update_below) <= float(self.threshold):
            raise ValueError(
                f"defense.update_below must be in (0, threshold = {self.threshold}], got {self.update_below}"
            )

    def word(self, prob: float) -> str:
        """The detector's word on one frame of probability `prob`: ATTACK at or above the threshold (or a
        non-finite probability), DOUBT at or above the doubt level `update_below`, else CLEAN. `Defense.step`
        flags on ATTACK and keeps a frame that is not CLEAN out of the filter (unless fusion is "motion");
        a per-image verdict (rpodguard's `predict`) is this word."""
        if not math.isfinite(prob) or prob >= self.threshold:
            return ATTACK
        return DOUBT if self.update_below is not None and prob >= self.update_below else CLEAN
