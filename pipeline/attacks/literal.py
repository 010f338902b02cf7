"""The paper's FGSM as its equation prints it, beside ours, for the ablation of issue 38.

- paper-literal: x' = x + eps sign(grad_x L(model(x), y)), with no clip to [0, 1] and no 8-bit storage: the
  adversarial image stays a float tensor, so on the black background (x = 0) every pixel whose gradient is
  negative becomes -eps, a value no camera delivers; `fgsm_literal`, delivered by `float_attack`.
- ours: x' = clip(x + eps sign(grad), 0, 1), stored as 8 bits as a camera delivers it
  (`pipeline.attacks.gradient.fgsm` through `stored_attack`): on the black background only the positive half of
  that signal survives, rounded to whole grey levels.

`fgsm_variant(model, loss_fn, eps, variant)` gives either as `(x, y) -> x'` (float images (B, 3, H, W); x clean on
the 8-bit grid, y the (B, 9) labels in metres and 6-D). The attacks of `ATTACKS` all keep images in [0, 1]; this
one is deliberately outside them.
"""

from __future__ import annotations

from typing import Callable

from torch import Tensor, nn

from pipeline.attacks.gradient import LossFn, _eval_mode, _input_grad, check_eps, fgsm, stored_attack

VARIANTS = ("ours", "paper")  # clipped and stored as 8 bits / the paper's equation: unclipped floats


def fgsm_literal(model: nn.Module, x: Tensor, y: Tensor, eps: float, loss_fn: LossFn) -> Tensor:
    """The paper's FGSM equation: x' = x + eps * sign(grad_x L(model(x), y)), pixels in [0, 1] units, not clipped
    (values in [-eps, 1 + eps]); eval mode, no parameter gradients, as every attack of gradient.py."""
    eps = check_eps(eps)
    x = x.detach()
    with _eval_mode(model):
        grad = _input_grad(model, x, y, loss_fn)
    return (x + eps * grad.sign()).detach()


def float_attack(
    model: nn.Module, loss_fn: LossFn, eps: float, attack: Callable[..., Tensor] = fgsm_literal
) -> Callable[[Tensor, Tensor], Tensor]:
    """`attack` at `eps` delivered as floats, neither clipped nor quantised: `(x, y) -> x'` (B, 3, H, W)."""
    eps = check_eps(eps)

    def apply(x: Tensor, y: Tensor) -> Tensor:
        return attack(model, x, y, eps, loss_fn)

    return apply


def fgsm_variant(model: nn.Module, loss_fn: LossFn, eps: float, variant: str) -> Callable[[Tensor, Tensor], Tensor]:
    """FGSM at `eps` as `(x, y) -> x'`: "ours" (clipped to [0, 1], stored as 8 bits and read back) or "paper"
    (the paper's equation: unclipped floats). Raises ValueError for another name."""
    if variant == "ours":
        return stored_attack(model, loss_fn, eps, fgsm)
    if variant == "paper":
        return float_attack(model, loss_fn, eps)
    raise ValueError(f"unknown FGSM variant {variant!r}; choose one of {', '.join(VARIANTS)}")
