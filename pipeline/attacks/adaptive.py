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

import copy
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from pipeline.attacks.filter_mirror import attitude_std_t, noise_terms_t
from pipeline.attacks.gradient import LossFn, pgd
from pipeline.shap import ExactShap
from pipeline.defense.kalman import MotionFilter
from pipeline.defense.noise import NoiseModel
from pipeline.geometry.rotations import rotvec_t, sixd_to_matrix_t

DEFAULT_STEPS = 20


class DifferentiableChain(Protocol):
    """What the adaptive attack differentiates through (`PerFrameChain`, `FusedBurstChain`).

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


def adaptive_pgd(chain: DifferentiableChain, x: Tensor, y: Tensor, eps: float, loss_fn: LossFn, lam: float, *,
                 steps: int = DEFAULT_STEPS, step_size: float | None = None, random_start: bool = True,
                 generator: torch.Generator | None = None) -> Tensor:
    """L-inf PGD (random start, `steps` signed steps of `step_size`, default 2.5 eps / steps) on
    `loss_fn(pose, y) - lam * mean(logit)` through `chain`; returns float images in [0, 1]
    within eps of `x` (store them with `pipeline.attacks.gradient.quantize`, as every attack).

    `x` (B, 3, H, W) in [0, 1], `y` (B, 9) labels [m, 6-D]; for a temporal chain the batch is one burst.
    """
    return pgd(chain, x, y, eps, adaptive_objective(loss_fn, lam), steps=steps, step_size=step_size,
               random_start=random_start, generator=generator)


# ----------------------------------------------------------------------------- the fused (temporal) chain
@dataclass(frozen=True)
class BurstPrior:
    """What the motion filter predicts for each of the K frames of a burst when it coasts on the
    chaser's commands through the burst (what the defense does with flagged frames); constants of
    the attack. Frames of pipeline/geometry/trajectories.py: world frame centred on the target."""

    R_cam: np.ndarray            # (K, 3, 3) camera -> world
    position: np.ndarray         # (K, 3) predicted rel (target relative to the chaser, world axes, m)
    position_cov: np.ndarray     # (K, 3, 3) covariance of that prediction (m^2)
    attitude: np.ndarray         # (K, 3, 3) predicted target -> world rotation
    attitude_cov: np.ndarray     # (K, 3, 3) covariance of the attitude error state (rad^2)


def burst_prior(motion: MotionFilter, R_cam: np.ndarray, u: np.ndarray) -> BurstPrior:
    """The filter's predictions over a burst: a copy of `motion` (started, in the state the clean
    frames before the burst left it) coasts on the commanded displacements `u` (K, 3) (world, m)
    with the camera attitudes `R_cam` (K, 3, 3); the filter itself is left as it was."""
    f = copy.deepcopy(motion)
    out: dict[str, list[np.ndarray]] = {"position": [], "position_cov": [], "attitude": [], "attitude_cov": []}
    for k in range(len(R_cam)):
        check = f.check(np.array([0.0, 0.0, 1.0]), R_cam[k], u[k])   # the measurement is irrelevant: it coasts
        out["position"].append(check.predicted)
        out["position_cov"].append(f.pos.P[:3, :3].copy())
        out["attitude"].append(f.attitude)
        out["attitude_cov"].append(f.att.P[:3, :3].copy())
        f.coast()
    return BurstPrior(np.asarray(R_cam, np.float64), *(np.stack(v) for v in out.values()))


class FusedBurstChain(nn.Module):
    """The attacker's differentiable copy of the defended chain over one burst (pipeline.evaluation.robustness).

    The fused chain (pipeline.defense.fusion, fusion "or": LSTM flag OR motion gate) on one burst of K
    frames in time order, differentiable: images (K, 3, H, W) -> (pose (K, 9), score (K,)).

    score = softplus(LSTM logit - logit(threshold)) + softplus((NIS_position - gate) / gate)
            + softplus((NIS_attitude - gate) / gate)
    per frame: each margin is > 0 where that check flags the frame, so descending the score evades
    both checks. The NIS are those of pipeline.defense.kalman.MotionFilter.check (noise model's bias and
    range-dependent covariance, rotated into world axes) against `prior`, the filter coasting on
    the commands through the burst. With `prior` None (the filter has not started: the defense
    trusts no estimate yet) only the LSTM margin counts.
    """

    temporal = True

    def __init__(self, chain: PerFrameChain, threshold: float, noise: NoiseModel, gate: float, prior: BurstPrior | None):
        super().__init__()
        if not 0 < threshold < 1 or not gate > 0:
            raise ValueError(f"threshold must be in (0, 1) and gate > 0, got {threshold} and {gate}")
        self.chain, self.noise, self.gate, self.prior = chain, noise, float(gate), prior
        self.logit_threshold = float(np.log(threshold / (1 - threshold)))
        self.eval()

    def forward(self, images: Tensor) -> tuple[Tensor, Tensor]:
        pose, logit = self.chain(images)
        score = F.softplus(logit - self.logit_threshold)
        if self.prior is not None:
            nis_p, nis_a = self.nis(pose)
            score = score + F.softplus((nis_p - self.gate) / self.gate) + F.softplus((nis_a - self.gate) / self.gate)
        return pose, score

    def nis(self, pose: Tensor) -> tuple[Tensor, Tensor]:
        """(K,) NIS of position and attitude of the estimates `pose` (K, 9) against the prior."""
        pr, n = self.prior, self.noise
        as_t = lambda a: torch.as_tensor(np.asarray(a), dtype=pose.dtype)  # noqa: E731
        t = pose[:, :3]
        rng = as_t(pr.position).norm(dim=1, keepdim=True)     # the noise model at the predicted range, as the filter
        bias, std = noise_terms_t(n, rng)
        R_cam = as_t(pr.R_cam)
        y = torch.einsum("kij,kj->ki", R_cam, t - bias) - as_t(pr.position)
        S = as_t(pr.position_cov) + R_cam @ torch.diag_embed(std ** 2) @ R_cam.transpose(1, 2)
        nis_p = (y * torch.linalg.solve(S, y.unsqueeze(2)).squeeze(2)).sum(1)
        dth = rotvec_t(as_t(pr.attitude).transpose(1, 2) @ R_cam @ sixd_to_matrix_t(pose[:, 3:]))
        att_std = attitude_std_t(n, rng)
        S_a = as_t(pr.attitude_cov) + torch.eye(3, dtype=pose.dtype) * (att_std ** 2).unsqueeze(2)
        nis_a = (dth * torch.linalg.solve(S_a, dth.unsqueeze(2)).squeeze(2)).sum(1)
        return nis_p, nis_a
