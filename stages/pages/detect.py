"""reports/detector.md, the page of `rpod detect`: the LSTM detector on the SHAP test split
beside the paper, and the baselines on the same split."""
from __future__ import annotations

import math
from typing import Any

from stages.config.sections import Detect

PAPER_ACCURACY = 0.9990


def detector_page(results: dict[str, dict[str, dict[str, float]]], scores: dict[str, Any], counts: dict[str, int],
                  result: Any, attrs: dict[str, Any], d: Detect) -> str:
    """reports/detector.md: the LSTM per eps, the baselines on the same split, and what the detectors see."""
    from pipeline.report.markdown import markdown_table

    def pct(m: dict[str, Any], key: str) -> str:
        """A rate in percent with its 95% Wilson interval, e.g. "94.1 [92.4, 95.4]"."""
        lo, hi = m.get(f"{key}_ci95") or (None, None)
        if m[key] is None or math.isnan(m[key]) or lo is None:
            return "-"
        return f"{100 * m[key]:.1f} [{100 * lo:.1f}, {100 * hi:.1f}]"

    def row(m: dict[str, Any]) -> dict[str, Any]:
        return {"n": m["n"], "accuracy (%)": pct(m, "accuracy"), "precision": m["precision"],
                "recall (%)": pct(m, "recall"), "FPR (%)": pct(m, "fpr"), "ROC-AUC": m["roc_auc"],
                "TPR @ 1% FPR": m["tpr_at_1pct_fpr"]}

    def nan_dash(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
        return [{k: ("-" if isinstance(v, float) and math.isnan(v) else v) for k, v in r.items()} for r in rows]

    lstm = results["lstm"]
    lstm_rows = [{"eps": k, **row(m)} for k, m in lstm.items()]
    lstm_table = markdown_table(nan_dash(lstm_rows), decimals=4)
    names = {"lstm": "LSTM on SHAP (paper)", "mlp": "MLP on SHAP", "mahalanobis": "Mahalanobis on GAP features",
             "lid": "LID on GAP features", "squeeze": "feature squeezing on images"}
    comp = [{"detector": names[k], **row(r["all"])} for k, r in results.items()]
    eps_keys = [k for k in lstm if k != "all"]
    recall_rows = [{"detector": names[k], **{f"eps {e}": pct(r[e], "recall") for e in eps_keys},
                    "FPR (%)": pct(r["all"], "fpr")} for k, r in results.items()]
    best = max(results, key=lambda k: results[k]["all"]["accuracy"])
    rates = ", ".join(f"{e}: {pct(lstm[e], 'recall')}%" for e in eps_keys)
    reading = (f"Detection rate of the LSTM by eps: {rates}; false alarms on clean images: "
               f"{pct(lstm['all'], 'fpr')}%. Highest test accuracy of all detectors here: {names[best]} "
               f"({pct(results[best]['all'], 'accuracy')}%). Brackets: 95% Wilson intervals over the test samples.")
    paper = f"{PAPER_ACCURACY * 100:.2f}%"
    ours = f"{pct(lstm['all'], 'accuracy')}%"
    return f"""# Attack detector

The paper's detector reads the DeepSHAP values of the pose network's 1000 GAP features
for its 9 outputs (a 9 x 1000 sequence per image, `rpod shap`) and says whether the image was
attacked: an LSTM of {d.hidden} units with ReLU, dense layers {d.dense}, one sigmoid output,
Adadelta (lr {d.lr}), early stopping after {d.patience} epochs without a lower validation loss.

**Test accuracy: {ours}** (paper: {paper} on its 30,000 SHAP samples).
{reading}

Data: {counts['samples']} SHAP samples (`datasets/shap.zarr`, method `{attrs.get('method')}`, background
of {attrs.get('background_size')} training images). Split {1 - d.test_fraction:.0%}/{d.test_fraction:.0%} train/test with
{d.val_fraction:.0%} of train held out for validation (grouped by source image: the clean and every eps version of
a frame sit on one side; stratified by eps; seeded): train {counts['train']},
validation {counts['validation']}, test {counts['test']} ({counts['test_clean']} clean, {counts['test_adversarial']} adversarial).
Adversarial samples are FGSM images at eps {', '.join(eps_keys)} (pixels in [0, 1]).

The LSTM trained {len(result.history)} epochs (best: {result.best_epoch}; fit times in reports/metrics/detect.json). Its decision
threshold on the probability, {float(scores['lstm'][1]):.4f}, was chosen on the validation samples for the
highest validation accuracy.

## LSTM detector on the test split

"all" is every test sample; an eps row is all clean test samples plus the attacks at that eps, so
its recall is the detection rate at that eps and its FPR is the same clean-sample FPR.
TPR @ 1% FPR reads the ROC curve at 1% false positives (coarse when the test split has few clean samples).

{lstm_table}
## Comparison with baselines (same split, thresholds on the same validation samples)

{markdown_table(nan_dash(comp), decimals=4)}
Detection rate (recall) per eps:

{markdown_table(nan_dash(recall_rows), decimals=4)}
- **MLP on SHAP**: scikit-learn MLPClassifier on the flattened 9 x 1000 values (standardised).
- **Mahalanobis** (Lee et al. 2018): one Gaussian per range bin (`train.range_bins`) with a shared
  Ledoit-Wolf covariance fitted on clean training GAP features; score = smallest distance. No input
  preprocessing or layer ensemble (one layer, the one the SHAP detectors see).
- **LID** (Ma et al. 2018): LID of the GAP features from the k = {d.lid_k} nearest clean neighbours
  in minibatches of {d.lid_batch}, then logistic regression; test frames against clean training minibatches.
- **Feature squeezing** (Xu et al. 2018): pose change (L1 over the 9 outputs, each divided by its
  clean standard deviation) under {d.squeeze_bits}-bit colour depth and a {d.squeeze_median}x{d.squeeze_median}
  median filter; score = the larger change. Needs the image and two extra pose passes per frame.

What the SHAP detectors see: with the linear heads, row j of a sample's SHAP values is
`W[j] * (a - mean_background)` (pipeline/shap.py), an element-wise rescaling of the GAP features.
The SHAP signature therefore carries the same information as the GAP features, weighted by how much
each feature moves each output; the SHAP detectors and the GAP-feature baselines differ in the model
they fit, not in what they can know.

ROC curves: `dvc plots show` (reports/plots/roc/). Training curves: dvclive/detect/.
"""
