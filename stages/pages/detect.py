"""reports/detector.md (the standard model's detector, the paper's reproduction) and reports/detector_robust.md
(the robust model's, the one that ships), the pages of `rpod detect --model ...`: the LSTM detector on the
SHAP test split beside the paper, and the baselines on the same split."""

from __future__ import annotations

import math
from typing import Any

from stages.artifacts.paths import ChainFiles, Model
from stages.config.sections import Detect
from stages.pages.paper import ATTACK_LENGTH, DETECTOR_ACCURACY, P_START

NAMES = {
    "lstm": "LSTM on SHAP (paper)",
    "mlp": "MLP on SHAP",
    "mahalanobis": "Mahalanobis on GAP features",
    "lid": "LID on GAP features",
    "squeeze": "feature squeezing on images",
}


def _pct(m: dict[str, Any], key: str) -> str:
    """A rate in percent with its 95% Wilson interval, e.g. "94.1 [92.4, 95.4]"."""
    from pipeline.stats import percent_ci

    ci = m.get(f"{key}_ci95") or (None, None)
    return "-" if m[key] is None or math.isnan(m[key]) or ci[0] is None else percent_ci(m[key], ci)


def _row(m: dict[str, Any]) -> dict[str, Any]:
    """One table row of a detector's metrics."""
    return {
        "n": m["n"],
        "accuracy (%)": _pct(m, "accuracy"),
        "precision": m["precision"],
        "recall (%)": _pct(m, "recall"),
        "FPR (%)": _pct(m, "fpr"),
        "ROC-AUC": m["roc_auc"],
        "TPR @ 1% FPR": m["tpr_at_1pct_fpr"],
    }


def _table(rows: list[dict[str, Any]]) -> str:
    """A Markdown table with 4 decimals, NaN shown as "-"."""
    from pipeline.report.markdown import markdown_table

    return markdown_table(
        [{k: ("-" if isinstance(v, float) and math.isnan(v) else v) for k, v in r.items()} for r in rows], decimals=4
    )


def _reading(results: dict[str, dict[str, dict[str, float]]], eps_keys: list[str]) -> str:
    """The paragraph under the headline: the LSTM's detection rate per eps, its FPR, the best detector."""
    lstm = results["lstm"]
    best = max(results, key=lambda k: results[k]["all"]["accuracy"])
    rates = ", ".join(f"{e}: {_pct(lstm[e], 'recall')}%" for e in eps_keys)
    return (
        f"Detection rate of the LSTM by eps: {rates}; false alarms on clean images: "
        f"{_pct(lstm['all'], 'fpr')}%. Highest test accuracy of all detectors here: {NAMES[best]} "
        f"({_pct(results[best]['all'], 'accuracy')}%). Brackets: 95% Wilson intervals over the test samples."
    )


def _headline_alarms(alarms: dict[str, Any] | None) -> str:
    """The clean-trajectory false alarms beside the headline accuracy (empty when not measured)."""
    if alarms is None:
        return ""
    from pipeline.stats import percent_ci

    return (
        f" At the same threshold it flags {percent_ci(alarms['rate'], alarms['rate_ci95'], 2)}% of the "
        f"{alarms['frames']} frames of fresh clean evaluation trajectories (below)."
    )


def _baselines(d: Detect) -> str:
    """The baseline detectors, one bullet each."""
    return f"""- **MLP on SHAP**: scikit-learn MLPClassifier on the flattened 9 x 1000 values (standardised).
- **Mahalanobis** (Lee et al. 2018): one Gaussian per range bin (`train.range_bins`) with a shared
  Ledoit-Wolf covariance fitted on clean training GAP features; score = smallest distance. No input
  preprocessing or layer ensemble (one layer, the one the SHAP detectors see).
- **LID** (Ma et al. 2018): LID of the GAP features from the k = {d.lid_k} nearest clean neighbours
  in minibatches of {d.lid_batch}, then logistic regression; test frames against clean training minibatches.
- **Feature squeezing** (Xu et al. 2018): pose change (L1 over the 9 outputs, each divided by its
  clean standard deviation) under {d.squeeze_bits}-bit colour depth and a {d.squeeze_median}x{d.squeeze_median}
  median filter; score = the larger change. Needs the image and two extra pose passes per frame."""


