"""Robustness stage: adaptive attack through the chain, corruptions, rows and their intervals, bad params."""

from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from tiny import FEATURES as D
from tiny import TinyPose
from torch import nn

from pipeline.attacks.adaptive import PerFrameChain, adaptive_objective, adaptive_pgd, check_lambdas
from pipeline.attacks.corruptions import CORRUPTIONS, corrupt
from pipeline.attacks.gradient import pgd, quantize
from pipeline.detectors.lstm import LSTMConfig, LSTMDetector
from pipeline.evaluation.robustness import attack_row, corruption_row, worst_by_eps, worst_over_lambda
from pipeline.pose.loss import PoseLoss
from pipeline.shap import ExactShap
from stages.config.params import load


@pytest.fixture()
def setup() -> tuple[PerFrameChain, TinyPose, torch.Tensor, torch.Tensor, PoseLoss]:
    torch.manual_seed(0)
    model = TinyPose().eval()
    detector = LSTMDetector(LSTMConfig(n_rows=9, n_features=D, hidden=8, dense=[4])).eval()
    x = torch.round(torch.rand(6, 3, 12, 16) * 255) / 255  # on the 8-bit grid, as camera frames
    with torch.no_grad():
        background = model.forward_features(torch.rand(20, 3, 12, 16))
        mu = background.mean(0)
        # standardise the SHAP rows as training would, so the logit depends on the image
        detector.set_normalisation((model.head.weight.unsqueeze(0) * (background - mu).unsqueeze(1)).numpy())
    chain = PerFrameChain(model, ExactShap(model.head.weight.detach(), mu), detector)
    y = torch.randn(6, 9)
    return chain, model, x, y, PoseLoss("mean")


def test_lambda_zero_is_plain_pgd(setup) -> None:
    chain, model, x, y, loss = setup
    ours = adaptive_pgd(chain, x, y, 0.05, loss, 0.0, steps=20, generator=torch.Generator().manual_seed(7))
    plain = pgd(model, x, y, 0.05, loss, steps=20, generator=torch.Generator().manual_seed(7))
    assert torch.equal(ours, plain)
    other_seed = adaptive_pgd(chain, x, y, 0.05, loss, 0.0, steps=20, generator=torch.Generator().manual_seed(8))
    assert not torch.equal(ours, other_seed)


def test_large_lambda_lowers_detector_logit(setup) -> None:
    chain, _, x, y, loss = setup

    def mean_logit(images: torch.Tensor) -> float:
        with torch.no_grad():
            return float(chain(quantize(images, x).float() / 255)[1].mean())

    plain = adaptive_pgd(chain, x, y, 0.1, loss, 0.0, steps=20, generator=torch.Generator().manual_seed(1))
    evasive = adaptive_pgd(chain, x, y, 0.1, loss, 100.0, steps=20, generator=torch.Generator().manual_seed(1))
    assert mean_logit(evasive) < mean_logit(plain) - 0.1
    assert mean_logit(evasive) < mean_logit(x)


@pytest.mark.parametrize("eps", [0.01, 0.05, 0.3])
@pytest.mark.parametrize("lam", [0.0, 10.0])
def test_stored_images_stay_within_eps(setup, eps: float, lam: float) -> None:
    chain, _, x, y, loss = setup
    adv = adaptive_pgd(chain, x, y, eps, loss, lam, steps=20, generator=torch.Generator().manual_seed(2))
    assert float((adv - x).abs().max()) <= eps + 1e-6 and adv.min() >= 0 and adv.max() <= 1
    stored = quantize(adv, x).int()
    levels = (stored - torch.round(x * 255).int()).abs()
    # 8-bit storage rounds each change to the nearest level: at most eps rounded to the nearest level
    assert int(levels.max()) <= math.floor(eps * 255 + 0.5)
    assert float(levels.float().max() / 255) <= eps + 0.5 / 255 + 1e-7


def test_adaptive_leaves_parameters_and_mode_alone(setup) -> None:
    chain, model, x, y, loss = setup
    adaptive_pgd(chain, x, y, 0.05, loss, 10.0, steps=20, generator=torch.Generator().manual_seed(3))
    # the pose model is shared with the evaluating chain: it must stay in eval mode (frozen BatchNorm)
    assert not chain.training and not model.training
    chain.train()
    before = copy.deepcopy(chain.state_dict())
    adaptive_pgd(chain, x, y, 0.05, loss, 10.0, steps=20, generator=torch.Generator().manual_seed(3))
    assert chain.training
    assert all(torch.equal(before[k], v) for k, v in chain.state_dict().items())
    assert all(p.grad is None for p in chain.parameters())


