"""PGD-k adversarial training of the pose regressor (Madry et al. 2018, for regression).

Each training batch is replaced (its first `fraction` of images) by PGD-k examples against the model being
trained: `steps` signed-gradient steps of 2.5 eps / k from a start in the L-inf ball (model in eval mode), on
one of two inner objectives:

- `objectives` empty (the default): an inner loss weighted toward position, since the harm an attacker
  seeks is a position error:

      inner = w exp(-2 s_p) ||p - p_gt|| + (1 - w) exp(-2 s_r) ||r - r_gt||,   w = position_weight,

  with the training loss's current learned weights s_p, s_r (detached), so each term is in units of its own
  typical error;
- `objectives` named: the strongest-attack suite's per-sample objectives (pipeline/attacks/objectives.py:
  position and range in m, geodesic attitude in degrees), the attacked row i ascending objectives[i mod n]
  within that objective's budget (`objective_eps`, default eps for every one; each ramps as eps does). A
  signed step ignores the objective's scale, so position and attitude need no common unit.

The start (`start`, pipeline/attacks/starts.py) is uniform in the ball (`random`) or, for a network with a
black-level clamp, lifts every channel value under the clamp to the lowest grey level above it (`lift`);
with `bpda` the input gradient passes the clamp as the identity (pipeline/attacks/bpda.py). Past the clamp
(eps above the model's black level) a random start and the clamp's true gradient leave the black background
where no step can move it: the attack would be masked, so such a budget is refused without both.

The budget eps ramps linearly from 0 to `eps` over the first `ramp_epochs` epochs. The training loss then fits
the whole batch, or with `attacked_rotation` off only the position of its attacked images (their rotation term
is left out: the rotation is fitted on the clean share of each batch; an attitude objective needs it on).

TRADES-style (Zhang et al. 2019, for regression), with `trades` = beta > 0: the attacked rows keep their clean
images too. The inner maximisation ascends the shift of the estimate from the clean estimate f(x) (the same
objectives, or inner loss, with f(x) in place of the truth), and the training loss (`batch`, PoseLoss
`consistency`) fits the clean batch plus beta times the consistency of the attacked rows with their clean ones:

    L(f(x), y) + beta [exp(-2 s_p) mean ||p' - p|| + exp(-2 s_r) mean ||r' - r||],   (p', r') = f(x'),

the learned weights held fixed in the second term, so the clean fit is what the network is trained on and the
attack only asks it to answer alike within the ball.

Catastrophic overfitting guard: every epoch, `validate` attacks a fixed seeded subset of `val_frames`
validation images with a stronger PGD (`val_steps` steps, full budgets, the training attack's start and
gradient; the position loss without `objectives`, else the objectives cycled over the rows), stored as
8 bits, so the checkpoint kept is chosen on clean + attacked validation error (pipeline/pose/train.py:
`selection_error`). Images are float (B, 3, H, W) in [0, 1]; eps in the same pixel units.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor, nn

from pipeline.attacks.bpda import black_level, bpda_forward
from pipeline.attacks.gradient import (
    LossFn,
    _check_steps,
    _eval_mode,
    _input_grad,
    attack_loss,
    check_eps,
    project,
    quantize,
)
from pipeline.attacks.objectives import get_objective
from pipeline.attacks.starts import STARTS, get_start
from pipeline.pose.loss import PoseLoss
from pipeline.pose.metrics import pose_errors, speed_score

POSITION_OBJECTIVES = ("position", "range_far", "range_near", "lateral")


@dataclass(frozen=True)
class AdversarialConfig:
    """eps: L-inf budget in [0, 1] pixel units (reached after `ramp_epochs` epochs); steps: PGD-k steps;
    position_weight: w of the inner loss (without `objectives`); fraction: share of each batch replaced by
    attacked images; attacked_rotation: fit the rotation of attacked images too (off: their position only);
    val_steps, val_frames: the per-epoch PGD check on validation images; objectives: the suite's objectives
    cycled over the attacked rows (empty: the inner loss); start: random | lift; bpda: the gradient passes
    the black-level clamp as the identity; trades: beta of the TRADES-style loss (0: off, module doc);
    objective_eps: each objective's budget, in (0, eps] (empty: eps for every one)."""

    eps: float = 0.05
    steps: int = 2
    ramp_epochs: float = 2.0
    position_weight: float = 0.8
    fraction: float = 1.0
    attacked_rotation: bool = True
    val_steps: int = 10
    val_frames: int = 64
    objectives: tuple[str, ...] = ()
    start: str = "random"
    bpda: bool = False
    trades: float = 0.0
    objective_eps: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        check_eps(self.eps)
        if self.objective_eps and (
            len(self.objective_eps) != len(self.objectives) or not all(0 < e <= self.eps for e in self.objective_eps)
        ):
            raise ValueError(
                f"objective_eps must give each of the {len(self.objectives)} objectives a budget in "
                f"(0, eps = {self.eps:g}], got {list(self.objective_eps)}"
            )
        if not self.trades >= 0:
            raise ValueError(f"trades (beta) must be >= 0, got {self.trades}")
        if self.steps < 1 or self.val_steps < 1 or self.val_frames < 1:
            raise ValueError(
                f"steps, val_steps and val_frames must be >= 1, got {self.steps}, {self.val_steps}, {self.val_frames}"
            )
        if self.ramp_epochs < 0 or not 0 <= self.position_weight <= 1 or not 0 < self.fraction <= 1:
            raise ValueError(
                f"need ramp_epochs >= 0, position_weight in [0, 1] and fraction in (0, 1], got "
                f"{self.ramp_epochs}, {self.position_weight}, {self.fraction}"
            )
        if not self.attacked_rotation and self.fraction == 1:
            raise ValueError("attacked_rotation off needs fraction < 1: the rotation is fitted on the clean share")
        for name in self.objectives:
            get_objective(name)
        if not self.attacked_rotation and any(o not in POSITION_OBJECTIVES for o in self.objectives):
            raise ValueError("an attitude objective needs attacked_rotation on (the attacked images' rotation fitted)")
        if self.start not in STARTS:
            raise ValueError(f"unknown start {self.start!r}; choose one of {', '.join(STARTS)}")

    def unmasked(self) -> bool:
        """Whether the attack reaches past a black-level clamp: the lifting start and BPDA both on."""
        return self.start == "lift" and self.bpda


