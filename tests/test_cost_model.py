"""benchmarks/cost_model.py: the prediction arithmetic on fake rates and the paper profile's unit counts
(no timings are measured here)."""

from __future__ import annotations

import pytest

from benchmarks import cost_model as cm
from stages.config import params as params_mod


def test_prediction_is_count_times_seconds_per_unit_and_stages_sum_their_units():
    counts = {"a": {"x": 10, "y": 0}, "b": {"x": 5, "y": 4}}
    rows = cm.predict(counts, {"x": 2.0, "y": 0.5})
    assert [(r["stage"], r["unit"], r["count"], r["rate"], r["seconds"]) for r in rows] == [
        ("a", "x", 10, 0.5, 20.0),
        ("b", "x", 5, 0.5, 10.0),
        ("b", "y", 4, 2.0, 2.0),
    ]  # a zero count is no row
    assert cm.stage_totals(rows) == {"a": 20.0, "b": 12.0}
    assert list(cm.stage_totals(cm.predict({"s": {"x": 1}, "t": {"x": 3}}, {"x": 1.0}))) == ["t", "s"]
    assert cm.unit_totals(rows) == {"x": 15, "y": 4}


@pytest.mark.parametrize("budget", [16.0, 3600.0])
def test_required_rates_fill_the_budget_in_the_measured_shares(budget):
    rows = cm.predict({"a": {"x": 10}, "b": {"x": 5, "y": 4}}, {"x": 2.0, "y": 0.5})
    need = cm.required_rates(rows, budget)
    assert sum(n / need[u] for u, n in cm.unit_totals(rows).items()) == pytest.approx(budget)
    assert need["x"] / need["y"] == pytest.approx(0.5 / 2.0)  # one common speed-up of every unit
    assert need["y"] == pytest.approx(4 / (budget * 2 / 32))


def test_schedule_and_training_counts():
    assert cm.attacked_fraction(0.2, 5) == pytest.approx(0.5) and cm.attacked_fraction(0.0, 5) == 0.0
    p = {"label": {"test_fraction": 0.2}, "train": {"val_fraction": 0.1}}
    assert cm.training_counts(1000, p, 10) == pytest.approx({"train": 7200.0, "forward": 1800.0})


def test_robustness_gradients_count_every_attack_row():
    p = {
        "attack": {"steps": 10},
        "robustness": {
            "eps": [0.1, 0.05],
            "unseen_eps": [0.2],
            "steps": 20,
            "transfer": ["pgd", "fgsm/position", "mifgsm"],
            "lambdas": [0, 10],
            "surrogate_attacks": ["fgsm"],
        },
    }
    # per eps: FGSM 1 + transfer (20 + 1 + 10) + adaptive 20 (lambda 0 is the plain PGD) + surrogate 1
    assert cm.robustness_gradients_per_frame(p) == 2 * (1 + 31 + 20 + 1) + 1


def test_paper_counts_follow_the_profile():
    paper, default = params_mod.compose("paper"), params_mod.compose("default")
    c = cm.paper_counts(paper, renders_per_step=0.5)
    n = 13 * paper["render"]["frames_per_sequence"]
    assert c["render"] == {"render": n}
    assert c["train"]["train"] == pytest.approx(paper["train"]["epochs"] * n * 0.8 * 0.9)
    assert c["guidance"]["render"] == pytest.approx(0.5 * c["guidance"]["forward1"])
    assert "lab_models" in c and "lab_models" not in cm.paper_counts(default)  # retrain: always vs auto
    assert set(c) >= {"attack", "shap", "detect", "eval_render", "calibrate", "evaluate", "surrogate", "robustness"}
