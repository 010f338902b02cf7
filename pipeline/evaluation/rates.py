"""Detection rates beside accuracy: a per-frame accuracy mixes two rates with the attacked fraction.

With f the fraction of frames that are attacked, TPR the share of attacked frames flagged and FPR the
share of clean frames flagged,

    accuracy = f TPR + (1 - f)(1 - FPR),

so one detector scores very differently on test sets that attack different fractions of their frames
(a detector that flags nothing scores 1 - f). `detection_rates` returns the four numbers, each with its
95% interval, and `DetectionRates.accuracy_at(f')` the accuracy the same TPR and FPR give at another
attacked fraction f' (e.g. the paper's: `pipeline.attacks.schedule.attacked_fraction`).

Intervals (`interval` says which):
- "wilson" (frames taken as independent trials): Wilson score intervals for TPR, FPR and f, and for the
  accuracy itself, which is also a proportion (correct frames of all frames). The re-weighted accuracy
  holds f' fixed and is a positive combination of two independent proportions (TPR over the attacked
  frames, 1 - FPR over the clean ones): its interval is MOVER-Wilson (Zou & Donner 2008, the method of
  Newcombe 1998 for a difference of proportions, for a weighted sum): the Wilson limits of each term
  recombined as value -/+ sqrt(sum of squared weighted distances to them).
- "bootstrap" (frames correlated within groups, e.g. trajectories): the percentile bootstrap over the
  groups of `pipeline.stats.bootstrap_rate` for TPR, FPR, f and accuracy (so they equal the
  intervals the integrated pages already print), and the same resampling of whole groups for the
  re-weighted accuracy. With a single group it falls back to "wilson".
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import stats as sps

from pipeline.stats import LEVEL, Rate, bootstrap_rate, wilson

COUNTS = ("flagged_attacked", "attacked", "flagged_clean", "clean")  # the columns of `DetectionRates.counts`


@dataclass(frozen=True, eq=False)
class DetectionRates:
    """Accuracy, TPR, FPR and attacked fraction of one set of flagged frames, each a `Rate` with its 95% interval.

    `counts` (G, 4) int: per group (one row when the frames are not grouped) the flagged attacked frames,
    attacked frames, flagged clean frames and clean frames (`COUNTS`); `interval` is "wilson" or "bootstrap".
    """

    accuracy: Rate
    tpr: Rate
    fpr: Rate
    attacked_fraction: Rate
    counts: np.ndarray
    interval: str

    def accuracy_at(self, f: float) -> Rate:
        """The accuracy f TPR + (1 - f)(1 - FPR) at attacked fraction `f` in [0, 1], with its 95% interval
        (MOVER-Wilson, or the bootstrap over groups; see the module). NaN when a term with a non-zero
        weight has no frame (e.g. no attacked frame and f > 0), with n = 0; else `n` is the number of frames."""
        f = float(f)
        if not 0.0 <= f <= 1.0:
            raise ValueError(f"attacked fraction must be in [0, 1], got {f}")
        tp, n_att, fp, n_clean = self.counts.sum(axis=0)
        n = int(n_att + n_clean)
        value = _weighted(f, tp, n_att, fp, n_clean)
        if math.isnan(value):
            return Rate(float("nan"), float("nan"), float("nan"), 0)
        if self.interval == "bootstrap":
            lo, hi = _bootstrap_weighted(f, self.counts)
            return Rate(value, min(lo, value), max(hi, value), n)
        spec = (1.0 - self.fpr.value, 1.0 - self.fpr.hi, 1.0 - self.fpr.lo)
        terms = [
            (w, p, lo, hi)
            for w, (p, lo, hi) in ((f, (self.tpr.value, self.tpr.lo, self.tpr.hi)), (1.0 - f, spec))
            if w > 0
        ]
        lo = value - math.sqrt(sum((w * (p - lo)) ** 2 for w, p, lo, _ in terms))
        hi = value + math.sqrt(sum((w * (hi - p)) ** 2 for w, p, _, hi in terms))
        return Rate(value, max(lo, 0.0), min(hi, 1.0), n)

    def as_json(self, f: float | None = None) -> dict[str, object]:
        """For a metrics JSON: each rate as {"value", "ci": [lo, hi], "n"}, the interval method, and with `f`
        the re-weighted accuracy under "accuracy_at" (plus its "f"). NaN values become None."""

        def one(r: Rate) -> dict[str, object]:
            return {"value": None if math.isnan(r.value) else float(r.value), "ci": r.ci(), "n": int(r.n)}

        out: dict[str, object] = {k: one(getattr(self, k)) for k in ("accuracy", "tpr", "fpr", "attacked_fraction")}
        out["interval"] = self.interval
        if f is not None:
            out["accuracy_at"] = {"f": float(f), **one(self.accuracy_at(f))}
        return out


def _weighted(f: float, tp: float, n_att: float, fp: float, n_clean: float) -> float:
    """f TPR + (1 - f)(1 - FPR) from counts; a term of weight 0 is left out, a needed term without frames is NaN."""
    value = 0.0
    for w, k, n, flip in ((f, tp, n_att, False), (1.0 - f, fp, n_clean, True)):
        if w == 0:
            continue
        if n == 0:
            return float("nan")
        value += w * ((1.0 - k / n) if flip else k / n)
    return value


def _bootstrap_weighted(f: float, counts: np.ndarray, n_resamples: int = 2000, seed: int = 0) -> tuple[float, float]:
    """Percentile bootstrap interval over the groups (rows of `counts`) of f TPR + (1 - f)(1 - FPR), resampling
    whole groups as `pipeline.stats.bootstrap_rate` does (same resamples and seed)."""

    def stat(tp: np.ndarray, n_att: np.ndarray, fp: np.ndarray, n_clean: np.ndarray, axis: int = -1) -> np.ndarray:
        with np.errstate(invalid="ignore", divide="ignore"):
            tpr = tp.sum(axis=axis) / n_att.sum(axis=axis)
            fpr = fp.sum(axis=axis) / n_clean.sum(axis=axis)
        return (f * tpr if f > 0 else 0.0) + ((1.0 - f) * (1.0 - fpr) if f < 1 else 0.0)

    cols = tuple(np.asarray(counts, dtype=float).T)
    res = sps.bootstrap(
        cols,
        stat,
        paired=True,
        vectorized=True,
        n_resamples=n_resamples,
        confidence_level=LEVEL,
        method="percentile",
        random_state=np.random.default_rng(seed),
    )
    return float(res.confidence_interval.low), float(res.confidence_interval.high)


def rates_from_counts(counts: np.ndarray, bootstrap: bool = False) -> DetectionRates:
    """`DetectionRates` from per-group counts (G, 4) (`COUNTS`: flagged attacked, attacked, flagged clean, clean).

    `bootstrap`: intervals by the bootstrap over the G groups (frames correlated within a group); otherwise,
    or with one group, Wilson (frames as independent trials). Raises ValueError on negative counts or more
    flagged frames than frames."""
    c = np.atleast_2d(np.asarray(counts, dtype=np.int64))
    if c.ndim != 2 or c.shape[1] != 4:
        raise ValueError(f"counts must be (groups, 4) = {COUNTS}, got shape {c.shape}")
    if (c < 0).any() or (c[:, 0] > c[:, 1]).any() or (c[:, 2] > c[:, 3]).any():
        raise ValueError("counts must be >= 0 with flagged frames <= frames in each group")
    tp, n_att, fp, n_clean = (int(v) for v in c.sum(axis=0))
    n = n_att + n_clean
    if bootstrap and len(c) >= 2:
        groups = np.arange(len(c))

        def boot(k: np.ndarray, m: np.ndarray) -> Rate:
            hits = np.concatenate([np.r_[np.ones(a, bool), np.zeros(b - a, bool)] for a, b in zip(k, m)])
            return bootstrap_rate(hits, np.repeat(groups, m))

        return DetectionRates(
            accuracy=boot(c[:, 0] + c[:, 3] - c[:, 2], c[:, 1] + c[:, 3]),
            tpr=boot(c[:, 0], c[:, 1]),
            fpr=boot(c[:, 2], c[:, 3]),
            attacked_fraction=boot(c[:, 1], c[:, 1] + c[:, 3]),
            counts=c,
            interval="bootstrap",
        )
    return DetectionRates(
        accuracy=wilson(tp + n_clean - fp, n),
        tpr=wilson(tp, n_att),
        fpr=wilson(fp, n_clean),
        attacked_fraction=wilson(n_att, n),
        counts=c,
        interval="wilson",
    )


def detection_rates(attacked: np.ndarray, flagged: np.ndarray, groups: np.ndarray | None = None) -> DetectionRates:
    """Accuracy, TPR, FPR and attacked fraction of per-frame labels `attacked` and detector flags `flagged`
    (equal-length bool arrays), each with its 95% interval: Wilson when `groups` is None, else the bootstrap
    over the groups (ids per frame, e.g. the trajectory). Raises ValueError on unequal shapes."""
    attacked = np.asarray(attacked, dtype=bool).ravel()
    flagged = np.asarray(flagged, dtype=bool).ravel()
    if attacked.shape != flagged.shape:
        raise ValueError(f"attacked {attacked.shape} and flagged {flagged.shape} differ in shape")
    g = np.zeros(attacked.size, np.int64) if groups is None else np.asarray(groups).ravel()
    if g.shape != attacked.shape:
        raise ValueError(f"groups {g.shape} and attacked {attacked.shape} differ in shape")
    ids = np.unique(g)
    counts = np.array(
        [
            [
                np.sum(attacked[m] & flagged[m]),
                np.sum(attacked[m]),
                np.sum(~attacked[m] & flagged[m]),
                np.sum(~attacked[m]),
            ]
            for m in (g == i for i in ids)
        ],
        dtype=np.int64,
    ).reshape(-1, 4)
    return rates_from_counts(counts, bootstrap=groups is not None)


def rates_by_eps(attacked: np.ndarray, flagged: np.ndarray, eps: np.ndarray) -> dict[str, DetectionRates]:
    """`detection_rates` (Wilson) overall ("all") and per attack eps (key f"{eps:g}": every clean sample plus that
    eps's attacked ones), as `pipeline.detectors.metrics.metrics_by_eps` splits a detector's test samples."""
    attacked = np.asarray(attacked, dtype=bool)
    flagged = np.asarray(flagged, dtype=bool)
    eps = np.asarray(eps, dtype=np.float64)
    out = {"all": detection_rates(attacked, flagged)}
    for e in sorted(set(eps[attacked].tolist()), reverse=True):
        keep = ~attacked | np.isclose(eps, e)
        out[f"{e:g}"] = detection_rates(attacked[keep], flagged[keep])
    return out


def sequence_rates(rows: list[dict[str, object]]) -> dict[float, DetectionRates]:
    """Per eps, the rates of `pipeline.evaluation.sequences.evaluate_sequences` rows (one per eps and sequence,
    with counts flagged_attacked, attacked_frames, flagged_clean, clean_frames) pooled over the sequences, with
    the bootstrap over the sequences (their frames are correlated). Keys in the rows' order."""
    out: dict[float, list[list[int]]] = {}
    for r in rows:
        out.setdefault(float(r["eps"]), []).append(
            [int(r[k]) for k in ("flagged_attacked", "attacked_frames", "flagged_clean", "clean_frames")]
        )
    return {e: rates_from_counts(np.array(c), bootstrap=True) for e, c in out.items()}


def rate_difference(a: Rate, b: Rate) -> tuple[float, float, float]:
    """a - b with its 95% interval (value, lo, hi) from the two rates' own intervals by MOVER (Newcombe 1998, method
    10, when both are Wilson): lo = d - sqrt((a - a.lo)^2 + (b.hi - b)^2), hi = d + sqrt((a.hi - a)^2 + (b - b.lo)^2).
    For independent samples; on the same test samples (a paired comparison) it is conservative. NaN when either
    rate has no trial."""
    if a.n == 0 or b.n == 0:
        return float("nan"), float("nan"), float("nan")
    d = a.value - b.value
    return (d, d - math.hypot(a.value - a.lo, b.hi - b.value), d + math.hypot(a.hi - a.value, b.value - b.lo))


def paired_difference(
    a: np.ndarray,
    b: np.ndarray,
    f: float | None = None,
    f_b: float | None = None,
    n_resamples: int = 2000,
    seed: int = 0,
) -> tuple[float, float, float]:
    """(difference, lo, hi): the accuracy of per-group counts `a` minus that of `b` (each (G, 4), `COUNTS`; the same G
    groups in the same order, e.g. two detectors on the same trajectories, or one set of counts twice), each re-weighted
    to an attacked fraction when one is given (`f` for a, `f_b` for b: `DetectionRates.accuracy_at`; None = the plain
    accuracy), with the 95% percentile bootstrap interval that resamples the groups once for both (paired: what a
    trajectory does to both cancels). Raises ValueError on counts of other shapes; with one group the interval is the
    difference itself."""
    a, b = (np.atleast_2d(np.asarray(c, dtype=float)) for c in (a, b))
    if a.shape != b.shape or a.ndim != 2 or a.shape[1] != 4:
        raise ValueError(f"paired counts must both be (groups, 4), got {a.shape} and {b.shape}")

    def acc(c: np.ndarray, at: float | None) -> np.ndarray:  # c (..., G, 4) -> accuracy (...)
        tp, n_att, fp, n_clean = (c[..., k].sum(axis=-1) for k in range(4))
        if at is None:
            return (tp + n_clean - fp) / (n_att + n_clean)
        with np.errstate(invalid="ignore", divide="ignore"):
            return at * tp / n_att + (1.0 - at) * (1.0 - fp / n_clean)

    d = float(acc(a, f) - acc(b, f_b))
    if len(a) < 2:
        return d, d, d
    idx = np.random.default_rng(seed).integers(0, len(a), size=(n_resamples, len(a)))
    boot = acc(a[idx], f) - acc(b[idx], f_b)
    lo, hi = np.nanpercentile(boot, [50 * (1 - LEVEL), 50 * (1 + LEVEL)])
    return d, float(min(lo, d)), float(max(hi, d))
