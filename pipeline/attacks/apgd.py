"""APGD, L-inf (Croce and Hein 2020, "Reliable evaluation of adversarial robustness with an ensemble of
diverse parameter-free attacks"), for a per-sample pose objective (pipeline/attacks/objectives.py), in the
interface of pipeline/attacks/stored.py.

Per restart, from a start point (pipeline/attacks/starts.py) with step size 2 eps per sample:
    z' = P(z + step sign(g));  z <- P(z + a (z' - z) + (1 - a)(z - z_prev)),  a = 0.75 (1 at the first step),
P the projection into the eps ball and [0, 1]. At checkpoints after 22%, then 19%, 16%, ... (never below 6%)
of the steps, a sample's step size halves and its iterate returns to its best point when, since the last
checkpoint, its objective rose in at most rho = 75% of the steps, or when its step size was not halved at
the last checkpoint and its best value has not improved since. The ascent is on the sum of the objective;
the bookkeeping (best point, step size, checkpoints) is per sample. Every iterate is stored as 8 bits and
its objective and gradient are taken at the stored image (the rounding passed straight through), so the
best iterate kept is the best stored image. Restarts cycle through `starts`; the best over restarts is
returned. `bpda`: the gradient passes the network's black-level clamp as the identity (pipeline/attacks/bpda.py).
"""

from __future__ import annotations

import contextlib
from typing import Sequence

import torch
from torch import Tensor, nn

from pipeline.attacks.bpda import black_level, bpda_forward
from pipeline.attacks.gradient import _eval_mode, project
from pipeline.attacks.objectives import Objective
from pipeline.attacks.starts import get_start
from pipeline.attacks.stored import Forward, Found, check_attack_inputs, evaluate

MOMENTUM = 0.75
RHO = 0.75


def checkpoints(steps: int) -> list[int]:
    """The 0-based steps after which APGD checks its step size: gaps of 22%, then 3% less each time,
    never below 6% of `steps` (each gap at least 1 step)."""
    gap, shrink, least = max(int(0.22 * steps), 1), max(int(0.03 * steps), 1), max(int(0.06 * steps), 1)
    out, at = [], gap - 1
    while at < steps:
        out.append(at)
        gap = max(gap - shrink, least)
        at += gap
    return out


def _run(
    forward: Forward, x: Tensor, y: Tensor, eps: float, objective: Objective, z: Tensor, steps: int, los: Tensor | None
) -> Found:
    """One APGD run from the start z (module doc): the best stored image per sample and its value."""
    shape = (-1,) + (1,) * (x.dim() - 1)
    u8, value, grad = evaluate(forward, z, x, y, objective, los, grad=True)
    best = Found(u8, value)
    best_z, best_grad = z, grad
    step = torch.full((len(x),), 2 * eps, dtype=x.dtype, device=x.device)
    rises = torch.zeros(len(x), dtype=torch.long, device=x.device)
    last_best, reduced_last = value, torch.ones(len(x), dtype=torch.bool, device=x.device)
    checks, since = set(checkpoints(steps)), 0
    z_prev = z
    for i in range(steps):
        a = 1.0 if i == 0 else MOMENTUM
        z1 = project(z + step.view(shape) * grad.sign(), x, eps)
        z, z_prev = project(z + a * (z1 - z) + (1 - a) * (z - z_prev), x, eps), z
        u8, new, grad = evaluate(forward, z, x, y, objective, los, grad=True)
        rises += new > value
        value = new
        improved = value > best.values
        best = best.best(Found(u8, value))
        best_z = torch.where(improved.view(shape), z, best_z)
        best_grad = torch.where(improved.view(shape), grad, best_grad)
        since += 1
        if i in checks:
            reduce = (rises <= RHO * since) | (~reduced_last & (last_best >= best.values))
            step = torch.where(reduce, step / 2, step)
            z = torch.where(reduce.view(shape), best_z, z)
            grad = torch.where(reduce.view(shape), best_grad, grad)
            reduced_last, last_best = reduce, best.values
            rises.zero_()
            since = 0
    return best


def apgd(
    model: nn.Module,
    x: Tensor,
    y: Tensor,
    eps: float,
    objective: Objective,
    *,
    generator: torch.Generator | None = None,
    los: Tensor | None = None,
    steps: int = 100,
    restarts: int = 5,
    starts: Sequence[str] = ("random",),
    bpda: bool = False,
) -> Found:
    """APGD-`steps` with `restarts` restarts (start kinds cycled from `starts`: random | lift) ascending
    `objective` per sample within the L-inf ball eps of the clean x (B, 3, H, W, 8-bit grid, [0, 1]); y the
    (B, 9) true poses (m, 6-D). Returns the best stored image per sample over all restarts and its value.
    Model in eval mode during the attack (its mode restored); parameter gradients untouched."""
    eps = check_attack_inputs(x, y, eps, los)
    if int(steps) < 1 or int(restarts) < 1 or not starts:
        raise ValueError(f"APGD needs steps >= 1, restarts >= 1 and a start kind, got {steps}, {restarts}, {starts}")
    x, level = x.detach(), black_level(model)
    with _eval_mode(model), bpda_forward(model) if bpda else contextlib.nullcontext(model) as forward:

        def restart(r: int) -> Found:
            z = get_start(starts[r % len(starts)], x, eps, level, generator)
            return _run(forward, x, y, eps, objective, z, int(steps), los)

        found = restart(0)
        for r in range(1, int(restarts)):
            found = found.best(restart(r))
    return found
