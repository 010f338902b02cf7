"""Adaptive white-box attack on the whole safety chain: ascend the pose loss while
descending the detector's logit.

The attacker knows the pose network and the detector. A *differentiable chain* maps a batch of
frames (B, 3, H, W) in [0, 1] to the pose (B, 9) [m, 6-D] and the detector's attack logit (B,)
with gradients (`DifferentiableChain`). L-inf PGD then ascends

    J(x') = pose_loss(pose(x'), y) - lambda * mean(logit(x'))

(Carlini and Wagner 2017; Tramer et al. 2020: an evaluation that skips this is no evaluation).
`adaptive_pgd` is `pipeline.attacks.gradient.pgd` run on that objective, so with lambda = 0 it is plain
PGD on the same seed, step for step.

Today's shipped chain is `PerFrameChain`: pose net -> GAP features a -> closed-form DeepSHAP
W * (a - mean_background) -> LSTM logit. A detector that reads frames in time order (a fused or
temporal detector) plugs in as another `DifferentiableChain` with `temporal = True`: it reads the
batch as one burst in time order, and the caller then attacks whole bursts (one burst per call),
so the attack optimises the burst jointly, never one frame alone.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np
import torch
from torch import Tensor, nn

from pipeline.attacks.gradient import LossFn, pgd
from pipeline.shap import ExactShap

DEFAULT_STEPS = 20


class DifferentiableChain(Protocol):
    """What the adaptive attack differentiates through (`PerFrameChain`; the chain-level attackers of
    pipeline/attackers/base.py take the same).

    Frames (B, 3, H, W) in [0, 1] -> (pose (B, 9) [m, 6-D], attack logit (B,)), differentiable.

    `temporal`: False when each frame's logit depends on that frame alone (the batch is any set of
    frames); True when the batch is read as one burst in time order.
    """

    temporal: bool

    def __call__(self, images: Tensor) -> tuple[Tensor, Tensor]: ...

    def eval(self) -> "DifferentiableChain": ...

    def train(self, mode: bool = True) -> "DifferentiableChain": ...

    @property
    def training(self) -> bool: ...


class PerFrameChain(nn.Module):
    """The attacker's differentiable copy of `OnboardChain`, frame by frame (stages/robustness.py's adaptive PGD).

    The shipped chain as one differentiable module: image -> pose and LSTM-on-SHAP logit.

    `model`: PoseNet (forward_features (B, D), forward_head (B, 9)); `weight` (9, D) the affine head
    weights and `background_mean` (D,) the SHAP background mean (as in `pipeline.defense.chain.OnboardChain`); `detector`:
    SHAP values (B, 9, D) -> logits (B,). The pose is `forward_head(forward_features(x))`, exactly
    `model(x)`, so the features are computed once for both outputs. Built in eval mode (BatchNorm
    statistics frozen): the attack restores this mode afterwards, so the shared pose model stays in it.
    """

    temporal = False

    def __init__(self, model: nn.Module, shap: ExactShap, detector: nn.Module):
        super().__init__()
        self.model = model
        self.detector = detector
        self.shap = shap
        self.eval()

    def forward(self, images: Tensor) -> tuple[Tensor, Tensor]:
        features = self.model.forward_features(images)
        pose = self.model.forward_head(features)
        return pose, self.detector(self.shap(features))


def check_lambdas(lambdas: list[float]) -> list[float]:
    """A non-empty list of finite lambda >= 0 (the weight of the detector's logit)."""
    out = [float(v) for v in lambdas]
    bad = [v for v in out if not np.isfinite(v) or v < 0]
    if not out or bad:
        raise ValueError(f"lambda must be a non-empty list of finite values >= 0, got {list(lambdas)}")
    return out


def adaptive_objective(loss_fn: LossFn, lam: float) -> LossFn:
    """J((pose, logit), y) = loss_fn(pose, y) - lam * mean(logit): what the adaptive attack ascends."""
    lam = check_lambdas([lam])[0]

    def objective(out: tuple[Tensor, Tensor], y: Tensor) -> Tensor:
        pose, logit = out
        return loss_fn(pose, y) - lam * logit.mean()

    return objective


def adaptive_pgd(
    chain: DifferentiableChain,
    x: Tensor,
    y: Tensor,
    eps: float,
    loss_fn: LossFn,
    lam: float,
    *,
    steps: int = DEFAULT_STEPS,
    step_size: float | None = None,
    random_start: bool = True,
    generator: torch.Generator | None = None,
) -> Tensor:
    """L-inf PGD (random start, `steps` signed steps of `step_size`, default 2.5 eps / steps) on
    `loss_fn(pose, y) - lam * mean(logit)` through `chain`; returns float images in [0, 1]
    within eps of `x` (store them with `pipeline.attacks.gradient.quantize`, as every attack).

    `x` (B, 3, H, W) in [0, 1], `y` (B, 9) labels [m, 6-D]; for a temporal chain the batch is one burst.
    """
    return pgd(
        chain,
        x,
        y,
        eps,
        adaptive_objective(loss_fn, lam),
        steps=steps,
        step_size=step_size,
        random_start=random_start,
        generator=generator,
    )
