"""Accuracy, TPR, FPR and the attacked fraction with intervals; accuracy re-weighted to another attacked fraction;
the attacked fraction of the paper's schedule."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.attacks.schedule import attack_schedule, attacked_fraction
from pipeline.evaluation.rates import detection_rates, rates_by_eps, rates_from_counts, sequence_rates
from pipeline.stats import bootstrap_rate, wilson


def _frames(tp: int, n_att: int, fp: int, n_clean: int) -> tuple[np.ndarray, np.ndarray]:
    attacked = np.r_[np.ones(n_att, bool), np.zeros(n_clean, bool)]
    flagged = np.r_[np.ones(tp, bool), np.zeros(n_att - tp, bool), np.ones(fp, bool), np.zeros(n_clean - fp, bool)]
    return attacked, flagged


def test_rates_are_the_wilson_proportions_of_the_counts():
    r = detection_rates(*_frames(28, 100, 1, 80))
    assert r.interval == "wilson"
    assert (r.tpr.value, r.fpr.value) == (0.28, 1 / 80)
    assert (r.tpr.lo, r.tpr.hi) == (wilson(28, 100).lo, wilson(28, 100).hi)
    assert (r.fpr.lo, r.fpr.hi) == (wilson(1, 80).lo, wilson(1, 80).hi)
    assert r.attacked_fraction.value == pytest.approx(100 / 180)
    assert r.accuracy.value == pytest.approx((28 + 79) / 180)
    assert (r.accuracy.lo, r.accuracy.hi) == (wilson(107, 180).lo, wilson(107, 180).hi)


def test_accuracy_at_the_observed_fraction_is_the_observed_accuracy():
    r = detection_rates(*_frames(28, 100, 1, 80))
    at = r.accuracy_at(r.attacked_fraction.value)
    assert at.value == pytest.approx(r.accuracy.value)
    assert at.lo < at.value < at.hi


def test_accuracy_moves_with_the_attacked_fraction_as_f_tpr_plus_1_minus_f_specificity():
    """The paper's arithmetic: a detector with TPR 28% and FPR 0 scores 1 - 0.72 f; at f = 0.2 it scores 85.6%."""
    r = detection_rates(*_frames(280, 1000, 0, 1000))
    for f in (0.0, 0.2, 5 / 9, 1.0):
        assert r.accuracy_at(f).value == pytest.approx(f * 0.28 + (1 - f) * 1.0)
    assert r.accuracy_at(0.2).value == pytest.approx(0.856)
    assert r.accuracy_at(0.0).hi == 1.0 and r.accuracy_at(1.0).lo == pytest.approx(wilson(280, 1000).lo)


def test_the_mover_interval_recombines_the_wilson_limits():
    r = detection_rates(*_frames(60, 100, 5, 100))
    f = 0.3
    at = r.accuracy_at(f)
    t, s = wilson(60, 100), wilson(95, 100)  # TPR and the specificity 1 - FPR
    lo = at.value - np.hypot(f * (t.value - t.lo), (1 - f) * (s.value - s.lo))
    hi = at.value + np.hypot(f * (t.hi - t.value), (1 - f) * (s.hi - s.value))
    assert (at.lo, at.hi) == (pytest.approx(lo), pytest.approx(hi))
    # narrower than either term's own interval scaled up: the two errors are independent
    assert at.hi - at.lo < f * (t.hi - t.lo) + (1 - f) * (s.hi - s.lo)


def test_a_term_without_frames_is_nan_unless_its_weight_is_zero():
    r = detection_rates(np.zeros(10, bool), np.zeros(10, bool))  # no attacked frame
    assert np.isnan(r.tpr.value) and r.tpr.n == 0
    assert np.isnan(r.accuracy_at(0.5).value) and r.accuracy_at(0.5).pct() == "-"
    assert r.accuracy_at(0.0).value == 1.0


