"""The paper-literal FGSM (unclipped floats) beside ours (clipped, stored as 8 bits), on a black background."""

from __future__ import annotations

import pytest
import torch
from test_attacks import TinyLoss, TinyPose

from pipeline.attacks.gradient import attack_loss, fgsm
from pipeline.attacks.literal import fgsm_literal, fgsm_variant


@pytest.fixture()
def black():
    """A model, its loss, and images with a black background (zeros) around a grey patch on the 8-bit grid."""
    torch.manual_seed(0)
    model, loss = TinyPose(), TinyLoss()
    x = torch.zeros(3, 3, 12, 16)
    x[:, :, 4:8, 5:11] = torch.randint(20, 230, (3, 3, 4, 6)).float() / 255
    return model, attack_loss("full", loss), x, torch.randn(3, 9)


@pytest.mark.parametrize("eps", [0.01, 0.05])
def test_the_paper_literal_fgsm_puts_negative_pixels_on_a_black_background(black, eps):
    model, loss_fn, x, y = black
    x_adv = fgsm_variant(model, loss_fn, eps, "paper")(x, y)
    assert x_adv.dtype == torch.float32
    background = x == 0
    assert torch.allclose((x_adv - x).abs(), torch.full_like(x, eps), atol=1e-7)  # every pixel moved by eps
    negative = x_adv < 0
    assert negative.any() and bool(background[negative].all())
    assert torch.isclose(x_adv.min(), torch.tensor(-eps))
    # exactly the equation: x + eps sign(grad), equal to our FGSM wherever our clip does not act
    inside = (x_adv >= 0) & (x_adv <= 1)
    assert torch.equal(x_adv[inside], fgsm(model, x, y, eps, loss_fn)[inside])
    assert torch.equal(x_adv, fgsm_literal(model, x, y, eps, loss_fn))


@pytest.mark.parametrize("eps", [0.01, 0.05])
def test_our_fgsm_stays_in_0_1_on_the_8_bit_grid_and_loses_the_negative_half(black, eps):
    model, loss_fn, x, y = black
    ours = fgsm_variant(model, loss_fn, eps, "ours")(x, y)
    paper = fgsm_variant(model, loss_fn, eps, "paper")(x, y)
    assert ours.min() >= 0 and ours.max() <= 1
    levels = ours * 255
    assert torch.equal(levels, torch.round(levels))  # stored as 8 bits
    assert bool((ours[paper < 0] == 0).all())  # the background's negative half is clipped away
    assert ((ours - x).abs().max() * 255).round() == max(1, round(eps * 255))  # a whole number of grey levels
    with torch.no_grad():
        gain_paper, gain_ours, clean = (loss_fn(model(v), y) for v in (paper, ours, x))
    assert gain_paper > clean and gain_ours > clean


def test_an_unknown_variant_is_refused(black):
    model, loss_fn, _, _ = black
    with pytest.raises(ValueError, match="unknown FGSM variant 'literal'"):
        fgsm_variant(model, loss_fn, 0.01, "literal")
