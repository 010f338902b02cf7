"""Adversarial training that covers attitude and eps past the black-level clamp (issue 37, item 3): the suite's
objectives in the inner maximisation, the background-lifting start and BPDA, the shipped recipe (c6) and the
position-loss step of the recipes before it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

import pipeline.pose.adversarial as adversarial
from pipeline.attacks.gradient import pgd
from pipeline.attacks.objectives import attitude, position
from pipeline.geometry.rotations import quat_to_6d
from pipeline.pose.adversarial import AdversarialConfig, Adversary
from pipeline.pose.loss import PoseLoss
from pipeline.pose.metrics import pose_errors
from pipeline.pose.model import PoseNet
from stages.config import params as params_mod
from stages.config.build import adversarial_config

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py

H, W = 27, 48


def _net(black_level: float = 0.0, x: torch.Tensor | None = None, y: torch.Tensor | None = None) -> PoseNet:
    """A small PoseNet in eval mode whose position head answers the image strongly (a trained network's
    sensitivity), its mean output on images x the mean of the poses y."""
    torch.manual_seed(0)
    model = PoseNet(0.125, 0.0, black_level=black_level).eval()
    if x is not None and y is not None:
        with torch.no_grad():
            model.head_pos.weight.mul_(10.0)
            offset = model(x).mean(0) - y.mean(0)
            model.head_pos.bias.sub_(offset[:3])
            model.head_rot.bias.sub_(offset[3:])
    return model


def _batch(n: int = 8, black: bool = False, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Images on the 8-bit grid (n, 3, H, W): noise, or a bright target on a black background; poses about
    30 m ahead with random attitudes within about 30 degrees of the identity (n, 9)."""
    rng = np.random.default_rng(seed)
    if black:
        images = np.zeros((n, 3, H, W), np.uint8)
        images[:, :, 9:18, 16:32] = rng.integers(60, 256, (n, 3, 9, 16))
    else:
        images = rng.integers(0, 256, (n, 3, H, W)).astype(np.uint8)
    q = np.c_[np.ones(n), rng.normal(0, 0.15, (n, 3))]
    t = np.c_[rng.normal(0, 2, (n, 2)), rng.uniform(20, 40, n)]
    y = np.c_[t, quat_to_6d(q / np.linalg.norm(q, axis=1, keepdims=True))]
    return torch.from_numpy(images).float() / 255, torch.tensor(y, dtype=torch.float32)


def test_the_inner_attack_ascends_the_attitude_objective_on_its_rows():
    x, y = _batch()
    model = _net(0.0, x, y)
    cfg = AdversarialConfig(eps=0.03, steps=3, ramp_epochs=0, objectives=("position", "attitude"))
    x_adv = Adversary(cfg, PoseLoss(), 1, 0).perturb(model, x, y, 0)
    # the position-weighted inner loss (the committed recipe) as the reference: attitude only as a side effect
    x_pos = Adversary(
        AdversarialConfig(eps=0.03, steps=3, ramp_epochs=0, position_weight=1.0), PoseLoss(), 1, 0
    ).perturb(model, x, y, 0)
    assert (x_adv - x).abs().max() <= 0.03 + 1e-6
    with torch.no_grad():
        clean, attacked, by_position = model(x), model(x_adv), model(x_pos)
    rows = slice(1, None, 2)  # odd rows ascend the attitude, even the position
    assert torch.all(attitude(attacked[rows], y[rows]) > attitude(clean[rows], y[rows]) + 1.0)
    assert attitude(attacked[rows], y[rows]).mean() > 1.5 * attitude(by_position[rows], y[rows]).mean()
    assert torch.all(position(attacked[::2], y[::2]) > position(clean[::2], y[::2]))
    # each objective within its own budget, ramped alike
    own = AdversarialConfig(
        eps=0.03, steps=3, ramp_epochs=1, objectives=("position", "attitude"), objective_eps=(0.03, 0.01)
    )
    x_own = Adversary(own, PoseLoss(), 2, 0).perturb(model, x, y, 0)  # half-way up the ramp
    assert (x_own - x)[1::2].abs().max() <= 0.005 + 1e-6 < (x_own - x)[::2].abs().max() <= 0.015 + 1e-6
    with pytest.raises(ValueError, match=r"objective_eps must give each of the 2 objectives a budget in \(0, eps"):
        AdversarialConfig(eps=0.03, objectives=("position", "attitude"), objective_eps=(0.05, 0.01))


