"""A targeted attack: make the pose network output a chosen camera-frame position (issue 40: realise the integrity
bound's worst fault sequence, frame by frame, in image space).

`toward` is APGD (pipeline/attacks/apgd.py: momentum, step-size checkpoints, best stored iterate, restarts) ascending
`miss`, the negative distance (m) between the estimated and the goal position; every candidate is stored as 8 bits
before it is scored, as in every attack of this project. The goal pose's rotation is not pursued (the integrity bound
shifts positions only; the attack leaves the attitude wherever the position pursuit moves it).
"""

from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor, nn

from pipeline.attacks.apgd import apgd
from pipeline.attacks.objectives import check_pose_pair
from pipeline.attacks.stored import Found


def miss(pred: Tensor, goal: Tensor, los: Tensor | None = None) -> Tensor:
    """-||p - p_goal|| in metres (B,): what `toward` ascends (0 when the estimate sits on the goal position)."""
    check_pose_pair(pred, goal)
    d = pred[:, :3] - goal[:, :3]
    return -torch.sqrt((d * d).sum(1) + torch.finfo(d.dtype).tiny)


def toward(
    model: nn.Module,
    x: Tensor,
    goal: Tensor,
    eps: float,
    *,
    generator: torch.Generator | None = None,
    steps: int = 100,
    restarts: int = 1,
    starts: Sequence[str] = ("random",),
    bpda: bool = False,
) -> Found:
    """The stored image per sample (uint8 (B, 3, H, W)) within the L-inf ball eps of the clean x (B, 3, H, W, 8-bit
    grid, [0, 1]) whose estimated position lies closest to the goal's, and that `miss` (-distance, m); goal (B, 9)
    camera-frame position (m) then a 6-D rotation (only its finiteness is checked). APGD-`steps` with `restarts`
    restarts from `starts` (random | lift); `bpda` passes the black-level clamp as the identity backward."""
    return apgd(
        model, x, goal, eps, miss, generator=generator, steps=steps, restarts=restarts, starts=starts, bpda=bpda
    )
