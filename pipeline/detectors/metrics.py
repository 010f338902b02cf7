"""Detection metrics for scores where higher means "attacked" (label 1) and clean is label 0."""
from __future__ import annotations

import numpy as np
from sklearn import metrics as skm

from pipeline.evaluation.stats import wilson

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


def metrics_by_eps(labels: np.ndarray, scores: np.ndarray, eps: np.ndarray,
                   threshold: float) -> dict[str, dict[str, float]]:
    """`detection_metrics` overall ("all") and per attack eps: all clean samples + that eps's attacks."""
    labels, scores, eps = np.asarray(labels).astype(int), np.asarray(scores), np.asarray(eps, dtype=np.float64)
    out = {"all": detection_metrics(labels, scores, threshold)}
    clean = labels == 0
    for e in sorted(set(eps[labels == 1].tolist()), reverse=True):
        keep = clean | ((labels == 1) & np.isclose(eps, e))
        out[f"{e:g}"] = detection_metrics(labels[keep], scores[keep], threshold)
    return out


def roc_points(labels: np.ndarray, scores: np.ndarray) -> dict[str, np.ndarray]:
    """ROC curve points (fpr, tpr, threshold) for plotting."""
    fpr, tpr, thr = skm.roc_curve(np.asarray(labels).astype(int), np.asarray(scores, dtype=np.float64))
    return {"fpr": fpr, "tpr": tpr, "threshold": thr}


def roc_csv(labels: np.ndarray, scores: np.ndarray) -> str:
    """The ROC curve as CSV text: a `fpr,tpr` header, then one point per line (6 decimals)."""
    roc = roc_points(labels, scores)
    return "\n".join(["fpr,tpr"] + [f"{a:.6f},{b:.6f}" for a, b in zip(roc["fpr"], roc["tpr"])]) + "\n"
