"""The onboard safety chain: image -> pose estimate -> SHAP signature -> attack flag (SPEC 8, 11).

The pose network's GAP features `a` (B, 1000) are computed once and used twice: the affine heads
turn them into the pose (B, 9), and the closed-form DeepSHAP of those heads,
phi[b, j, i] = W[j, i] * (a[b, i] - mean_background[i]), turns them into the (B, 9, 1000)
signature the detector reads. So the chain costs the pose forward plus one broadcast multiply and
the detector's small LSTM over 9 steps. The chain keeps no state between frames: a batch of frames
gives the same result as the frames one at a time.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from pipeline.explain import affine_head, exact_shap


@dataclass(frozen=True)
class ChainOutput:
    """One batch through the chain: pose (B, 9) [m, 6-D], shap (B, 9, D), prob (B,), flag (B,) bool."""

    pose: torch.Tensor
    shap: torch.Tensor
    prob: torch.Tensor
    flag: torch.Tensor


class SafetyChain:
    """Pose model + exact SHAP (head weights, background mean) + detector, in eval mode, no grad.

    `detector` maps SHAP values (B, 9, D) to attack logits (B,); a frame is flagged when
    sigmoid(logit) >= `threshold`.
    """

    def __init__(self, model: nn.Module, weight: np.ndarray | torch.Tensor,
                 background_mean: np.ndarray | torch.Tensor, detector: nn.Module, threshold: float = 0.5):
        self.model = model.eval()
        self.detector = detector.eval()
        self.weight = torch.as_tensor(np.asarray(weight), dtype=torch.float32)
        self.background_mean = torch.as_tensor(np.asarray(background_mean), dtype=torch.float32)
        if self.weight.ndim != 2 or self.background_mean.shape != (self.weight.shape[1],):
            raise ValueError(f"head weight {tuple(self.weight.shape)} and background mean "
                             f"{tuple(self.background_mean.shape)} do not fit (need (9, D) and (D,))")
        self.threshold = float(threshold)

    @classmethod
    def from_model(cls, model: nn.Module, background_mean: np.ndarray | torch.Tensor, detector: nn.Module,
                   threshold: float = 0.5) -> "SafetyChain":
        """Read the head weights from `model` (they must form an affine map, as in PoseNet)."""
        mu = np.asarray(torch.as_tensor(background_mean, dtype=torch.float32))
        head = affine_head(model, n_features=len(mu))
        if head is None:
            raise ValueError("the safety chain needs an affine pose head (exact SHAP); this model's head is not")
        return cls(model, head.weight, mu, detector, threshold)

    @torch.no_grad()
    def __call__(self, images: torch.Tensor) -> ChainOutput:
        """(B, 3, H, W) images in [0, 1] -> ChainOutput; a single (3, H, W) frame is batched."""
        x = images.unsqueeze(0) if images.ndim == 3 else images
        features = self.model.forward_features(x)
        pose = self.model.forward_head(features)
        phi = exact_shap(features, self.weight, self.background_mean)
        prob = torch.sigmoid(self.detector(phi))
        return ChainOutput(pose, phi, prob, prob >= self.threshold)

    @torch.no_grad()
    def pose_only(self, images: torch.Tensor) -> torch.Tensor:
        """The pose forward alone, (B, 9): the baseline the chain's cost is compared with."""
        x = images.unsqueeze(0) if images.ndim == 3 else images
        return self.model(x)
