"""White-box L-inf attacks on the 9-output pose regressor (position 3 + 6-D rotation 6).

The common attack libraries (torchattacks, ART) assume a classifier and a cross-entropy loss;
these functions take any differentiable `loss_fn(pred, target) -> scalar` instead and ascend it.
Images are float tensors (B, 3, H, W) in [0, 1]; targets are the (B, 9) labels (metres, 6-D).
Every attack runs the model in eval mode (BatchNorm statistics frozen, no dropout), restores the
model's mode afterwards, never touches its parameters' gradients, and returns images in [0, 1].
"""

from __future__ import annotations

import contextlib
import functools
from typing import Callable, Iterator

import torch
from torch import Tensor, nn

LossFn = Callable[[Tensor, Tensor], Tensor]
AttackFn = Callable[[nn.Module, Tensor, Tensor, float, LossFn], Tensor]

LOSSES = ("full", "position", "rotation")


def attack_loss(kind: str, pose_loss: nn.Module) -> LossFn:
    """The loss an attack ascends, from the training loss `pose_loss` (a `PoseLoss`).

    full: the training loss itself, with its learned weights exp(-2 s_p), exp(-2 s_r);
    position / rotation: only the position or only the 6-D rotation term (`pose_loss.parts`).
    """
    if kind == "full":
        return pose_loss
    if kind == "position":
        return lambda pred, target: pose_loss.parts(pred, target)[0]
    if kind == "rotation":
        return lambda pred, target: pose_loss.parts(pred, target)[1]
    raise ValueError(f"unknown attack loss {kind!r}; choose one of {', '.join(LOSSES)}")


def check_eps(eps: float) -> float:
    """eps is an L-inf budget in [0, 1] pixel units; it must lie in (0, 1]."""
    eps = float(eps)
    if not 0.0 < eps <= 1.0:
        raise ValueError(f"attack eps must be in (0, 1] (pixel values are in [0, 1]), got {eps}")
    return eps


@contextlib.contextmanager
def _eval_mode(model: nn.Module) -> Iterator[None]:
    was_training = model.training
    model.eval()
    try:
        yield
    finally:
        model.train(was_training)


def _input_grad(model: Callable[[Tensor], Tensor], x: Tensor, y: Tensor, loss_fn: LossFn) -> Tensor:
    """d loss_fn(model(x), y) / dx, without accumulating parameter gradients (`model`: a network, or any
    differentiable forward such as pipeline/attacks/bpda.py's)."""
    x = x.detach().requires_grad_(True)
    with torch.enable_grad():
        loss = loss_fn(model(x), y)
        (grad,) = torch.autograd.grad(loss, x)
    return grad


def project(x_adv: Tensor, x: Tensor, eps: float) -> Tensor:
    """Back into the eps ball around x and into [0, 1]."""
    return torch.clamp(torch.minimum(torch.maximum(x_adv, x - eps), x + eps), 0.0, 1.0)


def fgsm(model: nn.Module, x: Tensor, y: Tensor, eps: float, loss_fn: LossFn) -> Tensor:
    """Fast gradient sign method: x' = clip(x + eps * sign(grad_x L(model(x), y)), 0, 1)."""
    eps = check_eps(eps)
    x = x.detach()
    with _eval_mode(model):
        grad = _input_grad(model, x, y, loss_fn)
    return torch.clamp(x + eps * grad.sign(), 0.0, 1.0).detach()


def _check_steps(steps: int, step_size: float | None, default_per_eps: float, eps: float) -> tuple[int, float]:
    """Validated (steps, step size); the default step size is default_per_eps * eps / steps."""
    if int(steps) < 1:
        raise ValueError(f"iterative attacks need steps >= 1, got {steps}")
    alpha = default_per_eps * eps / int(steps) if step_size is None else float(step_size)
    if alpha <= 0:
        raise ValueError(f"attack step size must be positive, got {step_size}")
    return int(steps), alpha