def _composition(attrs: dict[str, Any]) -> str:
    """Where the SHAP samples come from (the store's attrs `counts` and `source`, `rpod shap`)."""
    c, src = attrs.get("counts", {}), attrs.get("source", {})
    return (
        f"All samples are images of the detector split (`{src.get('folder')}`, {src.get('images')} images on "
        f"{src.get('trajectories')} approach trajectories of their own seed, `shap.seed`), which the pose "
        f"network never saw, drawn over the envelope it was trained for (straight and projectile paths, "
        f"lateral offsets from 0 to the widest, the target at rest or turned afresh every frame): "
        f"{c.get('sources')} source images, each explained clean once and attacked at one "
        f"eps ({c.get('shared')} images are in both classes), so clean and attacked samples differ only by the "
        f"attack. (The paper drew its clean samples from the pose data set; in earlier versions ours came "
        f"mostly from the pose-training images while every attacked one was a test image; then, until the "
        f"envelope fix, only from projectile paths with the target at rest, and the shipped detector flagged "
        f"46% of clean pose-test frames and 51% of clean lab-like ones at its calibrated threshold.)"
    )


def _alarms(alarms: dict[str, Any] | None, model: Model) -> str:
    """The section on the LSTM's false alarms on the clean evaluation trajectories."""
    if alarms is None:
        return (
            "## False alarms on fresh clean trajectories\n\nNot measured (`rpod detect --no-eval-alarms`: "
            "the lab's synthetic-lab detector).\n"
        )
    from pipeline.stats import percent_ci

    per = ", ".join(f"{k}: {v}" for k, v in alarms["per_trajectory"].items())
    return f"""## False alarms on fresh clean trajectories

The LSTM at its own threshold ({alarms["threshold"]:.4f}, chosen on the SHAP validation samples) on every frame
of the {alarms["trajectories"]} clean evaluation trajectories (`datasets/eval_render`, their base seed following `seed`),
run through the onboard chain (pose -> exact SHAP -> LSTM; no motion filter): it flags
**{alarms["false_alarms"]} of {alarms["frames"]} frames, {percent_ci(alarms["rate"], alarms["rate_ci95"], 2)}%**
(Wilson interval over frames, optimistic: frames of one trajectory are correlated; per trajectory:
{per}). {_threshold_note(model)}
"""


def _threshold_note(model: Model) -> str:
    """What the page's threshold is for, per model."""
    if model == Model.standard:
        return (
            "This is the paper's detector as it was built; the shipped chain (robust model, "
            "reports/detector_robust.md) reads its own detector's threshold from models/defense.json."
        )
    return (
        "The shipped chain does not flag at this threshold: it reads its detector threshold from "
        "models/defense.json (`rpod calibrate`, chosen on clean validation trajectories)."
    )


def _intro(files: ChainFiles) -> str:
    """Which pose model the page's detector explains, and what the page is."""
    if files.model == Model.standard:
        return (
            f"# Attack detector (standard model: the paper's reproduction)\n\nOn the SHAP values of the standard "
            f"pose model (`{files.pose}`, `rpod train`); the chain that ships uses the robust model and its own "
            f"detector (reports/detector_robust.md).\n"
        )
    return (
        f"# Attack detector of the shipped chain (robust model)\n\nOn the SHAP values of the robust pose model "
        f"(`{files.pose}`, `rpod train --robust`): the detector of the chain that ships (`rpod predict`, the "
        f"weights bundle, every safety row). The paper's reproduction, on the standard model: reports/detector.md.\n"
    )


def _comparison(results: dict[str, Any], eps_keys: list[str], d: Detect) -> str:
    """The baselines section, or a line saying they were not run (`--no-baselines`)."""
    if len(results) == 1:
        return (
            "## Comparison with baselines\n\nNot run for this detector (`rpod detect --no-baselines`): the "
            "baseline comparison is the paper's reproduction, on the standard model (reports/detector.md).\n"
        )
    comp = [{"detector": NAMES[k], **_row(r["all"])} for k, r in results.items()]
    recall_rows = [
        {"detector": NAMES[k], **{f"eps {e}": _pct(r[e], "recall") for e in eps_keys}, "FPR (%)": _pct(r["all"], "fpr")}
        for k, r in results.items()
    ]
    return f"""## Comparison with baselines (same split, thresholds on the same validation samples)

{_table(comp)}
Detection rate (recall) per eps:

{_table(recall_rows)}
{_baselines(d)}
"""


def paper_fraction() -> float:
    """The attacked fraction of the paper's integrated evaluation (its schedule: pipeline.attacks.schedule)."""
    from pipeline.attacks.schedule import attacked_fraction

    return attacked_fraction(P_START, ATTACK_LENGTH)


