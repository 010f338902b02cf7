"""Detection metrics: per sample for scores where higher means "attacked" (label 1) and clean is
label 0 (`detection_metrics`), and per frame of a flagged sequence (`frame_metrics`).

Frame metrics count frames, as the paper does: accuracy = frames classified correctly / all frames,
where a frame is correct when its flag equals its attacked state. TPR = flagged attacked frames /
attacked frames, FPR = flagged clean frames / clean frames. The detection delay of a burst is the
number of frames from its first frame to its first flagged frame (0 = flagged at once); bursts
with no flag at all are counted as missed and have no delay.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from sklearn import metrics as skm

from pipeline.attacks.schedule import bursts
from pipeline.stats import wilson

METRICS = ("accuracy", "precision", "recall", "fpr", "roc_auc", "tpr_at_1pct_fpr")


def choose_threshold(scores: np.ndarray, labels: np.ndarray) -> float:
    """The threshold that maximises accuracy of `scores >= threshold` on (validation) data.

    Candidates are the midpoints between consecutive distinct scores (plus both ends); ties go to
    the candidate nearest the middle of the best run, so the margin to both classes is largest.
    """
    scores, labels = np.asarray(scores, dtype=np.float64), np.asarray(labels).astype(bool)
    values = np.unique(scores)
    if len(values) == 1:
        return float(values[0])
    candidates = np.concatenate([[values[0] - 1.0], (values[:-1] + values[1:]) / 2, [values[-1] + 1.0]])
    # for a candidate c, predicted positive = scores >= c
    pos_sorted = np.sort(scores[labels])
    neg_sorted = np.sort(scores[~labels])
    tp = len(pos_sorted) - np.searchsorted(pos_sorted, candidates, side="left")
    tn = np.searchsorted(neg_sorted, candidates, side="left")
    acc = (tp + tn) / len(scores)
    best = np.flatnonzero(acc == acc.max())
    return float(candidates[best[len(best) // 2]])


def detection_metrics(labels: np.ndarray, scores: np.ndarray, threshold: float) -> dict[str, float]:
    """Accuracy, precision, recall (TPR), false-positive rate, ROC-AUC and TPR at 1% FPR, with 95%
    Wilson intervals (`*_ci95`, [lo, hi]) for accuracy, recall and FPR (samples taken as independent).

    ROC-AUC and TPR at 1% FPR are threshold-free; they are NaN when only one class is present.
    """
    labels = np.asarray(labels).astype(int)
    scores = np.asarray(scores, dtype=np.float64)
    pred = (scores >= threshold).astype(int)
    tn, fp, fn, tp = skm.confusion_matrix(labels, pred, labels=[0, 1]).ravel()
    out = {
        "accuracy": float(skm.accuracy_score(labels, pred)),
        "precision": float(skm.precision_score(labels, pred, zero_division=0)),
        "recall": float(skm.recall_score(labels, pred, zero_division=0)),
        "fpr": float(fp / (fp + tn)) if fp + tn else float("nan"),
        "roc_auc": float("nan"),
        "tpr_at_1pct_fpr": float("nan"),
        "n": int(len(labels)),
        "accuracy_ci95": wilson(int(tp + tn), int(len(labels))).ci(),
        "recall_ci95": wilson(int(tp), int(tp + fn)).ci(),
        "fpr_ci95": wilson(int(fp), int(fp + tn)).ci(),
    }
    if len(np.unique(labels)) == 2:
        out["roc_auc"] = float(skm.roc_auc_score(labels, scores))
        fpr, tpr, _ = skm.roc_curve(labels, scores)
        out["tpr_at_1pct_fpr"] = float(tpr[fpr <= 0.01].max())
    return out


def metrics_by_eps(
    labels: np.ndarray, scores: np.ndarray, eps: np.ndarray, threshold: float
) -> dict[str, dict[str, float]]:
    """`detection_metrics` overall ("all") and per attack eps: all clean samples + that eps's attacks."""
    labels, scores, eps = np.asarray(labels).astype(int), np.asarray(scores), np.asarray(eps, dtype=np.float64)
    out = {"all": detection_metrics(labels, scores, threshold)}
    clean = labels == 0
    for e in sorted(set(eps[labels == 1].tolist()), reverse=True):
        keep = clean | ((labels == 1) & np.isclose(eps, e))
        out[f"{e:g}"] = detection_metrics(labels[keep], scores[keep], threshold)
    return out


def detection_delays(attacked_bursts: list[tuple[int, int]], flagged: np.ndarray) -> np.ndarray:
    """Per burst: frames from its start to its first flag, NaN when no frame of it was flagged."""
    flagged = np.asarray(flagged, dtype=bool)
    delays = np.full(len(attacked_bursts), np.nan)
    for k, (start, stop) in enumerate(attacked_bursts):
        hits = np.flatnonzero(flagged[start:stop])
        if len(hits):
            delays[k] = hits[0]
    return delays


@dataclass(frozen=True)
class FrameMetrics:
    """Frame-level detection figures for one sequence (rates in [0, 1]; NaN when undefined)."""

    frames: int
    attacked: int
    flagged: int
    accuracy: float
    tpr: float
    fpr: float
    bursts: int
    missed_bursts: int
    mean_delay: float  # frames, over bursts that were flagged at least once

    def as_dict(self) -> dict[str, float | int]:
        return asdict(self)


def _rate(num: int, den: int) -> float:
    """num / den, NaN when den is 0."""
    return float(num) / den if den else float("nan")


def frame_metrics(
    attacked: np.ndarray, flagged: np.ndarray, attacked_bursts: list[tuple[int, int]] | None = None
) -> FrameMetrics:
    """Accuracy (correct flags / all frames), TPR, FPR and burst delays of one flag sequence.

    `attacked_bursts` defaults to the runs of `attacked`; pass `schedule_bursts(...)` to count
    touching bursts separately.
    """
    attacked = np.asarray(attacked, dtype=bool)
    flagged = np.asarray(flagged, dtype=bool)
    if attacked.shape != flagged.shape or attacked.ndim != 1:
        raise ValueError(f"attacked {attacked.shape} and flagged {flagged.shape} must be equal 1-D shapes")
    n = len(attacked)
    tp = int(np.sum(attacked & flagged))
    fp = int(np.sum(~attacked & flagged))
    tn = int(np.sum(~attacked & ~flagged))
    b = bursts(attacked) if attacked_bursts is None else attacked_bursts
    delays = detection_delays(b, flagged)
    hit = delays[~np.isnan(delays)]
    return FrameMetrics(
        frames=n,
        attacked=int(attacked.sum()),
        flagged=int(flagged.sum()),
        accuracy=_rate(tp + tn, n),
        tpr=_rate(tp, int(attacked.sum())),
        fpr=_rate(fp, int((~attacked).sum())),
        bursts=len(b),
        missed_bursts=int(np.isnan(delays).sum()),
        mean_delay=float(hit.mean()) if len(hit) else float("nan"),
    )


def undetected_mask(attacked: np.ndarray, flagged: np.ndarray) -> np.ndarray:
    """Attacked frames the detector did not flag (the ones whose bad pose reaches guidance)."""
    return np.asarray(attacked, dtype=bool) & ~np.asarray(flagged, dtype=bool)


def mean_over(values: np.ndarray, mask: np.ndarray) -> float:
    """Mean of `values` where `mask` holds (e.g. pose error on undetected attacked frames); NaN if none."""
    values, mask = np.asarray(values, dtype=np.float64), np.asarray(mask, dtype=bool)
    return float(values[mask].mean()) if mask.any() else float("nan")
