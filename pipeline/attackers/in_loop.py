"""The in-loop attacker (issue 26): a closed-loop approach attacked frame by frame by an attacker who
knows the chain, the defense with its state and the guidance law, to put the chaser on a collision
course ("collide") or make it miss the docking point ("miss").

Before every frame the loop shows the attacker where it stands (`pipeline.guidance.law.LoopState`:
the true rel, the camera attitude, the command since the last frame, the live defense, read only).
For an attacked frame the attacker
1. reads the clean estimate t0 (camera frame, m), its attitude and the detector's probability;
2. looks one step ahead over candidate estimates t0 + b d, d each of +- the line of sight and +- the
   two axes across it (world axes, moved into the camera frame), b the largest bias whose innovation
   stays under `gate_fraction` of the motion gate (`pipeline.attackers.drift.stealthy_bias`, the drift's
   stealth) once the defense's filter runs, else each of `magnitudes` (m); for each it steps a copy of
   the defense and the guidance law (`pipeline.guidance.law.guidance_step`) as the loop will and keeps
   the estimate whose step brings the chaser nearest the target ("collide": the least distance from
   the target to the step's path) or farthest from the docking point ("miss"); the clean estimate is
   a candidate too, so the attacker never picks a worse step than none;
3. crafts the frame by targeted L-inf PGD toward that estimate (`pipeline.attackers.drift.targeted_pgd`,
   attitude kept at the clean estimate's, `steps` steps from a seeded random start), with the
   detector's margin in the objective when a defense reads it, stored as 8 bits.
It knows the chaser's true position (it watches the approach): the worst case. Greedy, one step of
lookahead: a course that needs a detour is not found; the counts measure what this attacker does.
The third in-loop goal, "capture" (`GOALS`), is pipeline/attackers/capture.py's `CaptureInLoop`: a consistent
bias from the first frame, held to docking (the chaser docks where the bias says the goal is).
Cost: `steps` frame-gradients per attacked frame (batch 1) and 7 copies of the defense stepped.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from pipeline.attackers.base import chain_outputs
from pipeline.attackers.drift import stealthy_bias, targeted_pgd
from pipeline.attacks.adaptive import DifferentiableChain
from pipeline.attacks.gradient import check_eps
from pipeline.defense.fusion import HOLD
from pipeline.geometry.rotations import sixd_to_matrix
from pipeline.guidance.law import LoopState, guidance_step, segment_range

GREEDY = ("collide", "miss")  # the goals of this module's greedy one-step attacker (`InLoopAttacker`)
GOALS = GREEDY + ("capture",)  # every in-loop goal: "capture" is pipeline/attackers/capture.py's `CaptureInLoop`


@dataclass(frozen=True)
class InLoopSettings:
    """goal: "collide" or "miss"; steps: PGD steps per attacked frame (>= 1); gate_fraction: every
    innovation's NIS stays under this fraction of the gate, in (0, 1]; cusum_fraction: every CUSUM statistic of
    the sequential test stays under this fraction of its threshold, in (0, 1] (None: the attacker ignores the
    test); margin_weight: the detector's margin in the objective (>= 0); magnitudes: candidate biases (m, > 0)
    where no filter bounds them."""

    goal: str = "collide"
    steps: int = 10
    gate_fraction: float = 0.5
    cusum_fraction: float | None = 0.5
    margin_weight: float = 1.0
    magnitudes: tuple[float, ...] = (0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0)

    def __post_init__(self) -> None:
        if self.goal not in GREEDY:
            raise ValueError(
                f"unknown in-loop attack goal {self.goal!r}; choose one of {', '.join(GREEDY)} "
                f"(capture: pipeline.attackers.capture.CaptureInLoop)"
            )
        if int(self.steps) < 1:
            raise ValueError(f"in-loop attack steps must be >= 1, got {self.steps}")
        if not 0 < float(self.gate_fraction) <= 1:
            raise ValueError(f"in-loop attack gate_fraction must be in (0, 1], got {self.gate_fraction}")
        if self.cusum_fraction is not None and not 0 < float(self.cusum_fraction) <= 1:
            raise ValueError(f"in-loop attack cusum_fraction must be in (0, 1] or None, got {self.cusum_fraction}")
        if not (math.isfinite(self.margin_weight) and self.margin_weight >= 0):
            raise ValueError(f"in-loop attack margin_weight must be a finite number >= 0, got {self.margin_weight}")
        if not self.magnitudes or not all(math.isfinite(m) and m > 0 for m in self.magnitudes):
            raise ValueError(f"in-loop attack magnitudes (m) must be finite and > 0, got {self.magnitudes}")


def axes(rel: np.ndarray) -> np.ndarray:
    """(6, 3) unit world directions: +- the line of sight rel / |rel| and +- two axes across it."""
    los = np.asarray(rel, np.float64) / np.linalg.norm(rel)
    side = np.cross(los, [0.0, 1.0, 0.0] if abs(los[1]) < 0.9 else [1.0, 0.0, 0.0])
    side /= np.linalg.norm(side)
    up = np.cross(los, side)
    return np.concatenate([np.stack([los, side, up]), -np.stack([los, side, up])])


class InLoopAttacker:
    """The attacker of one closed-loop run at L-inf budget `eps` through `chain` (pose, detector logit);
    `observe` is the loop's `observe` hook and the attacker itself the camera's `attack(x, y)` (images
    (1, 3, H, W) in [0, 1] on the 8-bit grid -> the stored frame read back as floats)."""

    name = "in_loop"

    def __init__(
        self, chain: DifferentiableChain, eps: float, settings: InLoopSettings = InLoopSettings(), seed: int = 0
    ):
        self.chain, self.eps, self.settings = chain, check_eps(eps), settings
        self.generator = torch.Generator().manual_seed(int(seed))
        self.state: LoopState | None = None
        self.wanted: list[np.ndarray] = []  # the camera-frame estimate aimed at, per attacked frame (m)

    def observe(self, state: LoopState) -> None:
        self.state = state

    def __call__(self, x: Tensor, y: Tensor | None = None) -> Tensor:
        """The attacked frame as stored (uint8 -> floats in [0, 1]), (1, 3, H, W); `y` is not used
        (the attacker reads the truth from the loop's state)."""
        if self.state is None:
            raise ValueError("in-loop attacker: no loop state; pass its observe to run_rendezvous")
        (pose,), (prob,) = chain_outputs(self.chain, x)
        wanted = self.aim(pose[:3], float(prob), sixd_to_matrix(pose[3:]))
        self.wanted.append(wanted)
        defense = self.state.defense
        threshold = 0.5 if defense is None else (defense.settings.update_below or defense.settings.threshold)
        target = torch.as_tensor(np.concatenate([wanted, pose[3:]]), dtype=x.dtype)[None]
        stored = targeted_pgd(
            self.chain,
            x,
            target,
            self.eps,
            math.log(threshold / (1 - threshold)),
            margin_weight=0.0 if defense is None else self.settings.margin_weight,
            steps=int(self.settings.steps),
            generator=self.generator,
        )
        return stored.float() / 255.0

    def aim(self, t0: np.ndarray, prob: float, R_pred: np.ndarray) -> np.ndarray:
        """The camera-frame estimate (m) whose next step best serves the goal (see the module docstring)."""
        s = self.state
        candidates = [np.asarray(t0, np.float64)]
        for d in axes(s.rel):
            d_cam = s.R_c.T @ d
            for b in self._biases(t0, d_cam):
                candidates.append(t0 + b * d_cam)
        scores = [self._score(self._next(t, prob, R_pred)) for t in candidates]
        return candidates[int(np.argmax(scores))]

    def _biases(self, t0: np.ndarray, d_cam: np.ndarray) -> tuple[float, ...]:
        """The candidate biases (m) along d_cam: the stealthiest-largest under the gate, or the magnitudes."""
        defense = self.state.defense
        if defense is None or not defense.filter.started:
            return self.settings.magnitudes
        motion = defense.filter
        s = self.settings
        cusum = None if s.cusum_fraction is None else s.cusum_fraction * motion.cusum.threshold
        b = stealthy_bias(
            motion, t0, self.state.R_c, self.state.u, d_cam, s.gate_fraction * motion.gate, cusum_limit=cusum
        )
        return (b,) if b > 0 else ()

    def _next(self, t: np.ndarray, prob: float, R_pred: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(true rel now, true rel after the step) if the chain read `t` (camera frame, m) with `prob`."""
        s = self.state
        g = s.settings
        flown: np.ndarray | None = s.R_c @ t
        if s.defense is not None:
            decision = copy.deepcopy(s.defense).step(t, prob, s.R_c, s.u, R_pred)
            if g.defense == "hold":
                flown = None if decision.flag else flown
            else:
                flown = None if decision.mode == HOLD else decision.trusted
        if flown is None:
            return s.rel, s.rel
        return s.rel, guidance_step(flown, s.rel, np.asarray(g.goal, np.float64), g.max_step, g.variant)[0]

    def _score(self, step: tuple[np.ndarray, np.ndarray]) -> float:
        """Larger is better for the attacker: minus the step's closest range, or the distance from the goal."""
        now, after = step
        if self.settings.goal == "collide":
            return -segment_range(now, after)
        return float(np.linalg.norm(after - np.asarray(self.state.settings.goal, np.float64)))
