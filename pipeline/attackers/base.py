"""The interface of the chain-level attackers (issue 26): one run of frames in, stored 8-bit images out.

Every attacker knows the whole chain: the pose network and the detector (a `DifferentiableChain`,
e.g. `pipeline.attacks.adaptive.PerFrameChain`: frames -> (pose (B, 9) [m, 6-D], attack logit
(B,))), and the defense with its state (`pipeline.defense.fusion.Defense`: the detector's
threshold, the motion filter, its noise model and gate, in the state the frames before the run
left it). Given the frames of a run (`AttackRun`) and an L-inf budget eps, an attacker returns the
images it delivers, as a camera stores them (uint8, 8-bit levels, `pipeline.attacks.gradient.quantize`).
An attacker may simulate the defense step by step on its own copy (`copy.deepcopy(defense)`); it
never changes the caller's `defense`, chain or run.

One module per attacker next to this one (pipeline/attackers/drift.py, pipeline/attackers/burst.py),
each a class with a `name` and `attack(chain, defense, run, eps)`; options (steps, restarts, rates)
go to its constructor. The registry by name is pipeline/attackers/suite.py (`ATTACKERS`, `get_attacker`):
a new attacker adds its class there.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from pipeline.attacks.adaptive import DifferentiableChain
from pipeline.defense.fusion import Defense


@dataclass(frozen=True)
class AttackRun:
    """The frames of one run, in time order, as the attacker sees them.

    images: (N, 3, H, W) float clean frames on the 8-bit grid (uint8 / 255); labels: (N, 9) true
    pose (camera-frame position, m; 6-D rotation); R_cam: (N, 3, 3) camera -> world; u: (N, 3)
    commanded displacement of rel since the previous frame (world axes, m; row 0 unused) or None
    for a still chaser (the `Defense.step` arguments); attacked: (N,) bool, the frames the attacker
    may change (None: all of them).
    """

    images: Tensor
    labels: Tensor
    R_cam: np.ndarray
    u: np.ndarray | None = None
    attacked: np.ndarray | None = None

    def __post_init__(self) -> None:
        n = len(self.images)
        if self.images.ndim != 4 or self.images.shape[1] != 3:
            raise ValueError(f"attack run: images must be (N, 3, H, W), got {tuple(self.images.shape)}")
        shapes = {"labels": (tuple(self.labels.shape), (n, 9)), "R_cam": (np.shape(self.R_cam), (n, 3, 3))}
        if self.u is not None:
            shapes["u"] = (np.shape(self.u), (n, 3))
        if self.attacked is not None:
            shapes["attacked"] = (np.shape(self.attacked), (n,))
        for name, (got, want) in shapes.items():
            if tuple(got) != want:
                raise ValueError(f"attack run: {name} must be {want} for {n} frames, got {tuple(got)}")

    def __len__(self) -> int:
        return len(self.images)

    @property
    def mask(self) -> np.ndarray:
        """(N,) bool: the frames the attacker may change."""
        return np.ones(len(self), bool) if self.attacked is None else np.asarray(self.attacked, bool)

    def stored(self) -> Tensor:
        """The clean frames as stored: uint8 (N, 3, H, W)."""
        return torch.round(self.images * 255.0).to(torch.uint8)


class SequenceAttacker(Protocol):
    """A chain-level attacker: `attack` returns the stored images (uint8, (N, 3, H, W)) it delivers
    for `run`, each within `eps` (L-inf, pixel values in [0, 1], eps in (0, 1]) of its clean frame
    up to the 8-bit rounding of `quantize`; frames outside `run.mask` are returned unchanged.
    `defense` None: the undefended chain (guidance flies on the raw estimate)."""

    name: str

    def attack(self, chain: DifferentiableChain, defense: Defense | None, run: AttackRun, eps: float) -> Tensor: ...


def pose_logit(out: Tensor | tuple[Tensor, Tensor]) -> tuple[Tensor, Tensor | None]:
    """A chain's output: (pose, logit) of a `DifferentiableChain`, or a bare pose model's pose (no detector)."""
    return out if isinstance(out, tuple) else (out, None)


def chain_outputs(chain: DifferentiableChain, images: Tensor, batch: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """What the chain reads from `images` (N, 3, H, W) in [0, 1]: pose (N, 9) [m, 6-D] and the detector's
    probability (N,), as float64 arrays (probability 0 without a detector), `batch` images per pass."""
    poses, probs = [], []
    with torch.no_grad():
        for lo in range(0, len(images), batch):
            p, logit = pose_logit(chain(images[lo : lo + batch]))
            poses.append(p.double())
            probs.append(torch.zeros(len(p), dtype=torch.float64) if logit is None else torch.sigmoid(logit.double()))
    return torch.cat(poses).numpy(), torch.cat(probs).numpy()


def margin_cost(z: Tensor, hinge: float | None) -> Tensor:
    """The price an attacker pays for a check's margin z (> 0 where the check stops the frame): softplus(z),
    or with a hinge m, max(0, z + m): nothing once the check is under its threshold by m."""
    return F.softplus(z) if hinge is None else F.relu(z + hinge)


def probability_logit(p: float) -> float:
    """log(p / (1 - p)): the logit of a detector's probability threshold p in (0, 1)."""
    return math.log(p / (1 - p))


def doubt_logit(defense: Defense | None) -> float | None:
    """The logit of the probability at which `defense` stops updating its filter (its doubt level,
    `update_below`, else its threshold: a frame at or above it captures nothing); None without a defense
    (nothing to evade)."""
    if defense is None:
        return None
    s = defense.settings
    return probability_logit(s.threshold if s.update_below is None else s.update_below)
