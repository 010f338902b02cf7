"""Where every artifact lives and the seed offset of every stage: the one table of both.

One path base. Outputs (datasets/, models/, reports/, dvclive/) are relative to the working folder: the
repository root under `dvc repro` (a stage run elsewhere reads and writes there). Code-side files
(conf/, dvc.yaml, the committed reports/benchmarks.md) are found from the package location, `ROOT`.
Each output is declared with the dvc.yaml stage whose `outs` (or `metrics`) hold it (`WRITTEN_BY`;
tests/test_dvc_ux.py checks it). This module imports nothing from stages/, so every module may import it.
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]   # the repository (package) root: code-side files only
CONF_DIR = ROOT / "conf"
DVC_YAML = ROOT / "dvc.yaml"
OPTIONAL_DVC_YAML = ROOT / "optional" / "dvc.yaml"   # stages run on demand (`dvc repro optional/dvc.yaml`), not by `dvc repro`
BENCHMARKS = ROOT / "reports" / "benchmarks.md"   # committed; `rpod report` adds its sections
PARAMS_FILE = Path("params.yaml")
README = Path("README.md")   # the project README: `rpod report --sync-readme` copies the results block into it
REPORTS = Path("reports")
VARIANCE = REPORTS / "variance.json"  # scripts/variance.py (not a stage): the spread of the headline numbers

WRITTEN_BY: dict[Path, str] = {}   # output -> the dvc.yaml stage that writes it


def _outputs(stage: str, *paths: str) -> tuple[Path, ...]:
    """The outputs `paths` of dvc.yaml stage `stage`, entered in WRITTEN_BY."""
    out = tuple(Path(p) for p in paths)
    WRITTEN_BY.update(dict.fromkeys(out, stage))
    return out


RENDER, IMAGES, PREVIEWS, RENDER_METRICS = _outputs("render", "datasets/render", "datasets/render/images.zarr",
                                                    "reports/figures/previews", "reports/metrics/render.json")
LABELS, DATASET_CARD = _outputs("label", "datasets/labels.parquet", "reports/dataset.md")
POSE, POSE_REPORT, TRAIN_METRICS, TRAIN_LIVE = _outputs("train", "models/pose.pt", "reports/pose.md",
                                                        "reports/metrics/train.json", "dvclive/train")
ATTACK, ADV, ATTACK_REPORT, ATTACK_FIGURE, ATTACK_METRICS = _outputs(
    "attack", "datasets/attack", "datasets/attack/adv.zarr", "reports/attack.md", "reports/figures/fgsm_example.png",
    "reports/metrics/attack.json")
GUIDANCE_REPORT, GUIDANCE_FIGURE, GUIDANCE_DEFENDED_FIGURE, GUIDANCE_METRICS = _outputs(
    "guidance", "reports/guidance.md", "reports/figures/guidance_trajectories.png",
    "reports/figures/guidance_defended.png", "reports/metrics/guidance.json")
(SHAP,) = _outputs("shap", "datasets/shap.zarr")
DETECTOR, DETECT_REPORT, DETECT_METRICS, DETECT_LIVE = _outputs(
    "detect", "models/detector.pt", "reports/detector.md", "reports/metrics/detect.json", "dvclive/detect")
# the same two stages on the robust pose model (`rpod shap --model robust`, `rpod detect --model robust`)
(SHAP_ROBUST,) = _outputs("shap_robust", "datasets/shap_robust.zarr")
DETECTOR_ROBUST, DETECT_ROBUST_REPORT, DETECT_ROBUST_METRICS, DETECT_ROBUST_LIVE = _outputs(
    "detect_robust", "models/detector_robust.pt", "reports/detector_robust.md", "reports/metrics/detect_robust.json",
    "dvclive/detect_robust")
ROC_DATA = DETECT_LIVE / "plots" / "sklearn"   # DVCLive's log_sklearn_plot("roc", name=D): D.json per detector
# the evaluation trajectories, the defense's validation ones (the mission's kind) and validation frames over the
# pose network's whole envelope (the detector threshold must hold on every kind of clean view)
EVAL_RENDER, VAL_RENDER, VAL_ENVELOPE, EVAL_RENDER_METRICS = _outputs(
    "eval_render", "datasets/eval_render", "datasets/val_render", "datasets/val_envelope",
    "reports/metrics/eval_render.json")
# the detector split (`rpod eval_render --detector`): the images `rpod shap` explains, never seen in training
DETECT_RENDER, DETECT_RENDER_METRICS = _outputs("detect_render", "datasets/detect_render",
                                                "reports/metrics/detect_render.json")
(DEFENSE,) = _outputs("calibrate", "models/defense.json")                       # the shipped chain's
(DEFENSE_STANDARD,) = _outputs("calibrate_standard", "models/defense_standard.json")   # the paper chain's
EVALUATE_REPORT, EVALUATE_FIGURE, EVALUATE_METRICS = _outputs(
    "evaluate", "reports/integrated.md", "reports/figures/timeline.png", "reports/metrics/evaluate.json")
# the robust pose model (`rpod train --robust`: adversarial training behind a black-level clamp) and its page
POSE_ROBUST, ROBUST_REPORT, ROBUST_METRICS, ROBUST_LIVE = _outputs(
    "robust", "models/pose_robust.pt", "reports/pose_robust.md", "reports/metrics/robust.json", "dvclive/robust")
# a second pose model (`rpod train --surrogate`) for black-box transfer
(SURROGATE,) = _outputs("surrogate", "models/surrogate.pt")
ROBUSTNESS_REPORT, ROBUSTNESS_FIGURE, ROBUSTNESS_METRICS, INTEGRITY_FIGURE = _outputs(
    "robustness", "reports/robustness.md", "reports/figures/robustness.png", "reports/metrics/robustness.json",
    "reports/figures/integrity.png")
LAB_MODELS, LAB_MODELS_SUMMARY = _outputs("lab_models", "datasets/lab_models", "datasets/lab_models/summary.json")
LAB, LAB_REPORT, LAB_METRICS = _outputs("lab", "datasets/lab", "reports/lab.md", "reports/metrics/lab.json")
# issue 38's 2 x 2 ablation of the paper's detector: a stage of optional/dvc.yaml (`dvc repro optional/dvc.yaml`), not of
# the default `dvc repro`
ABLATION_REPORT, ABLATION_METRICS = _outputs("ablation", "reports/ablation.md", "reports/metrics/ablation.json")
# the headline numbers (what `dvc metrics show` prints), then the report's own figures
PAGE, SUMMARY, *_FIGURES = _outputs("report", "reports/README.md", "reports/metrics/summary.json",
                                    *(f"reports/figures/{name}.png"
                                      for name in ("pose_errors", "error_vs_eps", "shap_heatmaps", "roc")))
REPORT_FIGURES = {path.stem: path for path in _FIGURES}



class Model(str, Enum):
    """The two pose models (the `--model` option of `rpod shap`, `detect`, `calibrate`): `standard` (`rpod
    train`, the paper's reproduction) and `robust` (`rpod train --robust`, the one that ships)."""

    standard = "standard"
    robust = "robust"


@dataclass(frozen=True)
class ChainFiles:
    """The files of one chain: its pose model, the SHAP store and detector made on that model's SHAP values
    (with the detector's report, metrics and curves), and the defense calibrated for it."""

    model: Model
    pose: Path
    shap: Path
    detector: Path
    detect_report: Path
    detect_metrics: Path
    detect_live: Path
    defense: Path


CHAINS: dict[Model, ChainFiles] = {
    Model.standard: ChainFiles(Model.standard, POSE, SHAP, DETECTOR, DETECT_REPORT, DETECT_METRICS, DETECT_LIVE,
                               DEFENSE_STANDARD),
    Model.robust: ChainFiles(Model.robust, POSE_ROBUST, SHAP_ROBUST, DETECTOR_ROBUST, DETECT_ROBUST_REPORT,
                             DETECT_ROBUST_METRICS, DETECT_ROBUST_LIVE, DEFENSE),
}
PAPER = Model.standard     # the paper's reproduction rows: the standard model and its own detector
SHIPPED = Model.robust     # what ships (rpod predict, rpodguard.load_chain, the weights bundle, every safety row)

# stage -> the offset added to its base seed (`seed`, or `lab.seed` for lab and lab_models; the evaluate
# schedule adds it to evaluate.seed + the trajectory number), so no two stages draw the same stream
SEED_OFFSET: dict[str, int] = {
    "render": 100, "label": 200, "train": 300, "attack": 400, "guidance": 500, "shap": 500, "detect": 600,
    "lab_models": 700, "robustness": 1500, "lab": 0, "evaluate_schedule": 17, "robust": 1600, "ablation": 1700,
}