def test_past_the_clamp_the_attack_lifts_the_background_and_passes_the_clamp(monkeypatch):
    x, y = _batch(black=True)
    model = _net(0.07, x, y)
    starts, passed = [], []
    get_start, bpda_forward = adversarial.get_start, adversarial.bpda_forward
    monkeypatch.setattr(adversarial, "get_start", lambda kind, *a, **k: starts.append(kind) or get_start(kind, *a, **k))
    monkeypatch.setattr(adversarial, "bpda_forward", lambda m: passed.append(m) or bpda_forward(m))
    cfg = AdversarialConfig(eps=0.1, steps=2, ramp_epochs=0, objectives=("position",), start="lift", bpda=True)
    x_adv = Adversary(cfg, PoseLoss(), 1, 0).perturb(model, x, y, 0)
    assert starts == ["lift"] and passed == [model] and model.black_level == 0.07  # the clamp is restored
    background = (x == 0).all(1, keepdim=True).expand_as(x)
    assert (model.clamp(x_adv)[background] > 0).float().mean() > 0.5  # the background reaches the network
    masked = pgd(
        model, x, y, 0.1, lambda p, t: position(p, t).sum(), steps=2, generator=torch.Generator().manual_seed(0)
    )
    with torch.no_grad():
        assert position(model(x_adv), y).mean() > position(model(masked), y).mean() > position(model(x), y).mean()
    for start, bpda in (("random", True), ("lift", False)):
        masked_cfg = AdversarialConfig(eps=0.1, ramp_epochs=0, objectives=("position",), start=start, bpda=bpda)
        with pytest.raises(ValueError, match="exceeds the black-level clamp 0.07: .* set start: lift and bpda: true"):
            Adversary(masked_cfg, PoseLoss(), 1, 0).perturb(model, x, y, 0)


def test_the_default_params_ship_the_chosen_recipe_and_the_position_loss_step_is_pgd_k():
    shipped = adversarial_config(params_mod.load().train.adversarial)
    # benchmarks/robust_recipes.py's c6, chosen on validation frames (black and Earth)
    assert (shipped.eps, shipped.objectives, shipped.objective_eps, shipped.trades) == (
        0.1,
        ("position", "attitude"),
        (0.1, 0.03),
        0.3,
    )
    assert shipped.unmasked() and shipped.attacked_rotation
    # the inner loss without objectives: the recipe before c6, below the clamp
    a = dataclasses.replace(
        shipped,
        eps=0.05,
        objectives=(),
        objective_eps=(),
        start="random",
        bpda=False,
        trades=0.0,
        attacked_rotation=False,
    )
    x, y = _batch(black=True)
    model, loss = _net(0.07, x, y), PoseLoss()
    with torch.no_grad():
        loss.s_p.fill_(0.3)
        loss.s_r.fill_(-0.2)
    adv = Adversary(a, loss, 4, 5)
    x_adv, skip = adv.perturb(model, x, y, 3), adv.skip_rotation(len(x))
    # the committed step: PGD-k of pipeline.attacks.gradient on the position-weighted inner loss, from the
    # seeded random start, on the first `fraction` of the batch; the rotation of those rows left out of the loss
    n = round(a.fraction * len(x))
    w, e_p, e_r = a.position_weight, torch.exp(torch.tensor(-0.6)), torch.exp(torch.tensor(0.4))
    inner = lambda p, t: w * e_p * loss.parts(p, t)[0] + (1 - w) * e_r * loss.parts(p, t)[1]  # noqa: E731
    ref = torch.cat(
        [pgd(model, x[:n], y[:n], a.eps / 2, inner, steps=a.steps, generator=torch.Generator().manual_seed(5)), x[n:]]
    )
    assert torch.equal(x_adv, ref) and skip == n and adv.ramp(3) == 0.5
    model.train()
    assert loss(model(x_adv), y, skip).item() == loss(model(ref), y, n).item()
    pred, target = np.c_[y[:, :3] + 1.0, y[:, 3:]], y.numpy()
    assert adv.selection_error(pred, target) == pytest.approx(
        np.mean(np.sqrt(3) / np.linalg.norm(target[:, :3], axis=1))
    )


def test_suite_objectives_validate_and_select_on_the_attacked_speed_score():
    from pipeline.pose.train import PoseDataset

    cfg = AdversarialConfig(
        eps=0.03, steps=1, ramp_epochs=0, val_steps=3, val_frames=6, objectives=("position", "attitude")
    )
    adv = Adversary(cfg, PoseLoss(), 1, 0)
    x, y = _batch(10)
    val_set = PoseDataset((x * 255).round().to(torch.uint8).permute(0, 2, 3, 1).numpy(), y.numpy())
    model = _net(0.0, x, y)
    pred, target = adv.validate(model, val_set)
    assert pred.shape == target.shape == (6, 9) and not model.training
    with torch.no_grad():
        clean = model(torch.from_numpy(np.stack([val_set[i][0].numpy() for i in range(10)])).permute(0, 3, 1, 2) / 255)
    rows = np.sort(np.random.default_rng(0).permutation(10)[:6])
    assert np.all(pose_errors(pred, target)[1][1::2] > pose_errors(clean.numpy()[rows], target)[1][1::2])
    pred = target.copy()
    pred[:, 3:] = _batch(6, seed=1)[1].numpy()[:, 3:]
    att = pose_errors(pred, target)[1]
    assert adv.selection_error(pred, target) == pytest.approx(np.mean(np.deg2rad(att)))
    for bad, message in (
        ({"objectives": ("speed",)}, "unknown attack objective 'speed'"),
        (
            {"objectives": ("attitude",), "attacked_rotation": False, "fraction": 0.5},
            "an attitude objective needs attacked_rotation on",
        ),
        ({"start": "zero"}, "unknown start 'zero'"),
    ):
        with pytest.raises(ValueError, match=message):
            AdversarialConfig(**bad)
    assert AdversarialConfig(objectives=("position", "range_near"), attacked_rotation=False, fraction=0.5).objectives


