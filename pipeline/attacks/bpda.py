"""BPDA (Athalye et al. 2018) through the pose network's black-level clamp max(x - t, 0)
(pipeline/pose/model.py `PoseNet.clamp`): the forward pass is the network's own, value for value; the
backward pass treats the clamp as the identity, so a black pixel below t gets the gradient the backbone
sees at its clamped input and an attack learns which dark pixels to lift past t. Used only to choose the
attack's direction; every score comes from the stored image through the true network (the values are
identical anyway: the forward is unchanged).
"""

from __future__ import annotations

import contextlib
from typing import Any, Callable, Iterator

import torch
from torch import Tensor, nn


class _ClampIdentityBackward(torch.autograd.Function):
    """relu(x - t) forward (as PoseNet.clamp computes it), the identity backward."""

    @staticmethod
    def forward(ctx: Any, x: Tensor, level: float) -> Tensor:
        return torch.relu(x - level)

    @staticmethod
    def backward(ctx: Any, grad: Tensor) -> tuple[Tensor, None]:
        return grad, None


def black_level(model: nn.Module) -> float:
    """The model's black-level clamp threshold t (pixel units; 0 for a model without a clamp)."""
    return float(getattr(model, "black_level", 0.0))


@contextlib.contextmanager
def bpda_forward(model: nn.Module, through: Callable[[Tensor], Any] | None = None) -> Iterator[Callable[[Tensor], Any]]:
    """Within the block, a forward `(B, 3, H, W) in [0, 1] -> (B, 9)` equal to `model` whose input gradient
    passes its clamp as the identity; `model` itself when it has no clamp. The model's clamp is switched
    off inside the block (the clamp is applied before it instead) and restored on exit. `through`: a module
    built on `model` (e.g. a chain whose pose network it is: pose and detector logit) forwarded the same way
    instead of `model` alone."""
    level = black_level(model)
    outer = model if through is None else through
    if level <= 0:
        yield outer
        return
    model.black_level = 0.0
    try:
        yield lambda x: outer(_ClampIdentityBackward.apply(x, level))
    finally:
        model.black_level = level
