"""Per-sample attack objectives for the 9-output pose regressor (position 3, m, then the 6-D rotation 6).

Every objective is `objective(pred, target, los=None) -> (B,)`: differentiable in `pred` (B, 9), one value
per sample (an attack ascends their sum and keeps its books per sample). `target` (B, 9) is the true pose
(camera-frame position in metres, OpenCV axes, then the 6-D rotation); `los` (B, 3) is the camera-frame
line of sight the range and lateral objectives split along (any non-zero length; default: the true target
direction t_gt / ||t_gt||).

- position: ||p - p_gt|| (m);
- range_far / range_near: the position error along the line of sight, +(p - p_gt).u (the estimate put
  farther than the truth) and -(p - p_gt).u (nearer), m. Along the line of sight rather than along z:
  the line of sight is the direction a monocular estimate is weakest in (scale and range are one
  unknown), along and across it split the error orthogonally (position^2 = range^2 + lateral^2), and it
  is the split the integrity bound consumes (attacker capacity along and across the line of sight). With
  the camera pointed at the target the two differ by the cosine of the off-boresight angle (< 1%);
- lateral: the norm of the position error across the line of sight (m);
- attitude: the geodesic angle between the Gram-Schmidt rotations of pred and target, in degrees.

The angle is computed as atan2(|v| / 2, (tr(R_pred^T R_gt) - 1) / 2) with v the skew part of R_pred^T R_gt:
the same value as acos((tr - 1) / 2) but accurate near 0 and pi, where acos loses precision and its
derivative is infinite. The angle is a cone at 0 and at pi (not differentiable there): its gradient is
finite everywhere (a tiny constant under the square root), exactly 0 where the skew part is exactly 0
(the same rotation), the analytic one everywhere else.
"""

from __future__ import annotations

from typing import Callable

import torch
from torch import Tensor

from pipeline.geometry.rotations import sixd_to_matrix_t

Objective = Callable[..., Tensor]


def check_pose_pair(pred: Tensor, target: Tensor) -> None:
    """One-line ValueError unless pred and target are both (B, 9)."""
    if pred.ndim != 2 or pred.shape[1] != 9 or pred.shape != target.shape:
        raise ValueError(f"pred and target must both be (B, 9), got {tuple(pred.shape)} and {tuple(target.shape)}")


def line_of_sight(target: Tensor, los: Tensor | None = None) -> Tensor:
    """(B, 3) unit camera-frame lines of sight: `los` normalised, or the true direction t_gt / ||t_gt||."""
    u = target[:, :3] if los is None else los.to(target)
    if u.shape != (len(target), 3):
        raise ValueError(f"line of sight must be (B, 3) = ({len(target)}, 3), got {tuple(u.shape)}")
    return u / torch.linalg.vector_norm(u, dim=1, keepdim=True)


def along_across(delta: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
    """A camera-frame displacement (B, 3) split on unit lines of sight u (B, 3): signed length along u
    (B,) and the norm of the rest (B,), both in the units of delta."""
    along = (delta * u).sum(1)
    across = delta - along.unsqueeze(1) * u
    return along, _norm(across)


def _norm(v: Tensor) -> Tensor:
    """||v|| over the last axis, with gradient 0 (not NaN) at v = 0."""
    return torch.sqrt((v * v).sum(-1) + torch.finfo(v.dtype).tiny)


def geodesic_deg(r6_a: Tensor, r6_b: Tensor) -> Tensor:
    """Angle in degrees (B,) between the rotations of two (B, 6) 6-D vectors (Gram-Schmidt; module doc)."""
    r = sixd_to_matrix_t(r6_a).transpose(1, 2) @ sixd_to_matrix_t(r6_b)
    v = torch.stack([r[:, 2, 1] - r[:, 1, 2], r[:, 0, 2] - r[:, 2, 0], r[:, 1, 0] - r[:, 0, 1]], 1)
    cos = (r.diagonal(dim1=1, dim2=2).sum(1) - 1) / 2
    return torch.rad2deg(torch.atan2(_norm(v) / 2, cos))


def position(pred: Tensor, target: Tensor, los: Tensor | None = None) -> Tensor:
    """||p - p_gt|| in metres (B,)."""
    check_pose_pair(pred, target)
    return _norm(pred[:, :3] - target[:, :3])


def range_far(pred: Tensor, target: Tensor, los: Tensor | None = None) -> Tensor:
    """+(p - p_gt).u in metres (B,): the estimate pushed away along the line of sight u."""
    check_pose_pair(pred, target)
    return along_across(pred[:, :3] - target[:, :3], line_of_sight(target, los))[0]


def range_near(pred: Tensor, target: Tensor, los: Tensor | None = None) -> Tensor:
    """-(p - p_gt).u in metres (B,): the estimate pulled closer along the line of sight u."""
    return -range_far(pred, target, los)


def lateral(pred: Tensor, target: Tensor, los: Tensor | None = None) -> Tensor:
    """Norm of the position error across the line of sight u, metres (B,)."""
    check_pose_pair(pred, target)
    return along_across(pred[:, :3] - target[:, :3], line_of_sight(target, los))[1]


def attitude(pred: Tensor, target: Tensor, los: Tensor | None = None) -> Tensor:
    """Geodesic attitude error in degrees (B,) between the 6-D rotations of pred and target."""
    check_pose_pair(pred, target)
    return geodesic_deg(pred[:, 3:], target[:, 3:])


OBJECTIVES: dict[str, Objective] = {
    "position": position,
    "range_far": range_far,
    "range_near": range_near,
    "lateral": lateral,
    "attitude": attitude,
}


def get_objective(name: str) -> Objective:
    """The objective `name` of OBJECTIVES; an unknown name is a one-line ValueError."""
    if name not in OBJECTIVES:
        raise ValueError(f"unknown attack objective {name!r}; choose one of {', '.join(OBJECTIVES)}")
    return OBJECTIVES[name]
