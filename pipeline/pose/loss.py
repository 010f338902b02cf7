"""Pose loss with learned position/rotation weighting (Kendall et al. 2017).

    L = exp(-2 s_p) * A(||p_i - p_gt_i||) + exp(-2 s_r) * A(||r_i - r_gt_i||) + 2 (s_p + s_r)

p: position in metres, r: 6-D rotation, both as the first 3 and last 6 of the model's 9 outputs;
s_p, s_r: learnable scalars (start at 0). A aggregates the per-sample L2 norms over the batch:
"sum" is the paper's formula; "mean" (our default) makes the loss, and the learned weights,
independent of the batch size (at the optimum exp(-2 s) equals 1 / A, so the weights track the
batch-mean error instead of the batch-sum).
"""

from __future__ import annotations

import torch
from torch import nn


class PoseLoss(nn.Module):
    """The pose loss; `parts` exposes the two unweighted error terms (for attacks)."""

    def __init__(self, reduction: str = "mean"):
        super().__init__()
        if reduction not in ("mean", "sum"):
            raise ValueError(f"reduction must be 'mean' or 'sum', got {reduction!r}")
        self.reduction = reduction
        self.s_p = nn.Parameter(torch.zeros(()))
        self.s_r = nn.Parameter(torch.zeros(()))

    def parts(self, pred: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, 9) prediction and target -> (position term in m, 6-D rotation term), reduced over B."""
        if pred.shape != target.shape or pred.shape[-1] != 9:
            raise ValueError(f"pred and target must both be (B, 9), got {tuple(pred.shape)} and {tuple(target.shape)}")
        pos = torch.linalg.vector_norm(pred[:, :3] - target[:, :3], dim=1)
        rot = torch.linalg.vector_norm(pred[:, 3:] - target[:, 3:], dim=1)
        if self.reduction == "mean":
            return pos.mean(), rot.mean()
        return pos.sum(), rot.sum()

    def consistency(self, pred: torch.Tensor, anchor: torch.Tensor) -> torch.Tensor:
        """How far (B, 9) predictions are from anchors (the same images' clean predictions), in the loss's units:
        exp(-2 s_p) A(||p - p_a||) + exp(-2 s_r) A(||r - r_a||) with the learned weights held fixed (no gradient
        to s_p, s_r): the TRADES-style term of adversarial training (pipeline/pose/adversarial.py)."""
        pos, rot = self.parts(pred, anchor)
        return torch.exp(-2 * self.s_p.detach()) * pos + torch.exp(-2 * self.s_r.detach()) * rot

    def forward(self, pred: torch.Tensor, target: torch.Tensor, skip_rotation: int = 0) -> torch.Tensor:
        """The loss of (B, 9) predictions; `skip_rotation` > 0 leaves the first rows out of the rotation term
        (adversarial training that fits only the position of its attacked images, pipeline/pose/adversarial.py)."""
        pos, rot = self.parts(pred, target)
        if skip_rotation:
            rot = self.parts(pred[skip_rotation:], target[skip_rotation:])[1]
        return torch.exp(-2 * self.s_p) * pos + torch.exp(-2 * self.s_r) * rot + 2 * (self.s_p + self.s_r)