def rates_section(rates: dict[str, Any]) -> str:
    """The LSTM's rows as rates: per row the attacked fraction f, TPR, FPR, accuracy and the accuracy re-weighted
    to the paper's integrated f (`rates`: row key -> pipeline.evaluation.rates.DetectionRates, Wilson)."""
    f = paper_fraction()
    rows = [
        {
            "eps": k,
            "n": r.accuracy.n,
            "attacked f (%)": r.attacked_fraction.pct(),
            "TPR (%)": r.tpr.pct(),
            "FPR (%)": r.fpr.pct(),
            "accuracy (%)": r.accuracy.pct(),
            f"accuracy at f = {100 * f:.1f}% (%)": r.accuracy_at(f).pct(),
        }
        for k, r in rates.items()
    ]
    return f"""## Rates and the attacked fraction

A test accuracy mixes the two rates with the share f of attacked samples: accuracy = f TPR + (1 - f)(1 - FPR),
so a detector that flags nothing scores 1 - f. The "all" row has f = {100 * rates["all"].attacked_fraction.value:.1f}%
(the paper's 15,000 + 15,000 SHAP samples: 50%); an eps row holds every clean test sample and only that eps's attacks, so its f is small and its
accuracy mostly counts clean samples. The last column re-weights each row's TPR and FPR to the attacked fraction of
the paper's integrated evaluation, f = {100 * f:.1f}% (a frame outside an attack starts one with probability
{P_START:g} and attacks last {ATTACK_LENGTH} frames: on average {ATTACK_LENGTH} attacked of every
{ATTACK_LENGTH} + (1 - {P_START:g}) / {P_START:g} = {ATTACK_LENGTH + (1 - P_START) / P_START:g} frames), the fraction
behind its per-eps integrated accuracies (reports/integrated.md). Brackets:
95% Wilson intervals over the test samples; the re-weighted accuracy holds f fixed and combines the Wilson limits
of TPR and 1 - FPR (MOVER, pipeline/evaluation/rates.py).

{_table(rows)}"""


def detector_page(
    results: dict[str, dict[str, dict[str, float]]],
    scores: dict[str, Any],
    counts: dict[str, int],
    result: Any,
    attrs: dict[str, Any],
    d: Detect,
    files: ChainFiles,
    alarms: dict[str, Any] | None = None,
    rates: dict[str, Any] | None = None,
) -> str:
    """The detector page of one model (`files`): the LSTM per eps (and, with `rates`, as rates beside the paper's
    attacked fraction), the baselines on the same split (when run), its false alarms on clean evaluation
    trajectories, and what the detectors see."""
    lstm = results["lstm"]
    lstm_table = _table([{"eps": k, **_row(m)} for k, m in lstm.items()])
    eps_keys = [k for k in lstm if k != "all"]
    reading = _reading(results, eps_keys)
    paper = f"{DETECTOR_ACCURACY * 100:.2f}%"
    ours = f"{_pct(lstm['all'], 'accuracy')}%"
    rates_text = "" if rates is None else rates_section(rates) + "\n"
    return f"""{_intro(files)}
The paper's detector reads the DeepSHAP values of the pose network's 1000 GAP features
for its 9 outputs (a 9 x 1000 sequence per image, `rpod shap`) and says whether the image was
attacked: an LSTM of {d.hidden} units with ReLU, dense layers {d.dense}, one sigmoid output,
Adadelta (lr {d.lr}), early stopping after {d.patience} epochs without a lower validation loss.

**Test accuracy: {ours}** (paper: {paper} on its 30,000 SHAP samples).{_headline_alarms(alarms)}
{reading}

Data: {counts["samples"]} SHAP samples (`{files.shap}`, method `{attrs.get("method")}`, background
of {attrs.get("background_size")} training images). {_composition(attrs)}
Split {1 - d.test_fraction:.0%}/{d.test_fraction:.0%} train/test with
{d.val_fraction:.0%} of train held out for validation (grouped by source image: the clean and the attacked version of
an image sit on one side; stratified by eps; seeded): train {counts["train"]},
validation {counts["validation"]}, test {counts["test"]} ({counts["test_clean"]} clean, {counts["test_adversarial"]} adversarial).
Adversarial samples are FGSM images at eps {", ".join(eps_keys)} (pixels in [0, 1]).

The LSTM trained {len(result.history)} epochs (best: {result.best_epoch}; fit times in {files.detect_metrics}). Its decision
threshold on the probability, {float(scores["lstm"][1]):.4f}, was chosen on the validation samples for the
highest validation accuracy.

## LSTM detector on the test split

"all" is every test sample; an eps row is all clean test samples plus the attacks at that eps, so
its recall is the detection rate at that eps and its FPR is the same clean-sample FPR.
TPR @ 1% FPR reads the ROC curve at 1% false positives (coarse when the test split has few clean samples).

{lstm_table}
{rates_text}{_comparison(results, eps_keys, d)}
{_alarms(alarms, files.model)}
What the SHAP detectors see: with the linear heads, row j of a sample's SHAP values is
`W[j] * (a - mean_background)` (pipeline/shap.py), an element-wise rescaling of the GAP features.
The SHAP signature therefore carries the same information as the GAP features, weighted by how much
each feature moves each output; the SHAP detectors and the GAP-feature baselines differ in the model
they fit, not in what they can know.

ROC curves and training curves: DVCLive data in {files.detect_live}/ (`dvc plots show` draws dvclive/detect/).
"""