def test_grouped_rates_use_the_bootstrap_over_groups():
    rng = np.random.default_rng(1)
    groups = np.repeat(np.arange(8), 150)
    attacked = rng.random(groups.size) < 0.55
    p_flag = np.repeat(rng.uniform(0.05, 0.95, 8), 150)  # very different TPR per group
    flagged = np.where(attacked, rng.random(groups.size) < p_flag, rng.random(groups.size) < 0.01)
    g = detection_rates(attacked, flagged, groups)
    w = detection_rates(attacked, flagged)
    assert g.interval == "bootstrap"
    b = bootstrap_rate(flagged[attacked], groups[attacked])
    assert (g.tpr.lo, g.tpr.hi) == (b.lo, b.hi)  # the same interval the pages already print
    assert g.tpr.value == pytest.approx(w.tpr.value)
    assert g.tpr.hi - g.tpr.lo > 2 * (w.tpr.hi - w.tpr.lo)
    at_g, at_w = g.accuracy_at(0.2), w.accuracy_at(0.2)
    assert at_g.value == pytest.approx(at_w.value)
    assert at_g.lo <= at_g.value <= at_g.hi
    assert at_g.hi - at_g.lo > at_w.hi - at_w.lo


def test_counts_are_checked():
    with pytest.raises(ValueError, match="flagged frames <= frames"):
        rates_from_counts(np.array([[5, 3, 0, 10]]))
    with pytest.raises(ValueError, match="differ in shape"):
        detection_rates(np.zeros(3, bool), np.zeros(4, bool))
    with pytest.raises(ValueError, match=r"in \[0, 1\]"):
        detection_rates(*_frames(1, 2, 0, 2)).accuracy_at(1.5)


def test_as_json_carries_the_reweighted_accuracy():
    j = detection_rates(*_frames(28, 100, 1, 80)).as_json(0.2)
    assert j["accuracy_at"]["f"] == 0.2 and j["accuracy_at"]["value"] == pytest.approx(0.2 * 0.28 + 0.8 * 79 / 80)
    assert j["interval"] == "wilson" and len(j["tpr"]["ci"]) == 2


@pytest.mark.parametrize("p, length", [(0.2, 5), (0.2, 10), (0.05, 3)])
def test_the_schedule_fraction_is_the_long_run_share_of_attacked_frames(p, length):
    assert attack_schedule(200_000, p, length, seed=5).mean() == pytest.approx(attacked_fraction(p, length), abs=0.005)


def test_the_papers_schedules_attack_five_ninths_and_five_sevenths_of_the_frames():
    assert attacked_fraction(0.2, 5) == pytest.approx(5 / 9)  # integrated evaluation, 5-frame attacks
    assert attacked_fraction(0.2, 10) == pytest.approx(5 / 7)  # lab, 10-frame attacks
    with pytest.raises(ValueError, match="p_start"):
        attacked_fraction(0.0, 5)


def _rows(eps: float, counts: list[tuple[int, int, int, int]]) -> list[dict[str, object]]:
    return [
        {
            "eps": eps,
            "sequence": f"T{i + 1}",
            "flagged_attacked": a,
            "attacked_frames": b,
            "flagged_clean": c,
            "clean_frames": d,
        }
        for i, (a, b, c, d) in enumerate(counts)
    ]


def test_sequence_rates_pool_the_sequences_per_eps():
    rows = _rows(0.01, [(10, 110, 0, 90), (60, 100, 1, 100), (30, 120, 0, 80)]) + _rows(0.5, [(110, 110, 0, 90)] * 3)
    r = sequence_rates(rows)
    assert list(r) == [0.01, 0.5]
    assert r[0.01].interval == "bootstrap" and r[0.01].tpr.value == pytest.approx(100 / 330)
    assert r[0.01].attacked_fraction.value == pytest.approx(330 / 600)
    assert r[0.5].accuracy_at(0.2).value == 1.0


