"""Square attack, L-inf (Andriushchenko et al. 2020, "Square Attack: a query-efficient black-box adversarial
attack via random search"), ascending a per-sample pose objective (pipeline/attacks/objectives.py) in the
interface of pipeline/attacks/stored.py: gradient-free, so it sees through masked or obfuscated gradients
(the black-level clamp's zero gradient below its threshold) and serves as the suite's gradient-masking check.

Start: vertical stripes x + eps * (+-1 per sample, channel and column). Each query draws, per sample, a
square window of side s at a random place and a random sign per channel, sets the window to x + sign eps
(clipped to [0, 1]) and keeps the candidate when its stored image has a larger objective. The window's
share p of the image starts at p_init and halves on the published schedule (queries 10, 50, 200, 500,
1000, 2000, 4000, 6000, 8000 of 10,000, rescaled to `queries`); s = round(sqrt(p H W)), in [1, min(H, W)].
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from pipeline.attacks.gradient import _eval_mode, project
from pipeline.attacks.objectives import Objective
from pipeline.attacks.stored import Found, check_attack_inputs, evaluate

HALVINGS = (10, 50, 200, 500, 1000, 2000, 4000, 6000, 8000)  # of 10,000 queries


def window_share(p_init: float, query: int, queries: int) -> float:
    """The share p of the image a window covers at 0-based `query` of `queries` (module doc)."""
    at = int(query / queries * 10000)
    return p_init / 2 ** sum(at > h for h in HALVINGS)


def _signs(shape: tuple[int, ...], generator: torch.Generator | None, like: Tensor) -> Tensor:
    """Random +-1 of `shape`, drawn on the CPU and moved to like's device and dtype."""
    return (torch.randint(0, 2, shape, generator=generator) * 2 - 1).to(like.device, like.dtype)


def square(
    model: nn.Module,
    x: Tensor,
    y: Tensor,
    eps: float,
    objective: Objective,
    *,
    generator: torch.Generator | None = None,
    los: Tensor | None = None,
    queries: int = 1000,
    p_init: float = 0.8,
) -> Found:
    """Square attack with `queries` forward passes ascending `objective` per sample within the L-inf ball eps
    of the clean x (B, 3, H, W, 8-bit grid, [0, 1]); y the (B, 9) true poses (m, 6-D). Returns the best stored
    image per sample and its value. Model in eval mode during the attack (its mode restored)."""
    eps = check_attack_inputs(x, y, eps, los)
    if int(queries) < 1 or not 0 < p_init <= 1:
        raise ValueError(f"square attack needs queries >= 1 and p_init in (0, 1], got {queries}, {p_init}")
    x = x.detach()
    b, c, h, w = x.shape
    rows = torch.arange(h, device=x.device).view(1, 1, h, 1)
    cols = torch.arange(w, device=x.device).view(1, 1, 1, w)
    with _eval_mode(model):
        z = project(x + eps * _signs((b, c, 1, w), generator, x), x, eps)
        u8, value, _ = evaluate(model, z, x, y, objective, los)
        for q in range(int(queries)):
            s = min(max(int(round(math.sqrt(window_share(p_init, q, int(queries)) * h * w))), 1), h, w)
            top = torch.randint(0, h - s + 1, (b, 1, 1, 1), generator=generator).to(x.device)
            left = torch.randint(0, w - s + 1, (b, 1, 1, 1), generator=generator).to(x.device)
            window = (rows >= top) & (rows < top + s) & (cols >= left) & (cols < left + s)
            candidate = torch.where(window, project(x + eps * _signs((b, c, 1, 1), generator, x), x, eps), z)
            cu8, cvalue, _ = evaluate(model, candidate, x, y, objective, los)
            better = cvalue > value
            z = torch.where(better.view(-1, 1, 1, 1), candidate, z)
            u8 = torch.where(better.view(-1, 1, 1, 1), cu8, u8)
            value = torch.where(better, cvalue, value)
    return Found(u8, value)
