"""Attacks on a tiny stand-in pose regressor (9 outputs) with a Kendall-style loss."""

from __future__ import annotations

import pytest
import torch
from tiny import TinyPose
from torch import nn

from pipeline.attacks.gradient import ATTACKS, attack_loss, fgsm, get_attack, mifgsm, pgd, quantize, stored_attack


class TinyLoss(nn.Module):
    """exp(-2 s_p) sum ||dp|| + exp(-2 s_r) sum ||dr|| + 2 (s_p + s_r), with .parts like PoseLoss."""

    def __init__(self) -> None:
        super().__init__()
        self.s_p = nn.Parameter(torch.tensor(0.3))
        self.s_r = nn.Parameter(torch.tensor(-0.2))

    def parts(self, pred: torch.Tensor, target: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return ((pred[:, :3] - target[:, :3]).norm(dim=1).sum(), (pred[:, 3:] - target[:, 3:]).norm(dim=1).sum())

    def forward(self, pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        p, r = self.parts(pred, target)
        return torch.exp(-2 * self.s_p) * p + torch.exp(-2 * self.s_r) * r + 2 * (self.s_p + self.s_r)


@pytest.fixture()
def setup():
    torch.manual_seed(0)
    model, loss = TinyPose(), TinyLoss()
    model.train()  # the attacks must switch to eval mode themselves and restore this
    u8 = torch.randint(0, 256, (4, 3, 12, 16), dtype=torch.uint8)
    u8[0, :, :3] = 0
    u8[0, :, -3:] = 255  # pixels at both clip bounds
    x = u8.float() / 255
    y = torch.randn(4, 9)
    return model, loss, x, y


def _grad(model, loss_fn, x, y):
    model.eval()
    x = x.clone().requires_grad_(True)
    loss_fn(model(x), y).backward()
    return x.grad


@pytest.mark.parametrize("eps", [0.5, 0.05, 0.01])
def test_fgsm_moves_every_pixel_by_eps_in_gradient_sign(setup, eps):
    model, loss, x, y = setup
    loss_fn = attack_loss("full", loss)
    x_adv = fgsm(model, x, y, eps, loss_fn)
    assert model.training, "the attack must restore the model's mode"
    g = _grad(model, loss_fn, x, y)
    expected = torch.clamp(x + eps * g.sign(), 0, 1)
    assert torch.equal(x_adv, expected)
    moved = x_adv - x
    nonzero = g != 0
    assert nonzero.float().mean() > 0.9
    at_bound = (x_adv == 0) | (x_adv == 1)
    full_step = torch.isclose(moved.abs(), torch.tensor(eps), atol=1e-6)
    assert bool((full_step | at_bound)[nonzero].all())
    assert bool((torch.sign(moved)[moved != 0] == g.sign()[moved != 0]).all())
    assert at_bound.any() and (~full_step & nonzero).any(), "the batch must exercise the clip bounds"
    assert x_adv.min() >= 0 and x_adv.max() <= 1


def test_attacks_leave_parameter_gradients_alone(setup):
    model, loss, x, y = setup
    for name in ATTACKS:
        get_attack(name, steps=2)(model, x, y, 0.1, attack_loss("full", loss))
    assert all(p.grad is None for p in model.parameters())
    assert all(p.grad is None for p in loss.parameters())


@pytest.mark.parametrize("kind", ["full", "position", "rotation"])
def test_pgd_stays_in_ball_and_beats_fgsm(setup, kind):
    model, loss, x, y = setup
    loss_fn = attack_loss(kind, loss)
    eps = 0.03
    x_pgd = pgd(model, x, y, eps, loss_fn, steps=10, generator=torch.Generator().manual_seed(1))
    x_fgsm = fgsm(model, x, y, eps, loss_fn)
    assert (x_pgd - x).abs().max() <= eps + 1e-6
    assert x_pgd.min() >= 0 and x_pgd.max() <= 1
    model.eval()
    with torch.no_grad():
        clean, l_fgsm, l_pgd = (float(loss_fn(model(v), y)) for v in (x, x_fgsm, x_pgd))
    assert l_fgsm > clean
    assert l_pgd >= l_fgsm


def test_mifgsm_stays_in_ball_and_raises_loss(setup):
    model, loss, x, y = setup
    loss_fn = attack_loss("full", loss)
    x_adv = mifgsm(model, x, y, 0.03, loss_fn, steps=5)
    assert (x_adv - x).abs().max() <= 0.03 + 1e-6
    model.eval()
    with torch.no_grad():
        assert float(loss_fn(model(x_adv), y)) > float(loss_fn(model(x), y))


def test_loss_kinds_pick_their_term(setup):
    _, loss, _, _ = setup
    pred = torch.randn(4, 9)
    target = pred.clone()
    target[:, :3] += 1.0  # only the position is wrong
    with torch.no_grad():
        _check_terms(loss, pred, target)


def _check_terms(loss, pred, target):
    assert float(attack_loss("rotation", loss)(pred, target)) == 0.0
    assert float(attack_loss("position", loss)(pred, target)) == pytest.approx(4 * 3**0.5, rel=1e-5)
    assert float(attack_loss("full", loss)(pred, target)) == pytest.approx(float(loss(pred, target)))


def test_quantize_keeps_perturbation_sign(setup):
    _, _, x, _ = setup
    sign = torch.where(torch.rand_like(x) > 0.5, 1.0, -1.0)
    for eps in (0.5, 0.01, 0.001):  # 0.001 is a quarter of an 8-bit level
        x_adv = torch.clamp(x + eps * sign, 0, 1)
        q = quantize(x_adv, x).float() / 255
        moved = x_adv != x
        assert torch.equal(torch.sign(q - x)[moved], torch.sign(x_adv - x)[moved])
        assert torch.equal(q[~moved], x[~moved])
        assert (q - x_adv).abs().max() <= 0.5 / 255 + max(0.0, 1 / 255 - eps) + 1e-6


@pytest.mark.parametrize("name", sorted(ATTACKS))
def test_stored_attack_is_the_attack_on_the_8_bit_grid(setup, name):
    model, loss, x, y = setup
    attack = get_attack(name, steps=3, generator=torch.Generator().manual_seed(1))
    attack_again = get_attack(name, steps=3, generator=torch.Generator().manual_seed(1))
    out = stored_attack(model, loss, 0.05, attack)(x, y)
    assert out.dtype == torch.float32 and out.shape == x.shape
    assert torch.equal(out, quantize(attack_again(model, x, y, 0.05, loss), x).float() / 255)
    levels = out * 255
    assert torch.equal(levels, torch.round(levels))  # every pixel on the 8-bit grid
    assert (out - x).abs().max() <= 0.05 + 0.5 / 255 + 1e-6 and (out != x).any()
    with pytest.raises(ValueError, match="eps must be in"):
        stored_attack(model, loss, 0.0)


def test_bad_inputs_raise_clear_errors(setup):
    model, loss, x, y = setup
    loss_fn = attack_loss("full", loss)
    for eps in (0.0, -0.1, 1.5):
        for name in ATTACKS:
            with pytest.raises(ValueError, match=r"eps must be in \(0, 1\]"):
                get_attack(name)(model, x, y, eps, loss_fn)
    with pytest.raises(ValueError, match="unknown attack 'cw'"):
        get_attack("cw")
    with pytest.raises(ValueError, match="unknown attack loss 'huber'"):
        attack_loss("huber", loss)
    with pytest.raises(ValueError, match="steps >= 1"):
        pgd(model, x, y, 0.1, loss_fn, steps=0)
