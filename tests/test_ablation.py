"""Issue 38's 2 x 2 ablation (FGSM ours / paper-literal x protocol strict / paper) from arrays, and the SHAP values of
a protocol's samples under both FGSM variants."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from test_attacks import TinyLoss
from test_robustness import D, TinyPose

from pipeline.attacks.gradient import attack_loss
from pipeline.detectors.lstm import LSTMConfig
from pipeline.evaluation.ablation import (
    ProtocolSamples,
    attacked_features,
    flag_counts,
    learning_curve,
    protocol_split,
    protocol_values,
    run_ablation,
)
from pipeline.evaluation.protocols import paper_plan
from pipeline.shap import ExactShap, sample_plan

EPS = [0.01, 0.05]
FIT = {"epochs": 4, "patience": 2, "batch_size": 32, "lr": 1.0}


def test_protocol_values_share_the_clean_rows_and_differ_only_on_attacked_ones():
    torch.manual_seed(0)
    model = TinyPose().eval()
    shap = ExactShap(model.head.weight.detach(), torch.zeros(D))
    images = np.zeros((10, 6, 8, 3), np.uint8)
    images[:, 2:4, 3:5] = 120  # a grey target on a black background
    eps = np.array([0, 0, 0, 0.01, 0.05, 0, 0.01, 0.05, 0.05, 0], np.float32)
    out = protocol_values(
        model, shap, attack_loss("full", TinyLoss()), images, np.random.randn(10, 9), eps, batch_size=4
    )
    assert set(out) == {"ours", "paper"} and out["ours"].shape == (10, 9, D)
    clean = eps == 0
    assert np.array_equal(out["ours"][clean], out["paper"][clean])
    assert not np.allclose(out["ours"][~clean], out["paper"][~clean])  # -eps on the background only in "paper"
    with torch.no_grad():
        plain = model.forward_features(torch.from_numpy(images[clean]).permute(0, 3, 1, 2).float() / 255)
    assert np.allclose(out["ours"][clean], (model.head.weight.detach()[None] * plain[:, None]).numpy(), atol=1e-6)


def _samples(protocol: str, plan: dict[str, np.ndarray], sequence: np.ndarray, frame: np.ndarray) -> ProtocolSamples:
    """SHAP-like values: a fixed pattern per source image, plus a shift on attacked samples (larger for 'paper')."""
    rng = np.random.default_rng(3)
    base = rng.normal(size=(int(plan["index"].max()) + 1, 9, 16)).astype(np.float32)
    eps = plan["eps"].astype(np.float64)
    values = {v: base[plan["index"]] + (eps[:, None, None] > 0) * k for v, k in (("ours", 0.3), ("paper", 3.0))}
    return ProtocolSamples(
        protocol,
        eps,
        plan["index"],
        sequence[plan["index"]],
        frame[plan["index"]],
        {v: a.astype(np.float32) for v, a in values.items()},
    )


def test_the_ablation_fits_four_cells_and_only_the_paper_protocol_is_leaky():
    seq, frame = np.repeat(np.arange(20), 30), np.tile(np.arange(30), 20)
    split = np.where(np.random.default_rng(0).random(600) < 0.2, "test", "train")
    strict = _samples("strict", sample_plan(120, 60, EPS, np.arange(600), np.random.default_rng(1)), seq, frame)
    paper = _samples("paper", paper_plan(split, 120, 60, EPS, np.random.default_rng(1)), seq, frame)
    cells = run_ablation(
        [strict, paper], LSTMConfig(n_rows=9, n_features=16, hidden=8, dense=[8]), FIT, 0.2, 0.2, seed=0
    )
    assert [(c.attack, c.protocol) for c in cells] == [
        ("ours", "strict"),
        ("paper", "strict"),
        ("ours", "paper"),
        ("paper", "paper"),
    ]
    assert [c.leaky for c in cells] == [False, False, True, True]
    assert cells[0].shared == 0.0 and cells[2].shared > 0.3
    for c in cells:
        assert list(c.rates) == ["all", "0.05", "0.01"]
        assert c.rates["all"].accuracy.n == c.counts["test"]
        assert sum(c.counts.values()) == 240
    assert cells[3].rates["all"].tpr.value > 0.9  # the large shift is learnt
    # both FGSM variants of a protocol use one split: the same test samples
    assert cells[0].counts == cells[1].counts and cells[2].counts == cells[3].counts


def test_the_learning_curve_fits_nested_subsets_on_the_same_test_samples():
    seq, frame = np.repeat(np.arange(20), 30), np.tile(np.arange(30), 20)
    paper = _samples(
        "paper",
        paper_plan(np.where(np.arange(600) % 5 == 0, "test", "train"), 120, 60, EPS, np.random.default_rng(1)),
        seq,
        frame,
    )
    config = LSTMConfig(n_rows=9, n_features=16, hidden=8, dense=[8])
    small, half = learning_curve(paper, "paper", [0.25, 0.5], config, FIT, 0.2, 0.2, seed=0, eps_set="paper")
    (full,) = [c for c in run_ablation([paper], config, FIT, 0.2, 0.2, seed=0, eps_set="paper") if c.attack == "paper"]
    assert small.counts["train"] == round(0.25 * full.counts["train"]) and half.counts["train"] == round(
        0.5 * full.counts["train"]
    )
    assert small.counts["test"] == half.counts["test"] == full.counts["test"] and small.eps_set == "paper"
    assert full.detector is not None and full.detector.predict(paper.values["paper"][:3]).shape == (3,)


def test_sequence_features_attack_only_the_scheduled_frames_and_counts_follow_the_flags():
    torch.manual_seed(0)
    model = TinyPose().eval()
    images = np.zeros((6, 6, 8, 3), np.uint8)
    images[:, 2:4, 3:5] = 120
    targets, attacked = np.random.randn(6, 9).astype(np.float32), np.array([0, 1, 1, 0, 0, 1], bool)
    loss = attack_loss("full", TinyLoss())
    ours, paper = (
        attacked_features(model, loss, images, targets, attacked, v, 0.05, batch_size=4) for v in ("ours", "paper")
    )
    with torch.no_grad():
        clean = model.forward_features(torch.from_numpy(images).permute(0, 3, 1, 2).float() / 255).numpy()
    assert np.allclose(ours[~attacked], clean[~attacked]) and np.allclose(paper[~attacked], clean[~attacked])
    assert not np.allclose(ours[attacked], paper[attacked])  # the literal attack's -eps on the background

    class Threshold:  # flags a frame whose first SHAP value is large
        def predict_proba(self, values: np.ndarray) -> np.ndarray:
            return (values[:, 0, 0] > 0.5).astype(float)

    shap = ExactShap(torch.eye(9, D), torch.zeros(D))
    feats = np.zeros((5, D), np.float32)
    feats[[0, 3], 0] = 1.0  # frames 0 and 3 are flagged
    counts = flag_counts(
        [feats[:3], feats[3:]], [np.array([1, 1, 0], bool), np.array([0, 1], bool)], shap, Threshold(), 0.5
    )
    assert counts.tolist() == [[1, 2, 0, 1], [0, 1, 1, 1]]


def test_an_unknown_protocol_is_refused():
    with pytest.raises(ValueError, match="unknown detector protocol 'leaky'"):
        protocol_split("leaky", np.arange(10), np.zeros(10), 0.2, 0.2, 0)


@pytest.mark.slow
def test_the_ablation_stage_writes_its_page_and_metrics(tmp_path, monkeypatch):
    """render -> label -> eval_render --detector with stand-in models, then `rpod ablation` on the smoke profile: four
    cells, the paper protocol's marked leaky on the page and in the metrics."""
    import json

    from test_lab import stand_in_models
    from typer.testing import CliRunner

    from stages.cli import app
    from stages.config import params as params_mod
    from stages.config.schema import build

    monkeypatch.chdir(tmp_path)
    p = params_mod.compose("smoke", ["detect.epochs=2"])
    params_mod.write_params(p)
    stand_in_models(build(p))
    runner = CliRunner()
    out = runner.invoke(app, ["ablation"])
    assert out.exit_code != 0 and "detect_render" in str(out.exception)  # the detector split is not there yet
    for args in (["render"], ["label"], ["eval_render", "--detector"], ["eval_render"]):
        out = runner.invoke(app, args)
        assert out.exit_code == 0, (args, out.output, out.exception)
    from stages.engine.lab_sets import render_lab

    render_lab(build(p), tmp_path / "datasets" / "lab")  # the lab stage's recordings (its models are not needed here)
    out = runner.invoke(app, ["ablation"])
    assert out.exit_code == 0, (out.output, out.exception)
    m = json.loads((tmp_path / "reports/metrics/ablation.json").read_text())
    assert [(c["attack"], c["protocol"], c["leaky"], c["eps_set"]) for c in m["cells"]] == [
        (a, pr, pr == "paper", mix)
        for mix in ("ablation", "paper")
        for pr in ("strict", "paper")
        for a in ("ours", "paper")
    ]
    assert m["profile"] == "smoke" and set(m["cells"][0]["rates"]) == {"all", "0.05", "0.01"}
    assert m["cells"][0]["rates"]["all"]["accuracy_at"]["f"] == pytest.approx(5 / 9)
    assert set(m["curves"]) == {"ours/strict", "paper/paper"} and len(m["curves"]["ours/strict"]) == 2
    integrated, lab = m["sequences"]["integrated"], m["sequences"]["lab"]
    assert lab["paper_fraction"] == pytest.approx(5 / 7) and integrated["paper_fraction"] == pytest.approx(5 / 9)
    names = {"standard/ours", "standard/paper", *(f"{c['attack']}/{c['protocol']}/{c['eps_set']}" for c in m["cells"])}
    assert set(integrated["detectors"]) == names and set(lab["detectors"]) == names
    row = integrated["detectors"]["standard/paper"]["0.01"]
    assert len(row["counts"]) == 1 and row["counts"][0][1] + row["counts"][0][3] == 20  # one 20-frame trajectory
    text = (tmp_path / "reports/ablation.md").read_text()
    assert "| paper (leaky) |" in text and "| strict (ours) |" in text and "## Each factor's effect" in text
    assert "## On the evaluation and lab sequences" in text and "## Training samples" in text
    assert m["cells"][2]["shared_source"] > 0 and m["cells"][0]["shared_source"] == 0
