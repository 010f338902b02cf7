"""reports/ablation.md, the page of `rpod ablation`: issue 38's 2 x 2 ablation of the paper's detector (FGSM ours |
paper-literal x protocol strict | paper) beside the paper's numbers, and each factor's measured effect."""
from __future__ import annotations

from typing import Any

from stages.config.ablation import Ablation
from stages.config.sections import Detect
from stages.pages.detect import paper_fraction
from stages.pages.paper import DETECTOR_ACCURACY, INTEGRATED_EPS

ATTACK = {"ours": "ours (clipped, 8-bit)", "paper": "paper-literal (unclipped float)"}
PROTOCOL = {"strict": "strict (ours)", "paper": "paper (leaky)"}
TARGET_POINTS = 5.0   # issue 38: the paper-protocol + paper-literal cell within 5 points of the paper's eps-0.01 accuracy


def cell_json(cell: Any) -> dict[str, Any]:
    """One cell (pipeline.evaluation.ablation.CellResult) for reports/metrics/ablation.json: rates per row key with the
    accuracy re-weighted to the paper's integrated attacked fraction, the fit, and the split's leak."""
    return {"attack": cell.attack, "protocol": cell.protocol, "leaky": cell.leaky, "shared_source": cell.shared,
            "shared_neighbour": cell.neighbours, "counts": cell.counts, "threshold": cell.threshold,
            "epochs": cell.epochs, "best_epoch": cell.best_epoch,
            "rates": {k: r.as_json(paper_fraction()) for k, r in cell.rates.items()}}


def _rows(cells: list[Any], f: float) -> list[dict[str, str]]:
    """The main table: per cell its "all" row and one row per eps."""
    rows = []
    for c in cells:
        for key, r in c.rates.items():
            rows.append({"FGSM": ATTACK[c.attack], "protocol": PROTOCOL[c.protocol], "eps": key,
                         "test samples": str(r.accuracy.n), "attacked f (%)": r.attacked_fraction.pct(),
                         "TPR (%)": r.tpr.pct(), "FPR (%)": r.fpr.pct(), "accuracy (%)": r.accuracy.pct(),
                         f"accuracy at f = {100 * f:.1f}% (%)": r.accuracy_at(f).pct(),
                         "test images also in training (%)": f"{100 * c.shared:.1f}",
                         "... or a neighbouring frame (%)": f"{100 * c.neighbours:.1f}"})
    return rows


def _effects(cells: list[Any], f: float) -> list[dict[str, str]]:
    """Each factor's effect with the other held: differences of TPR, FPR and accuracy at the paper's f, per eps row."""
    from pipeline.evaluation.rates import rate_difference

    by = {(c.attack, c.protocol): c for c in cells}
    pairs = [("paper-literal FGSM - ours, strict protocol", ("paper", "strict"), ("ours", "strict")),
             ("paper-literal FGSM - ours, paper protocol", ("paper", "paper"), ("ours", "paper")),
             ("paper protocol - strict, our FGSM", ("ours", "paper"), ("ours", "strict")),
             ("paper protocol - strict, paper-literal FGSM", ("paper", "paper"), ("paper", "strict")),
             ("both (paper's setting - ours)", ("paper", "paper"), ("ours", "strict"))]

    def diff(a: Any, b: Any) -> str:
        d, lo, hi = rate_difference(a, b)
        return "-" if d != d else f"{100 * d:+.1f} [{100 * lo:+.1f}, {100 * hi:+.1f}]"

    rows = []
    for name, a, b in pairs:
        for key in [k for k in by[a].rates if k in by[b].rates]:   # a small test split can lack an eps
            ra, rb = by[a].rates[key], by[b].rates[key]
            rows.append({"effect": name, "eps": key, "TPR (points)": diff(ra.tpr, rb.tpr),
                         "FPR (points)": diff(ra.fpr, rb.fpr),
                         f"accuracy at f = {100 * f:.1f}% (points)": diff(ra.accuracy_at(f), rb.accuracy_at(f))})
    return rows