def test_chain_pose_is_the_model_and_logit_the_detector_on_shap(setup) -> None:
    chain, model, x, _, _ = setup
    pose, logit = chain(x)
    assert torch.equal(pose, model(x))
    phi = chain.shap.weight.unsqueeze(0) * (model.forward_features(x) - chain.shap.background_mean).unsqueeze(1)
    assert torch.allclose(logit, chain.detector(phi))


@pytest.mark.parametrize("bad", [[0, -1, 10], [], [float("nan")]])
def test_bad_lambdas_refused(bad: list[float]) -> None:
    with pytest.raises(ValueError, match="lambda"):
        check_lambdas(bad)
    if bad:
        with pytest.raises(ValueError, match="lambda"):
            adaptive_objective(PoseLoss("mean"), min(bad) if not math.isnan(bad[0]) else bad[0])


def _wilson(k: int, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z / (1 + z * z / n) * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    return centre - half, centre + half


def test_attack_row_rates_and_wilson_intervals() -> None:
    pos = np.array([0.5, 2.0, 3.0, 0.2, 1.5, 4.0, 0.9, 1.1, 2.2, 0.1])
    flag = np.array([1, 0, 1, 0, 0, 1, 0, 0, 1, 1], bool)
    row = attack_row("pgd", "transfer", 0.05, pos, flag, harm_m=1.0)
    assert row["n"] == 10 and row["adaptive"] is False and row["lambda"] is None
    assert row["detection_rate"] == pytest.approx(0.5)
    # harmful (> 1 m) and unflagged: 2.0, 1.5, 1.1
    assert row["harmful_undetected_rate"] == pytest.approx(0.3)
    assert row["position_error_m"] == pytest.approx(pos.mean())
    assert row["ci95_detection"] == pytest.approx(list(_wilson(5, 10)), abs=1e-9)
    assert row["ci95_harmful_undetected"] == pytest.approx(list(_wilson(3, 10)), abs=1e-9)
    assert row["ci95_harmful_undetected"] == pytest.approx([0.107791, 0.603222], abs=1e-6)
    adaptive = attack_row("adaptive pgd", "adaptive", 0.05, pos, flag, 1.0, lam=10)
    assert adaptive["adaptive"] is True and adaptive["lambda"] == 10.0


def test_rows_refuse_nan_and_shape_mismatch() -> None:
    with pytest.raises(ValueError, match="NaN"):
        attack_row("fgsm", "seen", 0.1, np.array([1.0, np.nan]), np.zeros(2, bool), 1.0)
    with pytest.raises(ValueError, match="equal"):
        corruption_row("blur", 1.0, np.ones(3), np.zeros(2, bool), np.zeros(3, bool))
    with pytest.raises(ValueError, match="equal"):
        corruption_row("blur", 1.0, np.ones(3), np.zeros(3, bool), np.zeros(2, bool))


def test_corruption_row_false_alarms() -> None:
    row = corruption_row(
        "jpeg", 40, np.array([0.1, 0.2, 0.3, 0.4]), np.array([0, 1, 0, 0], bool), np.array([0, 0, 0, 0], bool)
    )
    assert row["false_alarm_rate"] == pytest.approx(0.25)
    assert row["shipped_false_alarm_rate"] == 0.0
    assert row["ci95_false_alarm"] == pytest.approx(list(_wilson(1, 4)), abs=1e-9)
    assert row["position_error_m"] == pytest.approx(0.25)


def test_worst_over_lambda_keeps_the_attackers_best_image_per_frame() -> None:
    pos = [np.array([2.0, 0.5, 3.0, 0.2]), np.array([1.5, 2.0, 0.3, 0.1])]
    flags = [np.array([1, 0, 0, 1], bool), np.array([0, 1, 0, 1], bool)]
    p, f, pick = worst_over_lambda(pos, flags, harm_m=1.0)
    # frame 0: only lambda 1 is harmful and unflagged; frame 1: none harmful-unflagged, lambda 0 unflagged;
    # frame 2: lambda 0 harmful and unflagged; frame 3: both flagged, larger error wins
    assert pick.tolist() == [1, 0, 0, 0]
    assert p.tolist() == [1.5, 0.5, 3.0, 0.2] and f.tolist() == [False, False, False, True]
    row = attack_row("worst", "adaptive", 0.05, p, f, 1.0)
    singles = [attack_row("x", "adaptive", 0.05, a, b, 1.0)["harmful_undetected_rate"] for a, b in zip(pos, flags)]
    assert row["harmful_undetected_rate"] >= max(singles)


def test_worst_by_eps_picks_the_highest_harmful_undetected_row_per_eps() -> None:
    pos, none, some = np.full(10, 2.0), np.zeros(10, bool), np.arange(10) < 6
    rows = [
        attack_row("fgsm", "seen", 0.05, pos, some, 1.0),
        attack_row("adaptive pgd", "adaptive", 0.05, pos, none, 1.0, 10),
        attack_row("pgd", "transfer", 0.01, pos, some, 1.0),
    ]
    worst = worst_by_eps(rows)
    assert set(worst) == {"0.05", "0.01"}
    assert worst["0.05"]["attack"] == "adaptive pgd" and worst["0.05"]["lambda"] == 10.0
    assert worst["0.05"]["harmful_undetected_rate"] == 1.0 and worst["0.01"]["harmful_undetected_rate"] == 0.4


@pytest.fixture()
def frames() -> np.ndarray:
    rng = np.random.default_rng(0)
    return rng.integers(20, 230, size=(3, 18, 32, 3), dtype=np.uint8)


@pytest.mark.parametrize(
    "name,strength", [("noise", 0.03), ("blur", 1.5), ("jpeg", 40), ("brightness", 1.4), ("contrast", 0.7)]
)
def test_corruptions_change_frames_deterministically(frames: np.ndarray, name: str, strength: float) -> None:
    out = corrupt(name, strength, seed=3)(frames)
    assert out.dtype == np.uint8 and out.shape == frames.shape
    assert not np.array_equal(out, frames)
    assert np.array_equal(out, corrupt(name, strength, seed=3)(frames))


@pytest.mark.parametrize("name,identity", [("noise", 0.0), ("brightness", 1.0), ("contrast", 1.0)])
def test_neutral_strength_is_identity(frames: np.ndarray, name: str, identity: float) -> None:
    assert np.array_equal(corrupt(name, identity)(frames), frames)


def test_corruption_strengths_have_their_units(frames: np.ndarray) -> None:
    noisy = corrupt("noise", 0.02, seed=1)(frames).astype(float) - frames
    assert np.std(noisy) == pytest.approx(0.02 * 255, rel=0.1)
    bright = corrupt("brightness", 1.2)(frames).astype(float)
    assert bright.mean() == pytest.approx(1.2 * frames.mean(), rel=0.02)
    assert set(CORRUPTIONS) == {"noise", "blur", "jpeg", "brightness", "contrast"}


@pytest.mark.parametrize(
    "name,strength,match",
    [
        ("fog", 1.0, "unknown corruption"),
        ("jpeg", 0, "out of range"),
        ("noise", -0.1, "out of range"),
        ("blur", float("nan"), "out of range"),
    ],
)
def test_bad_corruptions_refused(name: str, strength: float, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        corrupt(name, strength)


def _params() -> dict:
    from stages.config.params import compose

    return compose("smoke")


@pytest.mark.parametrize(
    "key,value,match",
    [
        ("transfer", ["pgd", "cw"], r"robustness: transfer: unknown attack 'cw'"),
        ("transfer", ["fgsm/angle"], r"robustness: transfer: unknown attack 'fgsm/angle'"),
        ("surrogate_attacks", ["deepfool"], r"robustness: surrogate_attacks: unknown attack"),
        ("lambdas", [0, -1, 10], r"robustness: lambdas must be"),
        ("eps", [0.05, 1.5], r"robustness: eps: 1\.5 is not in \(0, 1\]"),
        ("eps", [0.0], r"robustness: eps: 0\.0 is not in \(0, 1\]"),
        ("unseen_eps", [-0.2], r"robustness: unseen_eps"),
        ("steps", 5, r"robustness: steps"),
        ("harm_m", 0, r"robustness: harm_m"),
        ("corruptions", {"jpeg": [0]}, r"robustness\.corruptions: jpeg"),
        ("corruptions", {"fog": [1]}, r"unknown parameter 'robustness\.corruptions\.fog'"),
    ],
)
def test_bad_params_stop_with_one_message(key: str, value: object, match: str) -> None:
    from stages.config.schema import build
    from stages.config.sections import ParamsError

    p = _params()
    build(p)
    if key == "corruptions":
        value = {**p["robustness"]["corruptions"], **value}
    p["robustness"][key] = value
    with pytest.raises(ParamsError, match=match):
        build(p)


def test_schema_attack_names_are_the_librarys() -> None:
    import typing

    from pipeline.attacks.gradient import ATTACKS, LOSSES
    from stages.config.evaluation import AttackLoss, AttackMethod

    assert typing.get_args(AttackMethod) == tuple(ATTACKS)
    assert typing.get_args(AttackLoss) == tuple(LOSSES)


def test_train_surrogate_writes_only_its_checkpoint_with_its_own_seed(tmp_path, monkeypatch) -> None:
    from test_training import write_dataset

    from pipeline.formats.models import read_pose
    from stages.artifacts.paths import POSE, SURROGATE
    from stages.train import main

    monkeypatch.chdir(tmp_path)
    torch.set_num_threads(1)
    write_dataset(tmp_path, overrides=["robustness.surrogate_seed=5", "robustness.surrogate_epochs=1"])
    main(load(), surrogate=True)
    assert SURROGATE.exists() and not POSE.exists()
    assert not any(Path(p).exists() for p in ("reports/pose.md", "reports/metrics/train.json", "dvclive/train"))
    surrogate = read_pose(SURROGATE)
    assert surrogate["meta"]["epoch"] == 1
    main(load(), surrogate=False)
    ours = read_pose(POSE)
    assert not torch.equal(ours["model"]["head_pos.weight"], surrogate["model"]["head_pos.weight"])


class BurstChain(nn.Module):
    """A stand-in temporal detector: frame t's logit reads the change of the pose-net features since
    frame t - 1 of the same burst (the batch, in time order), as a motion-consistency test would."""

    temporal = True

    def __init__(self, model: TinyPose) -> None:
        super().__init__()
        self.model = model
        self.score = nn.Linear(D, 1)

    def forward(self, images: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        f = self.model.forward_features(images)
        jump = torch.cat([torch.zeros_like(f[:1]), f[1:] - f[:-1]])
        return self.model.forward_head(f), self.score(jump.abs()).squeeze(1)


def test_a_temporal_chain_plugs_in_and_is_attacked_over_the_burst(setup) -> None:
    _, model, x, y, loss = setup
    torch.manual_seed(4)
    chain = BurstChain(model).eval()
    with torch.no_grad():
        chain.score.weight.abs_()  # larger feature jumps -> higher logit

    def mean_logit(images: torch.Tensor) -> float:
        with torch.no_grad():
            return float(chain(quantize(images, x).float() / 255)[1].mean())

    plain = adaptive_pgd(chain, x, y, 0.1, loss, 0.0, steps=20, generator=torch.Generator().manual_seed(5))
    evasive = adaptive_pgd(chain, x, y, 0.1, loss, 100.0, steps=20, generator=torch.Generator().manual_seed(5))
    assert mean_logit(evasive) < mean_logit(plain)
    # the burst is optimised jointly: alone, frame 0's logit is constant and only the pose loss moves
    # it; inside the burst it also moves to lower frame 1's logit (no random start: same start point)
    alone = adaptive_pgd(chain, x[:1], y[:1], 0.1, loss, 100.0, steps=20, random_start=False)
    in_burst = adaptive_pgd(chain, x, y, 0.1, loss, 100.0, steps=20, random_start=False)
    alone_pose_only = adaptive_pgd(chain, x[:1], y[:1], 0.1, loss, 0.0, steps=20, random_start=False)
    assert torch.equal(alone, alone_pose_only)
    assert not torch.equal(in_burst[:1], alone)


def test_burst_schedule_and_world_motion() -> None:
    from pipeline.evaluation.robustness import burst_schedule, world_motion
    from pipeline.geometry.rotations import matrix_to_6d
    from pipeline.geometry.trajectories import approach_trajectory

    assert burst_schedule(20, 5, 8) == [(8, 13)]
    assert burst_schedule(30, 5, 8) == [(8, 13), (16, 21), (24, 29)]
    s = approach_trajectory(30, (10.0, -12.0), seed=1, jitter_deg=1.0)
    R_cam, u = world_motion(np.hstack([s.t, matrix_to_6d(s.R)]))
    assert np.allclose(R_cam, s.R_cam, atol=1e-9)
    assert np.allclose(u[1:], np.diff(s.rel, axis=0), atol=1e-9)