class Adversary:
    """The attacker of adversarial training for one run: `perturb` a training batch at optimiser step n,
    `validate` the network on the validation subset. `steps_per_epoch` sets the eps ramp; `seed` the
    random starts and the validation subset."""

    def __init__(self, cfg: AdversarialConfig, loss: PoseLoss, steps_per_epoch: int, seed: int):
        self.cfg, self.loss = cfg, loss
        self.ramp_steps = cfg.ramp_epochs * steps_per_epoch
        self.generator = torch.Generator().manual_seed(seed)
        self.seed = seed

    def ramp(self, step: int) -> float:
        """The share of each budget reached at optimiser step `step` (0-based): (step + 1) / ramp steps, capped at 1."""
        return 1.0 if self.ramp_steps <= 0 else min(1.0, (step + 1) / self.ramp_steps)

    def inner_loss(self, pred: Tensor, target: Tensor) -> Tensor:
        """The position-weighted loss PGD-k ascends without `objectives` (see the module doc)."""
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

    def attack(
        self,
        model: nn.Module,
        x: Tensor,
        y: Tensor,
        eps: float,
        loss_fn: LossFn,
        steps: int,
        generator: torch.Generator,
    ) -> Tensor:
        """PGD-`steps` (steps of 2.5 eps / steps) ascending `loss_fn` from the configured start, with the
        gradient through BPDA when set; the last iterate (B, 3, H, W) in [0, 1]. A ValueError when eps exceeds
        the model's black level and the attack is not `unmasked` (module doc)."""
        eps, level = check_eps(eps), black_level(model)
        if 0 < level < eps and not self.cfg.unmasked():
            raise ValueError(
                f"eps {eps:g} exceeds the black-level clamp {level:g}: a random start and the clamp's "
                f"gradient would mask the attack; set start: lift and bpda: true"
            )
        steps, alpha = _check_steps(steps, None, 2.5, eps)
        x = x.detach()
        with _eval_mode(model), bpda_forward(model) if self.cfg.bpda else contextlib.nullcontext(model) as forward:
            z = get_start(self.cfg.start, x, eps, level, generator)
            for _ in range(steps):
                z = project(z + alpha * _input_grad(forward, z, y, loss_fn).sign(), x, eps)
        return z.detach()

    def attack_rows(
        self,
        model: nn.Module,
        x: Tensor,
        target: Tensor,
        share: float,
        steps: int,
        generator: torch.Generator,
        loss_fn: LossFn,
    ) -> Tensor:
        """PGD-`steps` examples of every row of x: without `objectives` on `loss_fn` at eps x share; with them
        row i on objectives[i mod n] at its budget x share (target (B, 9): the truth, or with trades the clean
        estimate)."""
        if not self.cfg.objectives:
            return self.attack(model, x, target, self.cfg.eps * share, loss_fn, steps, generator)
        out = x.clone()
        budgets = self.cfg.objective_eps or (self.cfg.eps,) * len(self.cfg.objectives)
        for k, (name, budget) in enumerate(zip(self.cfg.objectives, budgets)):
            rows = slice(k, None, len(budgets))
            if len(x[rows]):
                objective = get_objective(name)
                out[rows] = self.attack(
                    model,
                    x[rows],
                    target[rows],
                    budget * share,
                    lambda pred, t, objective=objective: objective(pred, t).sum(),
                    steps,
                    generator,
                )
        return out

    def perturb(self, model: nn.Module, x: Tensor, y: Tensor, step: int) -> Tensor:
        """The batch with its first `fraction` of images replaced by PGD-k examples at the budgets of `step`."""
        n = self.attacked(len(x))
        x_adv = self.attack_rows(model, x[:n], y[:n], self.ramp(step), self.cfg.steps, self.generator, self.inner_loss)
        return x_adv if n == len(x) else torch.cat([x_adv, x[n:]])

    def batch(self, model: nn.Module, x: Tensor, y: Tensor, step: int) -> tuple[Tensor, int, int]:
        """What a training step fits at optimiser step `step`: (inputs, rows at their start left out of the
        rotation term, pairs). Without `trades`: the batch `perturb`ed, pairs 0. With it: the clean batch
        followed by PGD-k examples of its first n = `fraction` rows ascending the shift from their clean
        estimate (module doc), pairs n: the last n inputs are attacked copies of the first n."""
        if not self.cfg.trades:
            return self.perturb(model, x, y, step), self.skip_rotation(len(x)), 0
        n = self.attacked(len(x))
        with torch.no_grad(), _eval_mode(model):
            anchor = model(x[:n]).detach()
        x_adv = self.attack_rows(model, x[:n], anchor, self.ramp(step), self.cfg.steps, self.generator, self.inner_loss)
        return torch.cat([x, x_adv]), 0, n

    def selection_error(self, pred: np.ndarray, target: np.ndarray) -> float:
        """What the attacked validation images add to the checkpoint's score, from their (M, 9) predictions and
        targets: the mean relative position error ||p - p_gt|| / ||p_gt|| (without `objectives`: the harm is a
        position error), else their SPEED score (relative position error + attitude error in radians)."""
        if self.cfg.objectives:
            return speed_score(pred, target)
        return float(np.mean(pose_errors(pred, target)[0] / np.linalg.norm(target[:, :3], axis=1)))

    def validate(
        self,
        model: nn.Module,
        val_set: torch.utils.data.Dataset,
        device: torch.device | str = "cpu",
        batch_size: int = 64,
    ) -> tuple[np.ndarray, np.ndarray]:
        """(predictions (M, 9), targets (M, 9)) of `model` on the fixed subset of M = min(val_frames, N)
        validation images under PGD-`val_steps` at the full budgets (the position loss, or the objectives), stored
        as 8 bits. The random start is re-seeded each call, so every epoch faces the same attack."""
        rng = np.random.default_rng(self.seed)
        rows = np.sort(rng.permutation(len(val_set))[: self.cfg.val_frames])
        position = attack_loss("position", self.loss)
        gen = torch.Generator().manual_seed(self.seed)
        preds, targets = [], []
        for lo in range(0, len(rows), batch_size):
            items = [val_set[int(i)] for i in rows[lo : lo + batch_size]]
            x = torch.stack([im for im, _ in items]).permute(0, 3, 1, 2).float().div(255.0).to(device)
            y = torch.stack([t for _, t in items]).to(device)
            x_adv = self.attack_rows(model, x, y, 1.0, self.cfg.val_steps, gen, position)
            stored = quantize(x_adv, x).float() / 255.0
            with torch.no_grad():
                was = model.training
                model.eval()
                preds.append(model(stored).float().cpu())
                model.train(was)
            targets.append(y.cpu())
        return torch.cat(preds).numpy(), torch.cat(targets).numpy()