def _verdict(cells: list[Any], f: float) -> str:
    """The issue's target: the paper-protocol + paper-literal cell at eps 0.01 against the paper's accuracy there, how
    much the two factors together moved it from our setting, and what is left."""
    from pipeline.evaluation.rates import rate_difference

    by = {(c.attack, c.protocol): c for c in cells}
    cell, ours = by[("paper", "paper")], by[("ours", "strict")]
    paper = INTEGRATED_EPS.get("0.01")
    r, r0 = cell.rates.get("0.01"), ours.rates.get("0.01")
    if r is None or r0 is None or paper is None:
        return "A cell has no attacked test sample at eps 0.01, so the paper's eps-0.01 accuracy has no counterpart here."
    at, at0 = r.accuracy_at(f), r0.accuracy_at(f)
    gap = paper - 100 * at.value
    d, lo, hi = rate_difference(at, at0)
    within = "within" if abs(gap) <= TARGET_POINTS else "not within"
    return (f"**Paper-literal FGSM with the paper's protocol, eps 0.01**: accuracy at the paper's f = {100 * f:.1f}% "
            f"{at.pct()}% against the paper's {paper:.2f}% (its integrated evaluation at eps 0.01): {abs(gap):.1f} points "
            f"{'below' if gap > 0 else 'above'} it, {within} issue 38's {TARGET_POINTS:g} points (TPR {r.tpr.pct()}%, "
            f"FPR {r.fpr.pct()}%). From our setting (our FGSM, strict protocol: {at0.pct()}%) the two factors together "
            f"move it by {100 * d:+.1f} [{100 * lo:+.1f}, {100 * hi:+.1f}] points; the other {abs(gap):.1f} points are not "
            f"explained by them. Not measured here: what else differs from the paper (each cell's detector learns from "
            f"{cell.counts['train']} training samples, the paper's from 80% of 30,000; its images are 480x270 with the "
            f"full-width network; its detector saw five eps, 0.01 to 0.5, these only "
            f"{', '.join(k for k in cell.rates if k != 'all')}). On all its test samples (f = "
            f"{cell.rates['all'].attacked_fraction.pct()}%) the cell's accuracy is {cell.rates['all'].accuracy.pct()}% "
            f"against the paper's {100 * DETECTOR_ACCURACY:.2f}% on its SHAP test split.")


def ablation_page(cells: list[Any], a: Ablation, d: Detect, frames: tuple[int, int]) -> str:
    """reports/ablation.md: the four cells, each factor's effect, and the cell closest to the paper against it;
    `frames`: frames per approach of the pose data set and of the detector split (render.frames_per_sequence,
    shap.frames), each approach 50 m of range."""
    from pipeline.report.markdown import markdown_table

    f = paper_fraction()
    counts = cells[0].counts
    return f"""# Ablation: the paper's FGSM and detector protocol (issue 38)

The paper's LSTM detector on the SHAP values of the standard model (models/pose.pt; the `rpod detect` recipe and
params), trained and tested in four settings:

- **FGSM ours**: x' = clip(x + eps sign(grad), 0, 1), stored as 8 bits, as a camera would deliver it (the attack of
  every other page). **Paper-literal**: x' = x + eps sign(grad) as the paper's equation prints it, neither clipped nor
  stored: on the black background every pixel whose gradient is negative becomes -eps, a value no camera delivers,
  and the clip of ours removes that half of the perturbation.
- **Strict protocol (ours)**: {a.normal} clean and {a.per_eps} attacked samples per eps, all images of the detector
  split (trajectories the pose network never saw), each image explained clean once and attacked at most once; split
  grouped by source image. **Paper protocol (leaky)**: clean = pose-test images topped up with pose-training images,
  attacked = pose-test images (each eps draws its own, so one image can be clean and attacked at several eps), split
  at random per sample as the paper did: the same image, and its neighbouring frames of the same approach, sit in
  training and test (the last two columns measure it). The paper's 2,500 frames per 50 m approach put neighbours
  2 cm apart; ours about {_spacing(frames[0])} in the pose data set and {_spacing(frames[1])} in the detector split. The
strict split shares no image, though neighbouring frames of one detector-split trajectory can sit on both sides.

Both FGSM variants of a protocol attack the same images and share one split; each cell trains its own detector on
the clean samples and the attacks at eps {', '.join(f'{e:g}' for e in a.eps)} together ({counts['train']} train,
{counts['validation']} validation, {counts['test']} test samples: detect.test_fraction {d.test_fraction:g},
detect.val_fraction {d.val_fraction:g}; threshold on the validation samples). An eps row holds every clean test
sample and that eps's attacks. Accuracy = f TPR + (1 - f)(1 - FPR) depends on the attacked fraction f; the column
"accuracy at f" re-weights TPR and FPR to the paper's integrated evaluation, f = {100 * f:.1f}% (a frame outside an
attack starts one with probability 0.2, 5-frame attacks), where the paper reports 97.67% at eps 0.01. Brackets: 95%
Wilson intervals over the test samples (the re-weighted accuracy: MOVER-Wilson; pipeline/evaluation/rates.py).

{markdown_table(_rows(cells, f))}
{_verdict(cells, f)}

## Each factor's effect

Differences between two cells with the other factor held (percentage points; 95% intervals by MOVER from the two
cells' Wilson intervals, Newcombe's method 10: for independent samples, so conservative here, where the two cells of
an FGSM effect test the same images).

{markdown_table(_effects(cells, f))}
Metrics, fit epochs and thresholds: reports/metrics/ablation.json (`rpod ablation`, optional/dvc.yaml).
"""


def _spacing(frames: int) -> str:
    """The range between neighbouring frames of a 60 -> 10 m approach of `frames` frames, e.g. "17 cm"."""
    return f"{100 * 50 / max(frames - 1, 1):.0f} cm"
