"""95% intervals for the rates every report publishes: one helper, used by every stage.

- ``wilson(k, n)``: Wilson score interval of a proportion of independent trials (frames drawn
  independently, SHAP samples), from SciPy's ``binomtest(...).proportion_ci(method="wilson")``.
- ``bootstrap_rate(hits, groups)``: percentile bootstrap over groups (trajectories, sequences) for
  rates whose frames are correlated within a group, from ``scipy.stats.bootstrap``; the statistic is
  the pooled rate sum(hits) / n over the resampled groups.
- ``clopper_pearson(k, n)``: the exact (Clopper-Pearson) interval of k events in n independent trials
  (trajectories: an HMI count over independent approaches), from SciPy's ``binomtest`` (method "exact",
  beta quantiles), conservative at any n, [0, 1 - (alpha/2)^(1/n)] at k = 0.
- ``Rate``: a rate with its interval, formatted as ``"96.5 [95.1, 97.6]"`` (percent) for reports.
- ``percent_ci(value, ci)``: the one formatter of a percent with its interval in every report;
  ``percent_of(rate)`` the same for a rate as the metrics JSON stores it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np
from scipy import stats as sps

LEVEL = 0.95


def percent_ci(
    value: float | None,
    ci: Sequence[float | None] | None = None,
    decimals: int = 1,
    unit: str = "",
    signed: bool = False,
) -> str:
    """A rate in [0, 1] as `100 * value` with `decimals` places and `unit` (e.g. "%"; "-" when None),
    then its 95% interval " [lo, hi]" in percent when `ci` holds one: "94.1 [92.4, 95.4]"; `signed`: a difference
    of rates in points, every figure with its sign ("+1.2 [-0.4, +2.9]").
    Every percent-with-interval in the reports is written by this one function."""
    lo, hi = ci or (None, None)
    f = f"{'+' if signed else ''}.{decimals}f"
    head = "-" if value is None else f"{100 * value:{f}}{unit}"
    return head + ("" if lo is None else f" [{100 * lo:{f}}, {100 * hi:{f}}]")


def percent_of(rate: Mapping[str, Any] | None, decimals: int = 1) -> str:
    """`percent_ci` of a rate as the metrics JSON stores it ({"value", "ci": [lo, hi]} and, where counted, "n"):
    "-" when it is missing, has no value or counts no trial."""
    if not rate or rate.get("value") is None or ("n" in rate and not rate["n"]):
        return "-"
    return percent_ci(rate["value"], rate["ci"], decimals)


@dataclass(frozen=True)
class Rate:
    """A proportion in [0, 1] with its 95% interval; ``value`` is NaN when ``n`` is 0."""

    value: float
    lo: float
    hi: float
    n: int

    def pct(self, decimals: int = 1) -> str:
        """``"96.5 [95.1, 97.6]"``: percent with the interval, or ``"-"`` when there is no trial."""
        return "-" if self.n == 0 else percent_ci(self.value, (self.lo, self.hi), decimals)

    def ci(self) -> list[float | None]:
        """``[lo, hi]`` for JSON (``None`` when there is no trial)."""
        return [None, None] if self.n == 0 else [float(self.lo), float(self.hi)]


def wilson(k: int, n: int, level: float = LEVEL) -> Rate:
    """Wilson score interval of ``k`` successes in ``n`` independent trials."""
    return _binomial(k, n, level, "wilson")


def clopper_pearson(k: int, n: int, level: float = LEVEL) -> Rate:
    """Clopper-Pearson (exact) interval of ``k`` events in ``n`` independent trials (two-sided, ``level``)."""
    return _binomial(k, n, level, "exact")


def _binomial(k: int, n: int, level: float, method: str) -> Rate:
    """``k`` of ``n`` with SciPy's binomial interval ``method``; bad counts are one line naming the method."""
    k, n = int(k), int(n)
    if n < 0 or k < 0 or k > n:
        name = "wilson" if method == "wilson" else "clopper_pearson"
        raise ValueError(f"{name}: need 0 <= k <= n, got k={k}, n={n}")
    if n == 0:
        return Rate(float("nan"), float("nan"), float("nan"), 0)
    ci = sps.binomtest(k, n).proportion_ci(confidence_level=level, method=method)
    return Rate(k / n, float(ci.low), float(ci.high), n)


def rate(mask: np.ndarray, level: float = LEVEL) -> Rate:
    """Wilson interval of the fraction of ``True`` in a boolean array (independent trials)."""
    mask = np.asarray(mask, dtype=bool).ravel()
    return wilson(int(mask.sum()), mask.size, level)


def bootstrap_rate(
    hits: np.ndarray, groups: np.ndarray, level: float = LEVEL, n_resamples: int = 2000, seed: int = 0
) -> Rate:
    """Rate of ``hits`` (boolean per frame) with a percentile bootstrap over ``groups`` (ids per frame).

    Frames of one group (a trajectory) are resampled together, so correlation inside a group widens
    the interval as it should. With a single group the interval falls back to Wilson (and says so by
    being the independent-trials one, which is then optimistic).
    """
    hits = np.asarray(hits, dtype=bool).ravel()
    groups = np.asarray(groups).ravel()
    if hits.shape != groups.shape:
        raise ValueError(f"bootstrap_rate: hits {hits.shape} and groups {groups.shape} differ in shape")
    if hits.size == 0:
        return Rate(float("nan"), float("nan"), float("nan"), 0)
    ids = np.unique(groups)
    k = np.array([hits[groups == g].sum() for g in ids], dtype=float)
    n = np.array([(groups == g).sum() for g in ids], dtype=float)
    value = k.sum() / n.sum()
    if ids.size < 2:
        w = wilson(int(k.sum()), int(n.sum()), level)
        return Rate(value, w.lo, w.hi, int(n.sum()))
    res = sps.bootstrap(
        (k, n),
        lambda kk, nn, axis=-1: kk.sum(axis=axis) / nn.sum(axis=axis),
        paired=True,
        vectorized=True,
        n_resamples=n_resamples,
        confidence_level=level,
        method="percentile",
        random_state=np.random.default_rng(seed),
    )
    lo, hi = float(res.confidence_interval.low), float(res.confidence_interval.high)
    return Rate(value, min(lo, value), max(hi, value), int(n.sum()))


def mean_interval(values: np.ndarray, floor: float | None = None) -> tuple[float, float, float]:
    """(mean, low, high): the mean with its 95% Student-t interval (low = high = mean for n < 2), intersected with
    [floor, inf) when the values cannot lie below `floor` (errors: 0): the true mean lies there too, so the
    intersection keeps the coverage and the interval never reaches an impossible value."""
    values = np.asarray(values, np.float64)
    mean = float(values.mean())
    n = len(values)
    half = float(sps.t.ppf(0.5 + LEVEL / 2, n - 1)) * float(values.std(ddof=1)) / np.sqrt(n) if n > 1 else 0.0
    low = mean - half if floor is None else max(mean - half, float(floor))
    return mean, low, mean + half
