"""The robust pose model (issue 28): the black-level clamp inside the network, the cosine schedule and the
weights' moving average, PGD-k adversarial training, the attacked-error table, `rpod train --robust`."""

from __future__ import annotations

import copy
import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from test_training import H, W, write_dataset

from pipeline.attacks.gradient import attack_loss, fgsm
from pipeline.attacks.strongest import SuiteConfig, run_suite
from pipeline.formats.capacity import read_capacity
from pipeline.formats.models import model_from_checkpoint, read_pose, save_pose
from pipeline.pose.adversarial import AdversarialConfig, Adversary
from pipeline.pose.loss import PoseLoss
from pipeline.pose.metrics import tilt_roll_deg
from pipeline.pose.model import PoseNet
from pipeline.pose.optim import WeightEMA, cosine_factor, make_scheduler
from pipeline.pose.robustness import black_level_stats
from pipeline.pose.train import TrainConfig, fit, make_deterministic
from pipeline.seeds import seed_for
from stages.artifacts import data, models
from stages.artifacts.paths import POSE_ROBUST
from stages.config import params as params_mod
from stages.config.build import adversarial_config
from stages.config.sections import ParamsError
from stages.errors import StageError


@pytest.fixture
def dataset(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    torch.set_num_threads(1)
    return write_dataset(tmp_path, n=80)


def _target(n: int = 4) -> torch.Tensor:
    return torch.tensor([[0.0, 0.0, 30.0, 1, 0, 0, 0, 1, 0]] * n)


def test_the_clamp_is_inside_the_model_and_zeroes_the_gradient_on_black_pixels(tmp_path):
    torch.manual_seed(0)
    model = PoseNet(0.125, 0.0, black_level=0.07).eval()
    x = torch.zeros(4, 3, H, W)
    x[:, :, 10:17, 20:30] = torch.rand(4, 3, 7, 10) * 0.9 + 0.1  # a bright target on black
    x[:, :, 0, :5] = 0.069  # dark pixels just under t
    x = x.requires_grad_(True)
    loss = attack_loss("position", PoseLoss())
    (grad,) = torch.autograd.grad(loss(model(x), _target()), x)
    dark = x.detach() < 0.07
    assert torch.all(grad[dark] == 0) and torch.any(grad[~dark] != 0)
    # an attack through the module leaves the background at most eps < t, which the network sees as black
    x_adv = fgsm(model, x.detach(), _target(), 0.05, loss)
    assert torch.all(model.clamp(x_adv)[x.detach() == 0] == 0)
    torch.testing.assert_close(model(x_adv), model(torch.where(x.detach() == 0, 0.0, x_adv)))
    # the checkpoint's architecture rebuilds it; a standard model's reads as before
    save_pose(tmp_path / "m.pt", model, PoseLoss(), (H, W), {})
    assert read_pose(tmp_path / "m.pt")["arch"]["black_level"] == 0.07
    torch.testing.assert_close(model_from_checkpoint(read_pose(tmp_path / "m.pt"))(x.detach()), model(x.detach()))
    assert "black_level" not in PoseNet(0.125).arch()
    with pytest.raises(ValueError, match="black_level must be in"):
        PoseNet(0.125, black_level=1.0)


def test_the_cosine_schedule_reaches_its_floor_at_the_last_step():
    w = torch.nn.Parameter(torch.zeros(()))
    opt = torch.optim.Adam([{"params": [w], "lr": 1e-4}, {"params": [torch.nn.Parameter(torch.zeros(()))], "lr": 1e-3}])
    sched = make_scheduler(opt, "cosine", 50, lr_base=1e-4, lr_max=1e-3, lr_min=1e-6, cycle=10, warmup=5)
    used = []
    for _ in range(50):
        used.append([g["lr"] for g in opt.param_groups])
        opt.step()
        sched.step()
    assert used[0] == pytest.approx([1e-4, 1e-3]) and used[5] == pytest.approx([1e-3, 1e-2])
    assert used[-1] == pytest.approx([1e-6, 1e-5]) and min(u[0] for u in used) == pytest.approx(1e-6)
    assert all(a[0] >= b[0] for a, b in zip(used[5:], used[6:]))  # monotone after the warm-up
    assert cosine_factor(80, 50, 5, 1e-4, 1e-3, 1e-6) * 1e-3 == pytest.approx(1e-6)  # held after the end


def test_ema_weights_are_what_is_validated_and_kept(dataset):
    train, test = data.load_split(dataset, "train"), data.load_split(dataset, "test")
    make_deterministic(0)
    model = PoseNet(0.125, 0.0)
    kept = {}

    def on_epoch(stats, is_best, net):
        assert net is not model and not net.training
        if is_best:
            kept.update({k: v.clone() for k, v in net.state_dict().items()})

    cfg = TrainConfig(epochs=3, batch_size=8, schedule="cosine", warmup_epochs=0, ema=0.9)
    result = fit(
        model, PoseLoss(), data.pose_dataset(train), data.pose_dataset(test), cfg, on_epoch=on_epoch, progress=False
    )
    assert result.history[-1].lr == pytest.approx(cfg.lr_min)
    for k, v in result.best_state.items():
        torch.testing.assert_close(v, kept[k])
    raw = model.state_dict()
    assert any(not torch.equal(v, raw[k].cpu()) for k, v in result.best_state.items() if v.is_floating_point())


def test_weight_ema_averages_with_a_warm_up():
    net = torch.nn.Linear(1, 1, bias=False)
    with torch.no_grad():
        net.weight.fill_(0.0)
    ema = WeightEMA(net, 0.5)
    with torch.no_grad():
        net.weight.fill_(1.0)
    ema.update(net)  # d = min(0.5, 2 / 11)
    assert ema.model.weight.item() == pytest.approx(1 - 2 / 11)
    with pytest.raises(ValueError, match="EMA decay"):
        WeightEMA(net, 1.0)


def test_adversarial_training_lowers_the_pgd_error(dataset):
    train, test = data.load_split(dataset, "train"), data.load_split(dataset, "test")
    fit_set, val_set = data.pose_dataset(train), data.pose_dataset(test)
    make_deterministic(0)
    model, loss = PoseNet(0.125, 0.0), PoseLoss()
    model.set_output_bias(train.targets[:, :3].mean(0), train.targets[:, 3:].mean(0))
    fit(
        model,
        loss,
        fit_set,
        val_set,
        TrainConfig(epochs=6, batch_size=8, lr_max=2e-3, schedule="cosine", warmup_epochs=0),
        progress=False,
    )

    def tuned(adversarial: bool) -> dict[str, float]:
        m, lo = copy.deepcopy(model), copy.deepcopy(loss)
        cfg = TrainConfig(epochs=3, batch_size=8, lr_max=5e-4, schedule="cosine", warmup_epochs=0, seed=1)
        adv = (
            Adversary(
                AdversarialConfig(eps=0.05, steps=2, ramp_epochs=0, val_frames=8, val_steps=2), lo, len(fit_set) // 8, 1
            )
            if adversarial
            else None
        )
        result = fit(m, lo, fit_set, val_set, cfg, progress=False, adversary=adv)
        assert (result.history[0].val_adv_pos_m == result.history[0].val_adv_pos_m) == adversarial
        m.load_state_dict(result.best_state)
        pgd10 = run_suite(
            m, np.asarray(test.images), test.targets, [0.05], SuiteConfig(("pgd/position",), steps=10, restarts=1)
        )
        return {"clean": pgd10.clean["position_m"].mean(), "pgd-10": pgd10.errors["position_m"][0, 0].mean()}

    plain, robust = tuned(False), tuned(True)
    assert robust["pgd-10"] < 0.9 * plain["pgd-10"]
    assert plain["pgd-10"] > plain["clean"]


def test_the_eps_ramp_and_the_attacked_share():
    adv = Adversary(AdversarialConfig(eps=0.04, steps=1, ramp_epochs=2, fraction=0.5), PoseLoss(), 10, 0)
    assert 0.04 * adv.ramp(0) == pytest.approx(0.002) and 0.04 * adv.ramp(9) == pytest.approx(0.02)
    assert adv.ramp(19) == adv.ramp(500) == 1.0
    model = PoseNet(0.125, 0.0).eval()
    x = torch.rand(4, 3, H, W)
    x_adv = adv.perturb(model, x, _target(), 100)
    assert torch.equal(x_adv[2:], x[2:]) and (x_adv[:2] - x[:2]).abs().max() <= 0.04 + 1e-6
    assert not torch.equal(x_adv[:2], x[:2])


def test_attacked_images_can_leave_the_rotation_term():
    adv = Adversary(AdversarialConfig(fraction=0.5, attacked_rotation=False), PoseLoss(), 1, 0)
    assert adv.skip_rotation(8) == 4 and adv.skip_rotation(1) == 0
    assert Adversary(AdversarialConfig(fraction=0.5), PoseLoss(), 1, 0).skip_rotation(8) == 0
    loss, target = PoseLoss(), _target(4)
    pred = target.clone()
    pred[:2, 3:] += 1.0  # wrong rotations on the two attacked rows only
    assert loss(pred, target, skip_rotation=2).item() == pytest.approx(0.0)
    assert loss(pred, target).item() > 0
    with pytest.raises(ValueError, match="needs fraction < 1"):
        AdversarialConfig(attacked_rotation=False)


def test_black_level_stats_measure_the_render_and_the_lab_background():
    images = np.zeros((5, 40, 60, 3), np.uint8)
    images[:, 15:25, 25:35] = 200
    images[:, 15, 25:35] = 10  # a dark rim of the target, below t = 0.07
    b = black_level_stats(images, 0.07, 0.02, 0.0, seed=0)
    assert b["render_black"] == pytest.approx(1 - 100 / 2400) and b["target_erased"] == pytest.approx(0.1)
    assert 0.05 < b["lab_black_999"] < 0.08 and 0 < b["lab_passed"] < 0.01
    # frames over a background with a sensor offset (no exact black) would count their sky as the target's
    offset = images.copy()
    offset[offset == 0] = 5
    mixed = np.concatenate([images, offset])
    kinds = np.array(["black"] * 5 + ["space"] * 5)
    assert black_level_stats(mixed, 0.07, 0.02, 0.0, seed=0, backgrounds=kinds) == b
    assert black_level_stats(mixed, 0.07, 0.02, 0.0, seed=0)["target_erased"] > 0.5  # the flaw it avoids
    with pytest.raises(ValueError, match="none of the 5 given has one .*background share of 1"):
        black_level_stats(offset, 0.07, 0.02, 0.0, seed=0, backgrounds=np.array(["earth"] * 5))


def test_tilt_and_roll_split_the_attitude_error_about_the_line_of_sight():
    from pipeline.geometry.rotations import matrix_to_6d, rotvec_to_matrix

    t = np.array([[0.0, 0.0, 30.0]] * 3)
    r = [
        rotvec_to_matrix([0, 0, np.deg2rad(4)]),
        rotvec_to_matrix([np.deg2rad(3), 0, 0]),
        rotvec_to_matrix([0, np.deg2rad(3), np.deg2rad(4)]),
    ]
    pred = np.concatenate([t, matrix_to_6d(np.stack(r))], 1)
    target = np.concatenate([t, matrix_to_6d(np.stack([np.eye(3)] * 3))], 1)
    tilt, roll = tilt_roll_deg(pred, target)
    np.testing.assert_allclose(tilt[:2], [0, 3], atol=1e-6)
    np.testing.assert_allclose(roll[:2], [4, 0], atol=1e-6)
    assert 2.5 < tilt[2] < 3.5 and 3.5 < roll[2] < 4.5


@pytest.mark.parametrize(
    "key, value, message",
    [
        ("eps", 0.0, r"train.adversarial.eps must be a positive number in \(0, 1\]"),
        ("eps", 1.5, r"train.adversarial.eps must be a positive number in \(0, 1\]"),
        ("steps", 0, r"train.adversarial.steps must be a positive whole number in \[1, 1000\]"),
        ("black_level", 0.03, r"train.adversarial: black_level \(0.03\) must exceed eps \(0.05\)"),
        ("black_level", 1.0, r"train.adversarial.black_level must be a number in \[0, 1\)"),
        ("fraction", 1.0, r"train.adversarial: attacked_rotation: false needs fraction < 1"),
        (
            "start",
            "lift",
            r"train.adversarial: black_level \(0.03\) must exceed eps \(0.05\) unless start: lift and "
            r"bpda: true",
        ),  # black_level 0.03, bpda off
        ("objectives", ["speed"], r"train.adversarial.objectives"),
    ],
)
def test_bad_adversarial_params_are_refused_in_one_line_naming_the_key(tmp_path, monkeypatch, key, value, message):
    monkeypatch.chdir(tmp_path)
    p = params_mod.compose("smoke")
    # Each case on a budget below the clamp, the random start, no BPDA and the position objective alone (the
    # profiles ship eps 0.1 past the clamp with the lifting start, BPDA and attitude), so one key is wrong at a time.
    p["train"]["adversarial"].update(
        eps=0.05, start="random", bpda=False, objectives=[], objective_eps=[], attacked_rotation=False
    )
    p["train"]["adversarial"][key] = value
    if key == "start":
        p["train"]["adversarial"]["black_level"] = 0.03
    params_mod.write_params(p)
    with pytest.raises(ParamsError, match=message) as err:
        params_mod.load()
    assert "\n" not in str(err.value)


def test_a_budget_past_the_clamp_is_accepted_with_the_lifting_start_and_bpda(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    p = params_mod.compose("smoke")
    p["train"]["adversarial"].update(
        eps=0.1, black_level=0.07, start="lift", bpda=True, objectives=["position", "attitude"], attacked_rotation=True
    )
    params_mod.write_params(p)
    a = adversarial_config(params_mod.load().train.adversarial)
    assert a.unmasked() and a.eps == 0.1 and a.objectives == ("position", "attitude")


def test_robust_stage_writes_the_model_its_page_and_a_loader_reads_it(dataset, monkeypatch):
    from stages.train import main

    main(params_mod.load())
    main(params_mod.load(), robust=True)
    m = json.loads(Path("reports/metrics/robust.json").read_text())
    assert m["standard"]["test"]["n"] == m["robust"]["test"]["n"] == 16 and m["robust"]["suite"]["frames"] == 8
    for name in ("standard", "robust"):  # the suite's worst case per eps, each member's rows and the checks
        table = m[name]["suite"]
        assert [(r["attack"], r["eps"]) for r in table["rows"] if r["attack"] in ("clean", "suite")] == [
            ("clean", 0.0),
            ("suite", 0.01),
            ("suite", 0.1),
        ]
        assert {r["attack"] for r in table["rows"]} == {"clean", "suite", "bpda/position", "bpda/attitude"}
        assert len(table["sanity"]) == 4 and all(r["ok"] for r in table["sanity"])
        assert table["stability"]["frames"] == table["full_check"]["frames"] == 2
        assert list(table["backgrounds"]) == ["black"] and table["backgrounds"]["black"][0]["n"] == 8
    # the capacity comes from the validation frames (the standard model's split), never from test frames
    val = data.fit_and_validation_splits(params_mod.load(), seed_for(params_mod.load().seed, "train"))[1]
    test = set(data.load_split(params_mod.load(), "test").labels["index"])
    for name in ("standard", "robust"):
        frames, overbounds, meta = read_capacity("datasets/capacity", name)
        assert set(frames["index"]) == set(val.labels["index"]) and not set(frames["index"]) & test
        eps = [c.eps for c in overbounds]
        assert len(frames) == len(eps) * len(val) and eps == [0.01, 0.02, 0.05] and meta["split"] == "val"
        wide = frames.pivot(index="index", columns="eps", values="along_m")
        assert (wide[0.05] >= wide[0.02]).all() and (wide[0.02] >= wide[0.01]).all()  # nested in eps
        assert m["capacity"][name]["per_eps"][0]["count"] == [len(val)]
    assert m["robust"]["train_minutes"] > 0 and m["standard"]["train_minutes"] > 0
    a = params_mod.load().train.adversarial  # 1 epoch each; PGD-k on a share of each batch (+1: TRADES's pairs)
    assert a.trades > 0
    assert m["robust"]["gradients"] == round((1 + (a.steps + 1) * a.fraction) * m["standard"]["gradients"]) > 0
    page = Path("reports/pose_robust.md").read_text()
    assert "Black-level clamp t = 0.07" in page and "## Under the strongest attack suite" in page
    assert "## Attacker capacity (validation frames)" in page and "no Earth frames to split" in page
    pose = models.load_pose(params_mod.load(), POSE_ROBUST)
    assert pose.model.black_level == 0.07 and pose.model(torch.rand(1, 3, H, W)).shape == (1, 9)
    assert list(Path("dvclive/robust").glob("**/val_adv_pos_m.tsv"))
    other = params_mod.load()
    other = dataclasses.replace(
        other,
        train=dataclasses.replace(
            other.train, adversarial=dataclasses.replace(other.train.adversarial, black_level=0.08)
        ),
    )
    with pytest.raises(StageError, match=r"black_level=0.07 \(params: 0.08\)"):
        models.load_pose(other, POSE_ROBUST)
    # `rpod suite` (optional/dvc.yaml): the full suite and the lean one on every test frame of both models
    from stages.suite import main as suite

    suite(params_mod.load())
    full = json.loads(Path("reports/metrics/suite.json").read_text())["models"]["robust"]
    assert full["full"]["frames"] == full["lean"]["frames"] == 16 and len(full["full"]["members"]) == 12
    assert full["lean"]["full_check"]["frames"] == 16 and all(r["ok"] for r in full["full"]["sanity"])
    assert "## Worst case: the full suite" in Path("reports/suite.md").read_text()
    _suite_parts_are_kept_and_read(suite, monkeypatch)


def _suite_parts_are_kept_and_read(suite, monkeypatch) -> None:
    """`rpod suite` keeps a part per model, suite and eps; a second run reads them all (no attack), --partial writes
    the page from what is kept, --minutes stops before a missing part, and the parts scripts/suite_parts.py runs
    from an exported job are read as the stage's own."""
    from script_loader import load_script

    import pipeline.attacks.strongest as strongest

    eps, metrics = params_mod.load().suite.eps, Path("reports/metrics/suite.json")
    first = json.loads(metrics.read_text())["models"]
    assert len(list(Path("datasets/suite").glob("*.npz"))) == 4 * len(eps)
    attack = strongest.run_member

    def no_attack(*args, **kwargs):
        raise AssertionError("a kept part was attacked again")

    monkeypatch.setattr(strongest, "run_member", no_attack)
    suite(params_mod.load())
    assert json.loads(metrics.read_text())["models"] == first
    gone = f"standard-lean-{eps[-1]:g}.npz"
    Path("datasets/suite", gone).unlink()
    suite(params_mod.load(), partial=True)
    m = json.loads(metrics.read_text())
    assert m["missing"] == [gone] and m["models"]["robust"]["full"]["eps"] == eps
    assert m["models"]["standard"]["full"]["eps"] == m["models"]["standard"]["lean"]["eps"] == eps[:-1]
    page = Path("reports/suite.md").read_text()
    assert "**Partial run**" in page and gone.removesuffix(".npz") in page and "not run" in page
    with pytest.raises(StageError, match="minute budget"):
        suite(params_mod.load(), minutes=0.0)
    script = load_script("suite_parts")
    script.export(Path("job"))
    with pytest.raises(SystemExit, match="the job folder nojob cannot be read .*plan.json"):
        script.run(Path("nojob"), Path("out"), None, "cpu", [])
    monkeypatch.setattr(strongest, "run_member", attack)
    assert script.run(Path("job"), Path("out"), None, "cpu", ["standard/lean"]) == 0
    assert sorted(p.name for p in Path("out").glob("*.npz")) == sorted(f"standard-lean-{e:g}.npz" for e in eps)
    Path("out", gone).rename(Path("datasets/suite", gone))
    monkeypatch.setattr(strongest, "run_member", no_attack)
    suite(params_mod.load())
    m = json.loads(metrics.read_text())
    assert m["missing"] == [] and _untimed(m["models"]) == _untimed(first)  # the same attacks, timed again


def _untimed(tree):
    """A metrics tree less its timings (seconds per frame)."""
    if isinstance(tree, dict):
        return {k: _untimed(v) for k, v in tree.items() if not k.endswith("seconds_per_frame")}
    return [_untimed(v) for v in tree] if isinstance(tree, list) else tree
