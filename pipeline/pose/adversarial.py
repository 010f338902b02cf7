"""PGD-k adversarial training of the pose regressor (Madry et al. 2018, for regression).

Each training batch is replaced (its first `fraction` of images) by PGD-k examples against the model being
trained: `steps` signed-gradient steps of 2.5 eps / k from a random start in the L-inf ball (the
`pipeline.attacks.gradient.pgd` attack, model in eval mode), on an inner loss weighted toward position,
since the harm an attacker seeks is a position error:

    inner = w exp(-2 s_p) ||p - p_gt|| + (1 - w) exp(-2 s_r) ||r - r_gt||,   w = position_weight,

with the training loss's current learned weights s_p, s_r (detached), so each term is in units of its own
typical error. The budget eps ramps linearly from 0 to `eps` over the first `ramp_epochs` epochs. The
training loss then fits the whole batch, or with `attacked_rotation` off only the position of its attacked
images (their rotation term is left out: the rotation is fitted on the clean share of each batch).

Catastrophic overfitting guard: every epoch, `validate` attacks a fixed seeded subset of `val_frames`
validation images with a stronger PGD (`val_steps` steps, full budget, position-only loss, stored as
8 bits), so the checkpoint kept is chosen on clean + attacked validation error (pipeline/pose/train.py).
Images are float (B, 3, H, W) in [0, 1]; eps in the same pixel units.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor, nn

from pipeline.attacks.gradient import attack_loss, check_eps, pgd, quantize
from pipeline.pose.loss import PoseLoss


@dataclass(frozen=True)
class AdversarialConfig:
    """eps: L-inf budget in [0, 1] pixel units (reached after `ramp_epochs` epochs); steps: PGD-k steps;
    position_weight: w of the inner loss; fraction: share of each batch replaced by attacked images;
    attacked_rotation: fit the rotation of attacked images too (off: their position only);
    val_steps, val_frames: the per-epoch PGD check on validation images."""

    eps: float = 0.05
    steps: int = 2
    ramp_epochs: float = 2.0
    position_weight: float = 0.8
    fraction: float = 1.0
    attacked_rotation: bool = True
    val_steps: int = 10
    val_frames: int = 64

    def __post_init__(self) -> None:
        check_eps(self.eps)
        if self.steps < 1 or self.val_steps < 1 or self.val_frames < 1:
            raise ValueError(f"steps, val_steps and val_frames must be >= 1, got {self.steps}, {self.val_steps}, "
                             f"{self.val_frames}")
        if self.ramp_epochs < 0 or not 0 <= self.position_weight <= 1 or not 0 < self.fraction <= 1:
            raise ValueError(f"need ramp_epochs >= 0, position_weight in [0, 1] and fraction in (0, 1], got "
                             f"{self.ramp_epochs}, {self.position_weight}, {self.fraction}")
        if not self.attacked_rotation and self.fraction == 1:
            raise ValueError("attacked_rotation off needs fraction < 1: the rotation is fitted on the clean share")


class Adversary:
    """The attacker of adversarial training for one run: `perturb` a training batch at optimiser step n,
    `validate` the network on the validation subset. `steps_per_epoch` sets the eps ramp; `seed` the
    random starts and the validation subset."""

    def __init__(self, cfg: AdversarialConfig, loss: PoseLoss, steps_per_epoch: int, seed: int):
        self.cfg, self.loss = cfg, loss
        self.ramp_steps = cfg.ramp_epochs * steps_per_epoch
        self.generator = torch.Generator().manual_seed(seed)
        self.seed = seed

    def eps_at(self, step: int) -> float:
        """The budget at optimiser step `step` (0-based): eps * (step + 1) / ramp steps, capped at eps."""
        if self.ramp_steps <= 0:
            return self.cfg.eps
        return self.cfg.eps * min(1.0, (step + 1) / self.ramp_steps)

    def inner_loss(self, pred: Tensor, target: Tensor) -> Tensor:
        """The position-weighted loss PGD-k ascends (see the module doc)."""
        pos, rot = self.loss.parts(pred, target)
        w = self.cfg.position_weight
        s_p, s_r = self.loss.s_p.detach(), self.loss.s_r.detach()
        return w * torch.exp(-2 * s_p) * pos + (1 - w) * torch.exp(-2 * s_r) * rot

    def attacked(self, batch: int) -> int:
        """How many images of a batch of `batch` are attacked (the first ones): at least one."""
        return max(1, round(self.cfg.fraction * batch))

    def skip_rotation(self, batch: int) -> int:
        """Rows at the start of a batch left out of the training loss's rotation term (PoseLoss)."""
        return 0 if self.cfg.attacked_rotation else min(self.attacked(batch), batch - 1)

    def perturb(self, model: nn.Module, x: Tensor, y: Tensor, step: int) -> Tensor:
        """The batch with its first `fraction` of images replaced by PGD-k examples at eps_at(step)."""
        n = self.attacked(len(x))
        x_adv = pgd(model, x[:n], y[:n], self.eps_at(step), self.inner_loss, steps=self.cfg.steps,
                    generator=self.generator)
        return x_adv if n == len(x) else torch.cat([x_adv, x[n:]])

    def validate(self, model: nn.Module, val_set: torch.utils.data.Dataset,
                 device: torch.device | str = "cpu", batch_size: int = 64) -> tuple[np.ndarray, np.ndarray]:
        """(predictions (M, 9), targets (M, 9)) of `model` on the fixed subset of M = min(val_frames, N)
        validation images under PGD-`val_steps` at the full eps on the position loss, stored as 8 bits.
        The random start is re-seeded each call, so every epoch faces the same attack."""
        rng = np.random.default_rng(self.seed)
        rows = np.sort(rng.permutation(len(val_set))[:self.cfg.val_frames])
        position = attack_loss("position", self.loss)
        gen = torch.Generator().manual_seed(self.seed)
        preds, targets = [], []
        for lo in range(0, len(rows), batch_size):
            items = [val_set[int(i)] for i in rows[lo:lo + batch_size]]
            x = torch.stack([im for im, _ in items]).permute(0, 3, 1, 2).float().div(255.0).to(device)
            y = torch.stack([t for _, t in items]).to(device)
            x_adv = pgd(model, x, y, self.cfg.eps, position, steps=self.cfg.val_steps, generator=gen)
            stored = quantize(x_adv, x).float() / 255.0
            with torch.no_grad():
                was = model.training
                model.eval()
                preds.append(model(stored).float().cpu())
                model.train(was)
            targets.append(y.cpu())
        return torch.cat(preds).numpy(), torch.cat(targets).numpy()
