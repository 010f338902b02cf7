"""Learning-rate schedules and the exponential moving average (EMA) of the weights, per optimiser step.

Schedules (`SCHEDULES`), as multipliers of each parameter group's initial learning rate, indexed by the
optimiser step i = 0 .. total - 1 (the rate step i uses):
- cyclic: CyclicLR "triangular2" between lr_base and lr_max, a half cycle of `cycle` steps, the peak
  halving every cycle (the paper's schedule; it never goes below lr_base);
- cosine: a linear warm-up from lr_base to lr_max over `warmup` steps, then a half cosine from lr_max
  down to the floor lr_min, reached exactly at the last step (and held after it).
"""

from __future__ import annotations

import copy
import math

import torch
from torch import nn

SCHEDULES = ("cyclic", "cosine")


def cosine_factor(step: int, total: int, warmup: int, lr_base: float, lr_max: float, lr_min: float) -> float:
    """The cosine schedule's learning rate at optimiser step `step`, divided by lr_max (see the module doc)."""
    if step < warmup:
        return (lr_base + (lr_max - lr_base) * step / warmup) / lr_max
    span = max(total - 1 - warmup, 1)
    progress = min((step - warmup) / span, 1.0)
    return (lr_min + 0.5 * (lr_max - lr_min) * (1 + math.cos(math.pi * progress))) / lr_max


def make_scheduler(
    opt: torch.optim.Optimizer,
    schedule: str,
    total: int,
    *,
    lr_base: float,
    lr_max: float,
    lr_min: float,
    cycle: int,
    warmup: int,
) -> torch.optim.lr_scheduler.LRScheduler:
    """The scheduler of `schedule` for `opt`, whose groups were created with lr = f * lr_base (any f per
    group: the schedule scales every group alike); `total` steps in all, `cycle` and `warmup` in steps."""
    if schedule == "cyclic":
        return torch.optim.lr_scheduler.CyclicLR(
            opt,
            base_lr=[g["lr"] for g in opt.param_groups],
            max_lr=[g["lr"] * lr_max / lr_base for g in opt.param_groups],
            mode="triangular2",
            step_size_up=max(1, cycle),
            cycle_momentum=False,
        )
    if schedule != "cosine":
        raise ValueError(f"unknown learning-rate schedule {schedule!r}; choose one of {', '.join(SCHEDULES)}")
    for g in opt.param_groups:  # LambdaLR multiplies the initial rate: start from lr_max's
        g["lr"] *= lr_max / lr_base

    def factor(i: int) -> float:
        return cosine_factor(i, total, warmup, lr_base, lr_max, lr_min)

    return torch.optim.lr_scheduler.LambdaLR(opt, factor)


class WeightEMA:
    """Exponential moving average of a model's parameters and floating-point buffers (BatchNorm running
    statistics): after optimiser step n, avg <- d avg + (1 - d) w with d = min(decay, (1 + n) / (10 + n)),
    the usual warm-up, so the first average is not dominated by the initial weights. Integer buffers
    (BatchNorm's step counter) are copied. `model` is the averaged copy (eval mode, no gradients)."""

    def __init__(self, model: nn.Module, decay: float):
        if not 0 < decay < 1:
            raise ValueError(f"EMA decay must be in (0, 1), got {decay}")
        self.decay, self.updates = float(decay), 0
        self.model = copy.deepcopy(model).eval()
        for p in self.model.parameters():
            p.requires_grad_(False)

    @torch.no_grad()
    def update(self, model: nn.Module) -> None:
        """Fold the current weights of `model` (same architecture) into the average."""
        self.updates += 1
        d = min(self.decay, (1 + self.updates) / (10 + self.updates))
        for avg, new in zip(self.model.state_dict().values(), model.state_dict().values()):
            if avg.dtype.is_floating_point:
                avg.mul_(d).add_(new.detach(), alpha=1 - d)
            else:
                avg.copy_(new)
