"""Start points of the iterative attacks, inside the L-inf eps ball around clean images x (B, 3, H, W) on the
8-bit grid, pixel values in [0, 1]. Every draw is made on the CPU `generator` and moved to x's device, so a
CPU and a CUDA run start at the same point.

- random: uniform in the ball (clipped to [0, 1]), as PGD's random start;
- lift: for a network with a black-level clamp max(x - t, 0) in front (pipeline/pose/model.py), a pixel
  darker than t reaches the network as 0 with zero input gradient, so a random start leaves most of a
  black background where no gradient step can move it. The lifting start puts every channel value below
  t at the lowest grey level above t when eps reaches it (at x + eps when it does not), and draws the
  others uniformly in the ball as `random` does. Adversarial training (issue 37, item 3) can start its
  inner maximisation here too.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from pipeline.attacks.gradient import check_eps, project

STARTS = ("random", "lift")


def random_start(x: Tensor, eps: float, generator: torch.Generator | None = None) -> Tensor:
    """A uniform random point of the eps ball around x, clipped to [0, 1] ((B, 3, H, W) float)."""
    eps = check_eps(eps)
    noise = torch.rand(x.shape, generator=generator, dtype=x.dtype).to(x.device)
    return project(x + (2 * noise - 1) * eps, x, eps)


def lift_level(black_level: float) -> float:
    """The lowest 8-bit value strictly above the clamp threshold t (pixel units): floor(255 t + 1) / 255."""
    if not 0 < black_level < 1:
        raise ValueError(f"black level must be in (0, 1) (pixel units), got {black_level}")
    return math.floor(255 * black_level + 1) / 255


def lifting_start(x: Tensor, eps: float, black_level: float, generator: torch.Generator | None = None) -> Tensor:
    """The background-lifting start (module doc): values below the clamp threshold `black_level` lifted to
    the lowest grey level above it (or by eps where that is farther), the rest uniform in the ball."""
    start = random_start(x, eps, generator)
    lifted = torch.minimum(torch.full_like(x, lift_level(black_level)), x + check_eps(eps))
    return torch.where(x < black_level, lifted, start)


def get_start(
    kind: str, x: Tensor, eps: float, black_level: float = 0.0, generator: torch.Generator | None = None
) -> Tensor:
    """The start `kind` of STARTS; `lift` on a network without a clamp (`black_level` 0) is `random`."""
    if kind not in STARTS:
        raise ValueError(f"unknown attack start {kind!r}; choose one of {', '.join(STARTS)}")
    if kind == "lift" and black_level > 0:
        return lifting_start(x, eps, black_level, generator)
    return random_start(x, eps, generator)
