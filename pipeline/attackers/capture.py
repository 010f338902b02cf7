"""Capture at acquisition: a consistent world-frame bias from the first frame, held or grown to docking.

The classic attack on a filtered navigator. The motion filter (pipeline/defense/kalman.py) starts on
the first frame the detector lets through and from then on checks each estimate against its own
prediction, the previous state moved by the commanded displacement. An estimate biased by the same
world-frame vector b on every frame from the first one on is consistent with the commanded motion: the
filter starts at truth + b and every innovation is the pose network's noise alone, so neither the gate
nor the sequential test sees anything; the protection level assumes the first `trusted_start` frames
fault-free (its assumption A) and does not count it either. The guidance then flies the chaser to
g - b: a docking miss of |b| (along the line of sight outward, an overshoot toward the target). Only
the detector, frame by frame, and the attacker's capacity (how far eps moves the pose network's
output at each range) stand in the way.

Plan (`CaptureSettings`, `capture_bias`): a world direction fixed at acquisition from the first
frame's line of sight (pipeline/attackers/drift.py `drift_direction`: "los" outward, "near" inward,
"lateral" / "vertical" across), and the bias wanted on the k-th attacked frame b_k = min(initial + rate
k, final) (m): `rate` 0 holds the acquisition bias to docking, > 0 grows it. Once the filter runs, the
bias delivered is the one nearest b_k that keeps the innovation under `gate_fraction` of the gate and
every CUSUM statistic under `cusum_fraction` of its threshold (`stealthy_bias`, the drift's stealth),
so a held bias costs nothing and a grown one as fast as the checks allow. Against the undefended chain
the wanted bias is delivered as is.

At the pixel level each attacked frame is a `FrameAttack` (pipeline/attackers/drift.py; `TargetedPGD` by
default) toward the clean estimate + b_k d, the detector's margin taken against its doubt level (the
probability at which the defense stops updating its filter: a doubtful frame would not capture it).
- On recorded trajectories: `CaptureAttacker` (the chain-level interface of pipeline/attackers/base.py),
  or its planner (`CaptureSettings.planner`) in the batched runner
  (pipeline.evaluation.integrity_runs.plan_attack).
- In the closed loop: `CaptureInLoop`, an in-loop attacker (`observe` the loop's state, then
  `__call__(x, y)` as the camera's attack), reading the live defense's filter to stay under its checks.
  A drift from acquisition in the loop is the same attacker with a small initial bias and a rate
  (e.g. initial 0.05 m, rate 0.1 m/frame: the checks decide how fast it may grow).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from pipeline.attackers.base import AttackRun, chain_outputs, doubt_logit
from pipeline.attackers.drift import (
    DIRECTIONS,
    BiasPlanner,
    FrameAttack,
    TargetedPGD,
    drift_direction,
    planned_attack,
    stealthy_bias,
)
from pipeline.attacks.adaptive import DifferentiableChain
from pipeline.attacks.gradient import check_eps
from pipeline.defense.fusion import Defense
from pipeline.defense.kalman import MotionFilter


@dataclass(frozen=True)
class CaptureSettings:
    """direction: one of drift.DIRECTIONS, fixed in world axes at acquisition; initial: the bias at
    acquisition (m, > 0); rate: its growth per attacked frame (m/frame, >= 0; 0 holds it); final: a
    ceiling on the grown bias (m; None: none); gate_fraction in (0, 1] and cusum_fraction in (0, 1] or
    None: the stealth once the filter runs (as `DriftSettings`)."""

    direction: str = "lateral"
    initial: float = 1.0
    rate: float = 0.0
    final: float | None = None
    gate_fraction: float = 0.5
    cusum_fraction: float | None = 0.5

    def __post_init__(self) -> None:
        if self.direction not in DIRECTIONS:
            raise ValueError(f"unknown capture direction {self.direction!r}; choose one of {', '.join(DIRECTIONS)}")
        if not (math.isfinite(self.initial) and self.initial > 0):
            raise ValueError(f"capture initial bias (m) must be a finite number > 0, got {self.initial}")
        if not (math.isfinite(self.rate) and self.rate >= 0):
            raise ValueError(f"capture rate (m/frame) must be a finite number >= 0, got {self.rate}")
        if self.final is not None and not (math.isfinite(self.final) and self.final >= self.initial):
            raise ValueError(
                f"capture final bias (m) must be None or at least the initial {self.initial}, got {self.final}"
            )
        if not 0 < float(self.gate_fraction) <= 1:
            raise ValueError(f"capture gate_fraction must be in (0, 1], got {self.gate_fraction}")
        if self.cusum_fraction is not None and not 0 < float(self.cusum_fraction) <= 1:
            raise ValueError(f"capture cusum_fraction must be in (0, 1] or None, got {self.cusum_fraction}")

    def wanted(self, k: int) -> float:
        """The bias (m) wanted on the k-th attacked frame (0: acquisition)."""
        b = self.initial + self.rate * int(k)
        return b if self.final is None else min(b, self.final)

    def planner(self, defense: Defense | None) -> "CapturePlanner":
        """This capture's planner against (a copy of) `defense` (None: the undefended chain)."""
        return CapturePlanner(defense, self)