def test_rates_by_eps_keeps_every_clean_sample_in_each_eps_row():
    attacked = np.r_[np.zeros(500, bool), np.ones(200, bool)]
    eps = np.r_[np.zeros(500), np.full(100, 0.05), np.full(100, 0.01)]
    flagged = np.r_[np.zeros(498, bool), np.ones(2, bool), np.ones(100, bool), np.ones(19, bool), np.zeros(81, bool)]
    r = rates_by_eps(attacked, flagged, eps)
    assert list(r) == ["all", "0.05", "0.01"]
    assert r["0.01"].attacked_fraction.value == pytest.approx(100 / 600)
    assert r["0.01"].accuracy.value == pytest.approx((19 + 498) / 600)  # 86%: mostly clean samples
    assert r["0.01"].accuracy_at(5 / 9).value == pytest.approx(5 / 9 * 0.19 + 4 / 9 * 0.996)  # 55%


def test_the_pages_rate_tables_reweight_to_the_papers_fraction():
    from stages.pages.detect import paper_fraction
    from stages.pages.detect import rates_section as detect_rates
    from stages.pages.evaluate import rates_section

    assert paper_fraction() == pytest.approx(5 / 9)
    text = rates_section(_rows(0.01, [(28, 100, 0, 100), (30, 110, 1, 90)]), 5, {0.01: 97.67}, "trajectories")
    row = next(line for line in text.splitlines() if line.startswith("| 0.01"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert "accuracy at the paper's f = 55.6% (%)" in text
    assert cells[2].startswith("27.6 [") and cells[6] == "97.67"
    assert cells[7] == f"{100 * (0.9767 - 4 / 9) / (5 / 9):.1f}"  # 95.8: the least TPR 97.67% needs
    page = detect_rates({"all": detection_rates(*_frames(19, 100, 2, 500))})
    assert "accuracy at f = 55.6% (%)" in page and "| all   | 600 | 16.7 [" in page


def test_rate_difference_is_newcombes_method_10():
    """Newcombe (1998), Table II: 56/70 - 48/80 = 0.2000 [0.0524, 0.3339]; 9/10 - 3/10 = 0.6 [0.1705, 0.8090]."""
    from pipeline.evaluation.rates import rate_difference

    for (k1, n1, k2, n2), (lo, hi) in (((56, 70, 48, 80), (0.0524, 0.3339)), ((9, 10, 3, 10), (0.1705, 0.8090))):
        d, got_lo, got_hi = rate_difference(wilson(k1, n1), wilson(k2, n2))
        assert d == pytest.approx(k1 / n1 - k2 / n2)
        assert (round(got_lo, 4), round(got_hi, 4)) == (lo, hi)
    assert np.isnan(rate_difference(wilson(0, 0), wilson(1, 2))[0])


def test_the_papers_frame_count_and_step_cannot_both_hold():
    from stages.pages.paper import frames_note

    note = frames_note()
    assert "would each span 625 m" in note and "200 frames at 0.25 m" in note and "2 cm per frame" in note


def test_paired_difference_resamples_the_groups_together():
    from pipeline.evaluation.rates import paired_difference

    rng = np.random.default_rng(0)
    b = np.array([[rng.integers(0, 50), 50, rng.integers(0, 5), 50] for _ in range(10)])
    same = paired_difference(b, b)
    assert same == (0.0, 0.0, 0.0)
    a = b.copy()
    a[:, 0] = np.minimum(a[:, 0] + 20, 50)  # the same trajectories, 20 more attacked frames flagged each
    d, lo, hi = paired_difference(a, b)
    assert d == pytest.approx(((a[:, 0] - b[:, 0]).sum()) / 1000) and 0 < lo <= d <= hi
    d_f, lo_f, hi_f = paired_difference(a, b, f=0.5, f_b=0.5)
    assert d_f == pytest.approx(0.5 * (a[:, 0].sum() - b[:, 0].sum()) / 500) and lo_f <= d_f <= hi_f
    assert paired_difference(a[:1], b[:1])[1] == paired_difference(a[:1], b[:1])[0]  # one group: no interval
    reweighted = paired_difference(b, b, f=0.5)  # one detector: re-weighted to f = 0.5 minus as measured
    assert reweighted[0] == pytest.approx(0.0) and reweighted[1] <= 0 <= reweighted[2]  # b attacks half its frames
    with pytest.raises(ValueError, match="both be"):
        paired_difference(a, b[:3])