def test_ablation_rows_split_each_models_suite_run_by_background():
    from pipeline.attacks.strongest import SuiteConfig
    from pipeline.pose.ablation import ablation_rows

    x, y = _batch(6, black=True)
    images = (x * 255).round().to(torch.uint8).permute(0, 2, 3, 1).numpy()
    images[3:, :4] = 200  # three frames with a bright backdrop
    models = {"clamp only": _net(0.07, x, y), "no clamp": _net(0.0, x, y)}
    config = SuiteConfig(members=("apgd/position", "bpda/attitude"), steps=3, restarts=1, starts=("lift",))
    kinds = np.array(["black"] * 3 + ["earth"] * 3)
    rows = ablation_rows(models, images, y.numpy(), [0.02, 0.1], config, kinds)
    assert [(r["model"], r["background"], r["eps"], r["n"]) for r in rows] == [
        (m, b, e, 3) for m in models for b in ("black", "earth") for e in (0.0, 0.02, 0.1)
    ]
    for m in models:
        for b in ("black", "earth"):
            clean, *attacked = [r for r in rows if r["model"] == m and r["background"] == b]
            assert clean["pos_m"] <= attacked[0]["pos_m"] <= attacked[1]["pos_m"]  # nested in eps
            assert attacked[0]["pos_ci"][0] <= attacked[0]["pos_m"] <= attacked[0]["pos_ci"][1]
    whole = ablation_rows({"both": models["no clamp"]}, images, y.numpy(), [0.02], config)
    assert {r["background"] for r in whole} == {"black"} and whole[0]["n"] == 6
    with pytest.raises(ValueError, match="one background per frame"):
        ablation_rows(models, images, y.numpy(), [0.02], config, kinds[:4])


def test_trades_fits_the_clean_batch_and_the_attacked_rows_consistency():
    from pipeline.pose.train import _Objective

    x, y = _batch(6)
    model, loss = _net(0.0, x, y), PoseLoss()
    cfg = AdversarialConfig(
        eps=0.03, steps=3, ramp_epochs=0, fraction=0.5, objectives=("position", "attitude"), trades=2.0
    )
    adv = Adversary(cfg, loss, 1, 0)
    inputs, skip, pairs = adv.batch(model, x, y, 0)
    assert pairs == 3 and skip == 0 and torch.equal(inputs[:6], x) and (inputs[6:] - x[:3]).abs().max() <= 0.03 + 1e-6
    with torch.no_grad():
        clean, attacked = model(x[:3]), model(inputs[6:])
    # the attack ascends the shift from the clean estimate (no truth): attitude rows turn, position rows move
    assert attitude(attacked[1::2], clean[1::2]).min() > 1.0 and position(attacked[::2], clean[::2]).min() > 0.1
    value, pred = _Objective(model, loss)(inputs, y, skip, pairs, cfg.trades)
    with torch.no_grad():
        assert torch.equal(pred, model(x))
        expected = loss(pred, y) + 2.0 * loss.consistency(model(inputs[6:]), pred[:3])
    assert value.item() == pytest.approx(expected.item()) and value.item() > loss(pred, y).item()
    # the learned weights get no gradient from the consistency term
    value.backward()
    s_p_grad = loss.s_p.grad.clone()
    loss.zero_grad()
    loss(_Objective(model, loss)(inputs[:6], y)[1], y).backward()
    assert loss.s_p.grad.item() == pytest.approx(s_p_grad.item())


def test_paired_forward_shares_each_pairs_dropout_mask():
    torch.manual_seed(0)
    model = PoseNet(0.125, 0.5).train()
    x = torch.rand(4, 3, H, W)
    torch.manual_seed(1)
    paired = model.forward_paired(torch.cat([x, x[:2]]), 2)
    torch.testing.assert_close(paired[4:], paired[:2])  # same image, same mask: same output
    assert not torch.allclose(paired[:2], model(x[:2]))  # a fresh mask otherwise
    with torch.no_grad():
        torch.testing.assert_close(model.eval().forward_paired(torch.cat([x, x[:2]]), 2)[:4], model(x))