def pgd(
    model: nn.Module,
    x: Tensor,
    y: Tensor,
    eps: float,
    loss_fn: LossFn,
    *,
    steps: int = 10,
    step_size: float | None = None,
    random_start: bool = True,
    generator: torch.Generator | None = None,
) -> Tensor:
    """Projected gradient descent on the loss, L-inf ball (Madry et al. 2018).

    Starts at a uniform random point of the eps ball (or at x), then `steps` signed-gradient steps
    of `step_size` (default 2.5 * eps / steps), each projected back into the ball and [0, 1].
    Returns the last iterate.
    """
    eps = check_eps(eps)
    steps, alpha = _check_steps(steps, step_size, 2.5, eps)
    x = x.detach()
    x_adv = x
    if random_start:
        # drawn on the CPU generator and moved: the same start on every device
        noise = torch.rand(x.shape, generator=generator, dtype=x.dtype).to(x.device)
        x_adv = project(x + (2 * noise - 1) * eps, x, eps)
    with _eval_mode(model):
        for _ in range(steps):
            grad = _input_grad(model, x_adv, y, loss_fn)
            x_adv = project(x_adv + alpha * grad.sign(), x, eps)
    return x_adv.detach()


def mifgsm(
    model: nn.Module,
    x: Tensor,
    y: Tensor,
    eps: float,
    loss_fn: LossFn,
    *,
    steps: int = 10,
    step_size: float | None = None,
    momentum: float = 1.0,
) -> Tensor:
    """Momentum iterative FGSM (Dong et al. 2018), L-inf.

    g <- momentum * g + grad / ||grad||_1 (per image); x' <- clip_eps(x' + step_size * sign(g)),
    step_size defaulting to eps / steps as in the paper.
    """
    eps = check_eps(eps)
    steps, alpha = _check_steps(steps, step_size, 1.0, eps)
    x = x.detach()
    x_adv = x
    g = torch.zeros_like(x)
    with _eval_mode(model):
        for _ in range(steps):
            grad = _input_grad(model, x_adv, y, loss_fn)
            l1 = grad.abs().flatten(1).sum(1).clamp_min(1e-12).view(-1, *([1] * (x.dim() - 1)))
            g = momentum * g + grad / l1
            x_adv = project(x_adv + alpha * g.sign(), x, eps)
    return x_adv.detach()


ATTACKS: dict[str, Callable[..., Tensor]] = {"fgsm": fgsm, "pgd": pgd, "mifgsm": mifgsm}


def get_attack(
    name: str,
    *,
    steps: int = 10,
    step_size: float | None = None,
    random_start: bool = True,
    momentum: float = 1.0,
    generator: torch.Generator | None = None,
) -> AttackFn:
    """An attack from ATTACKS as `attack(model, x, y, eps, loss_fn)`, with its options bound."""
    if name not in ATTACKS:
        raise ValueError(f"unknown attack {name!r}; choose one of {', '.join(ATTACKS)}")
    if name == "pgd":
        return functools.partial(pgd, steps=steps, step_size=step_size, random_start=random_start, generator=generator)
    if name == "mifgsm":
        return functools.partial(mifgsm, steps=steps, step_size=step_size, momentum=momentum)
    return fgsm


def quantize(x_adv: Tensor, x: Tensor) -> Tensor:
    """Adversarial images as stored: uint8 (B, 3, H, W), each pixel's perturbation rounded to the
    nearest 8-bit level but never to zero, so every perturbed pixel keeps the sign of its
    perturbation (eps = 0.01 is 2.55 levels: stored as 3 levels = 0.0118).

    `x` must be the clean image on the 8-bit grid (uint8 / 255).
    """
    delta = (x_adv - x) * 255.0
    levels = torch.sign(delta) * torch.round(delta.abs()).clamp_min(1.0)
    return torch.clamp(torch.round(x * 255.0) + levels, 0, 255).to(torch.uint8)


def stored_attack(
    model: nn.Module, loss_fn: LossFn, eps: float, attack: AttackFn = fgsm
) -> Callable[[Tensor, Tensor], Tensor]:
    """`attack` at `eps` as a camera would deliver it: `(x, y) -> x'` with x' the adversarial image
    stored as 8 bits (`quantize`) and read back as floats in [0, 1], (B, 3, H, W).

    `x` must be clean images on the 8-bit grid (uint8 / 255); `y` their (B, 9) labels (m, 6-D).
    """
    eps = check_eps(eps)

    def apply(x: Tensor, y: Tensor) -> Tensor:
        return quantize(attack(model, x, y, eps, loss_fn), x).float() / 255.0

    return apply
