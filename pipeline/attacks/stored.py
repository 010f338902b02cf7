"""The interface of the per-frame pose attacks of the strongest-attack suite (pipeline/attacks/apgd.py,
square.py, the PGD baseline in strongest.py): every candidate image is stored as 8 bits before it is scored.

An attack is `attack(model, x, y, eps, objective, *, generator, los, **options) -> Found`: clean images x
(B, 3, H, W) on the 8-bit grid (uint8 / 255, pixel values in [0, 1]), true poses y (B, 9) (camera-frame
position in m, 6-D rotation), an L-inf budget eps in (0, 1], a per-sample objective
(pipeline/attacks/objectives.py) to ascend, a CPU `torch.Generator` (every random draw is made on the CPU
and moved, so CPU and CUDA runs start alike) and optional lines of sight los (B, 3). It returns, per
sample, the stored image with the largest objective it found and that value.

Budget in grey levels: the float iterate stays within eps of x; storing it (`gradient.quantize`) rounds
each pixel's perturbation to the nearest level (never to 0), so a stored image is within
`levels(eps)` = max(1, round(255 eps)) grey levels of the clean 8-bit image (eps 0.01 -> 3 levels, 0.05 ->
13, 0.1 -> 26 (25.5 rounds half to even), 0.2 -> 51): up to half a level (0.002) past eps, as every
stored attack of this project (the PGD-50 table included).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from pipeline.attacks.gradient import check_eps, quantize
from pipeline.attacks.objectives import Objective

Forward = Callable[[Tensor], Tensor]


@dataclass(frozen=True)
class Found:
    """What an attack found per sample: stored images uint8 (B, 3, H, W) and their objective values (B,)."""

    images: Tensor
    values: Tensor

    def best(self, other: "Found") -> "Found":
        """Per sample, whichever of self and other has the larger value (self on ties)."""
        take = other.values > self.values
        return Found(
            torch.where(take.view(-1, 1, 1, 1), other.images, self.images), torch.where(take, other.values, self.values)
        )


def levels(eps: float) -> int:
    """Grey levels of an eps perturbation as stored: max(1, round(255 eps)) (module doc)."""
    return max(1, int(round(check_eps(eps) * 255)))


def check_attack_inputs(x: Tensor, y: Tensor, eps: float, los: Tensor | None = None) -> float:
    """eps, after one-line ValueErrors for: eps outside (0, 1]; x not (B, 3, H, W), not finite, outside
    [0, 1] or off the 8-bit grid; y not (B, 9) or not finite; los not (B, 3), not finite or of zero length."""
    eps = check_eps(eps)
    if x.ndim != 4 or x.shape[1] != 3:
        raise ValueError(f"attack images must be (B, 3, H, W), got {tuple(x.shape)}")
    if not bool(torch.isfinite(x).all()) or x.min() < 0 or x.max() > 1:
        raise ValueError("attack images must be finite pixel values in [0, 1]")
    if not torch.equal(torch.round(x * 255) / 255, x):
        raise ValueError("attack images must be on the 8-bit grid (uint8 / 255)")
    if y.shape != (len(x), 9) or not bool(torch.isfinite(y).all()):
        raise ValueError(f"attack targets must be finite (B, 9) = ({len(x)}, 9), got {tuple(y.shape)}")
    if los is not None and (
        los.shape != (len(x), 3)
        or not bool(torch.isfinite(los).all())
        or bool((torch.linalg.vector_norm(los, dim=1) == 0).any())
    ):
        raise ValueError(f"lines of sight must be finite non-zero (B, 3) = ({len(x)}, 3), got {tuple(los.shape)}")
    return eps


def evaluate(
    forward: Forward, z: Tensor, x: Tensor, y: Tensor, objective: Objective, los: Tensor | None, grad: bool = False
) -> tuple[Tensor, Tensor, Tensor | None]:
    """(stored image uint8, objective (B,), gradient of the objective's sum with respect to the stored image
    (B, 3, H, W), or None without `grad`) of the iterate z: the gradient at the stored point is the
    ascent direction for z (the rounding passed straight through)."""
    u8 = quantize(z, x)
    xs = u8.to(x.dtype) / 255.0
    if not grad:
        with torch.no_grad():
            return u8, objective(forward(xs), y, los).detach(), None
    xs.requires_grad_(True)
    with torch.enable_grad():
        value = objective(forward(xs), y, los)
        (g,) = torch.autograd.grad(value.sum(), xs)
    return u8, value.detach(), g
