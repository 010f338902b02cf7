"""Intervals: Wilson against the closed form computed by hand, bootstrap over groups."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline.stats import bootstrap_rate, percent_of, rate, wilson


def _wilson_by_hand(k: int, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z / (1 + z * z / n) * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    return centre - half, centre + half


@pytest.mark.parametrize("k,n", [(0, 10), (3, 10), (10, 10), (54, 100), (1197, 1200)])
def test_wilson_matches_hand_computed(k: int, n: int) -> None:
    r = wilson(k, n)
    lo, hi = _wilson_by_hand(k, n)
    assert r.value == pytest.approx(k / n)
    assert r.lo == pytest.approx(lo, abs=1e-9) and r.hi == pytest.approx(hi, abs=1e-9)


def test_wilson_known_value_and_format() -> None:
    # 8 of 10: the textbook Wilson interval is [0.490, 0.943]
    r = wilson(8, 10)
    assert (round(r.lo, 3), round(r.hi, 3)) == (0.490, 0.943)
    assert r.pct() == "80.0 [49.0, 94.3]"
    assert wilson(0, 0).pct() == "-" and wilson(0, 0).ci() == [None, None]


def test_wilson_refuses_bad_counts() -> None:
    with pytest.raises(ValueError, match="k <= n"):
        wilson(5, 3)


def test_rate_of_mask() -> None:
    assert rate(np.array([True, False, True, True])).value == pytest.approx(0.75)


def test_bootstrap_over_groups_is_wider_when_groups_differ() -> None:
    rng = np.random.default_rng(0)
    groups = np.repeat(np.arange(6), 200)
    # groups with very different rates: frames are correlated within a group
    p = np.repeat([0.05, 0.9, 0.1, 0.8, 0.2, 0.95], 200)
    hits = rng.random(groups.size) < p
    b = bootstrap_rate(hits, groups)
    w = rate(hits)
    assert b.value == pytest.approx(w.value)
    assert b.lo <= b.value <= b.hi
    assert (b.hi - b.lo) > 2 * (w.hi - w.lo)
    # deterministic for a seed
    assert bootstrap_rate(hits, groups) == b


def test_bootstrap_single_group_falls_back_to_wilson() -> None:
    hits = np.array([True] * 7 + [False] * 3)
    b = bootstrap_rate(hits, np.zeros(10))
    w = wilson(7, 10)
    assert (b.lo, b.hi) == (w.lo, w.hi)


def test_percent_of_formats_a_metrics_rate_and_dashes_what_has_none() -> None:
    r = wilson(12, 40)
    stored = {"value": r.value, "ci": r.ci(), "n": r.n}
    assert percent_of(stored) == r.pct() == "30.0 [18.1, 45.4]"
    assert percent_of(stored, 2) == r.pct(2)
    assert percent_of({"value": 0.5, "ci": [0.25, 0.75]}) == "50.0 [25.0, 75.0]"  # a rate stored without its count
    for empty in (None, {}, {"value": None, "ci": [None, None], "n": 3}, {"value": 0.5, "ci": [0.1, 0.9], "n": 0}):
        assert percent_of(empty) == "-"


def test_pages_format_stored_rates_with_the_one_helper() -> None:
    """No page writes its own wrapper around percent_ci for a stored rate (issue 36: one home)."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    for path in sorted((root / "stages").rglob("*.py")):
        text = path.read_text()
        assert 'percent_ci(r["value"], r["ci"]' not in text, f"{path}: use pipeline.stats.percent_of"
        assert 'percent_ci(x["value"], x["ci"]' not in text, f"{path}: use pipeline.stats.percent_of"


def test_percent_ci_writes_a_difference_of_rates_in_signed_points() -> None:
    """Issue 36: the ablation's differences in points go through the one formatter, every figure with its sign."""
    from pipeline.stats import percent_ci

    assert percent_ci(0.012, (-0.004, 0.029), signed=True) == "+1.2 [-0.4, +2.9]"
    assert percent_ci(-0.5, None, signed=True) == "-50.0"
    assert percent_ci(0.941, (0.924, 0.954)) == "94.1 [92.4, 95.4]"  # rates unsigned, as before


def test_mean_interval_is_students_t_and_floored_where_values_cannot_go() -> None:
    from scipy import stats as sps

    from pipeline.stats import mean_interval

    x = np.array([0.1, 0.2, 3.0])  # skewed, n = 3: the t interval reaches below 0
    mean, lo, hi = mean_interval(x)
    half = sps.t.ppf(0.975, 2) * x.std(ddof=1) / math.sqrt(3)
    assert (mean, lo, hi) == pytest.approx((1.1, 1.1 - half, 1.1 + half))
    assert lo < 0
    assert mean_interval(x, floor=0.0) == pytest.approx((1.1, 0.0, 1.1 + half))
    wide = np.linspace(1.0, 2.0, 50)  # far from the floor: the floor changes nothing
    assert mean_interval(wide, floor=0.0) == mean_interval(wide)
    assert mean_interval(np.array([2.5])) == (2.5, 2.5, 2.5)