def capture_bias(
    settings: CaptureSettings,
    k: int,
    motion: MotionFilter | None,
    t_clean: np.ndarray,
    R_cam: np.ndarray,
    u: np.ndarray | None,
    d_cam: np.ndarray,
) -> float:
    """The bias (m) along the camera-frame unit vector d_cam for the k-th attacked frame whose clean
    estimate is t_clean (camera frame, m): `settings.wanted(k)` before the filter `motion` runs (or
    without one), else the stealthy bias nearest it (pipeline.attackers.drift.stealthy_bias)."""
    wanted = settings.wanted(k)
    if motion is None or not motion.started:
        return wanted
    cusum = None if settings.cusum_fraction is None else settings.cusum_fraction * motion.cusum.threshold
    return stealthy_bias(motion, t_clean, R_cam, u, d_cam, settings.gate_fraction * motion.gate, wanted, cusum)


def _world_direction(settings: CaptureSettings, t_clean: np.ndarray, R_cam: np.ndarray) -> np.ndarray:
    """The capture's world direction (3,), from the acquisition frame's clean line of sight."""
    return np.asarray(R_cam, np.float64) @ drift_direction(t_clean, settings.direction)


class CapturePlanner(BiasPlanner):
    """The capture against a copy of `defense` (None: undefended), as `DriftPlanner` plans the drift:
    `target` gives the estimate wanted for the next attacked frame, `deliver` steps the copy on what was
    delivered; `bias` (m) the last planned bias, `direction` (world) fixed on the first attacked frame."""

    def __init__(self, defense: Defense | None, settings: CaptureSettings):
        super().__init__(defense, settings)
        self.frames = 0

    def target(self, t_clean: np.ndarray, R_cam: np.ndarray, u: np.ndarray | None) -> np.ndarray:
        """The camera-frame estimate (m) the capture wants for a frame whose clean estimate is t_clean."""
        R_cam = np.asarray(R_cam, np.float64)
        if self.direction is None:
            self.direction = _world_direction(self.settings, t_clean, R_cam)
        d = R_cam.T @ self.direction
        motion = None if self.defense is None else self.defense.filter
        self.bias = capture_bias(self.settings, self.frames, motion, t_clean, R_cam, u, d)
        self.frames += 1
        return np.asarray(t_clean, np.float64) + self.bias * d


class CaptureAttacker:
    """The capture on recorded runs (pipeline/attackers/base.py's interface): `settings` the plan,
    `frame_attack` the per-frame attack (default `TargetedPGD()`), `seed` its random draws. Frames
    outside `run.mask` are left clean (attack from frame 0 to capture at acquisition)."""

    name = "capture"

    def __init__(
        self, settings: CaptureSettings = CaptureSettings(), *, frame_attack: FrameAttack | None = None, seed: int = 0
    ):
        self.settings, self.seed = settings, int(seed)
        self.frame_attack = TargetedPGD() if frame_attack is None else frame_attack

    def attack(self, chain: DifferentiableChain, defense: Defense | None, run: AttackRun, eps: float) -> Tensor:
        """The stored images (uint8 (N, 3, H, W)) the capture delivers for `run` at L-inf budget eps."""
        return planned_attack(
            chain,
            run,
            check_eps(eps),
            self.settings.planner(defense),
            self.frame_attack,
            doubt_logit(defense),
            torch.Generator().manual_seed(self.seed),
        )


class CaptureInLoop:
    """The capture in the closed loop (pipeline/guidance/law.py): `observe` is the loop's observe hook and
    the attacker itself the camera's `attack(x, y)` (images (1, 3, H, W) in [0, 1] on the 8-bit grid ->
    the stored frame read back as floats). Attack from the first frame (an AttackWindow at the start
    range) to capture at acquisition. `bias` holds the planned bias per attacked frame (m)."""

    name = "capture_in_loop"

    def __init__(
        self,
        chain: DifferentiableChain,
        eps: float,
        settings: CaptureSettings = CaptureSettings(),
        *,
        frame_attack: FrameAttack | None = None,
        seed: int = 0,
    ):
        self.chain, self.eps, self.settings = chain, check_eps(eps), settings
        self.frame_attack = TargetedPGD() if frame_attack is None else frame_attack
        self.generator = torch.Generator().manual_seed(int(seed))
        self.state: Any = None  # the loop's pipeline.guidance.law.LoopState (read only)
        self.direction: np.ndarray | None = None
        self.bias: list[float] = []

    def observe(self, state: Any) -> None:
        """The loop's observe hook: `state` is the pipeline.guidance.law.LoopState before the next frame."""
        self.state = state

    def __call__(self, x: Tensor, y: Tensor | None = None) -> Tensor:
        """The attacked frame as stored (uint8 -> floats in [0, 1]), (1, 3, H, W); `y` is not used."""
        s = self.state
        if s is None:
            raise ValueError("capture in the loop: no loop state; pass its observe to run_rendezvous")
        (pose,), _ = chain_outputs(self.chain, x)
        t0 = pose[:3]
        if self.direction is None:
            self.direction = _world_direction(self.settings, t0, s.R_c)
        d = s.R_c.T @ self.direction
        motion = None if s.defense is None else s.defense.filter
        b = capture_bias(self.settings, len(self.bias), motion, t0, s.R_c, s.u, d)
        self.bias.append(b)
        target = torch.as_tensor(np.concatenate([t0 + b * d, pose[3:]]), dtype=x.dtype)[None]
        stored = self.frame_attack(self.chain, x, target, self.eps, doubt_logit(s.defense), self.generator)
        return stored.float() / 255.0
