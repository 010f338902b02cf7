"""Where every artifact lives and the seed offset of every stage: the one table of both.

One path base. Outputs (datasets/, models/, reports/, dvclive/) are relative to the working folder: the
repository root under `dvc repro` (a stage run elsewhere reads and writes there). Code-side files
(conf/, dvc.yaml, the committed reports/benchmarks.md) are found from the package location, `ROOT`.
`WRITTEN_BY` names the dvc.yaml stage whose `outs` (or `metrics`) hold each output
(tests/test_dvc_ux.py checks it). This module imports nothing from stages/, so every module may import it.
"""
from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]   # the repository (package) root: code-side files only
CONF_DIR = ROOT / "conf"
DVC_YAML = ROOT / "dvc.yaml"
BENCHMARKS = ROOT / "reports" / "benchmarks.md"   # committed; `rpod report` adds its sections
PARAMS_FILE = Path("params.yaml")

# datasets/ and models/
RENDER = Path("datasets/render")
IMAGES = RENDER / "images.zarr"
LABELS = Path("datasets/labels.parquet")
ATTACK = Path("datasets/attack")
ADV = ATTACK / "adv.zarr"
SHAP = Path("datasets/shap.zarr")
EVAL_RENDER = Path("datasets/eval_render")
VAL_RENDER = Path("datasets/val_render")
LAB = Path("datasets/lab")
LAB_MODELS = Path("datasets/lab_models")
LAB_MODELS_SUMMARY = LAB_MODELS / "summary.json"
POSE = Path("models/pose.pt")
SURROGATE = Path("models/surrogate.pt")   # a second pose model (`rpod train --surrogate`) for black-box transfer
DETECTOR = Path("models/detector.pt")
DEFENSE = Path("models/defense.json")

# reports/: pages, metrics, figures, curves
REPORTS = Path("reports")
METRICS_DIR = REPORTS / "metrics"   # reports/metrics/<stage>.json (stages/pages/report.py SECTIONS names them)
FIGURES = REPORTS / "figures"
PREVIEWS = FIGURES / "previews"
DATASET_CARD = Path("reports/dataset.md")
POSE_REPORT = Path("reports/pose.md")
TRAIN_METRICS = Path("reports/metrics/train.json")
TRAIN_LIVE = Path("dvclive/train")
ATTACK_REPORT = Path("reports/attack.md")
ATTACK_FIGURE = FIGURES / "fgsm_example.png"
ATTACK_METRICS = Path("reports/metrics/attack.json")
GUIDANCE_REPORT = Path("reports/guidance.md")
GUIDANCE_FIGURE = FIGURES / "guidance_trajectories.png"
GUIDANCE_DEFENDED_FIGURE = FIGURES / "guidance_defended.png"
GUIDANCE_METRICS = Path("reports/metrics/guidance.json")
DETECT_REPORT = Path("reports/detector.md")
DETECT_METRICS = Path("reports/metrics/detect.json")
DETECT_LIVE = Path("dvclive/detect")
ROC_DIR = Path("reports/plots/roc")
EVALUATE_REPORT = Path("reports/integrated.md")
EVALUATE_FIGURE = FIGURES / "timeline.png"
EVALUATE_METRICS = Path("reports/metrics/evaluate.json")
ROBUSTNESS_REPORT = Path("reports/robustness.md")
ROBUSTNESS_FIGURE = FIGURES / "robustness.png"
ROBUSTNESS_METRICS = Path("reports/metrics/robustness.json")
LAB_REPORT = Path("reports/lab.md")
LAB_METRICS = Path("reports/metrics/lab.json")
PAGE = Path("reports/README.md")
SUMMARY = Path("reports/metrics/summary.json")   # the headline numbers: what `dvc metrics show` prints
REPORT_FIGURES = {name: FIGURES / f"{name}.png" for name in ("pose_errors", "error_vs_eps", "shap_heatmaps", "roc")}
README = Path("README.md")   # the project README: `rpod report --sync-readme` copies the results block into it
VARIANCE = Path("reports/variance.json")  # scripts/variance.py (not a stage): the spread of the headline numbers

# output -> the dvc.yaml stage that writes it
WRITTEN_BY: dict[Path, str] = {
    RENDER: "render", IMAGES: "render", PREVIEWS: "render",
    LABELS: "label", DATASET_CARD: "label",
    POSE: "train", POSE_REPORT: "train", TRAIN_METRICS: "train", TRAIN_LIVE: "train",
    ATTACK: "attack", ADV: "attack", ATTACK_REPORT: "attack", ATTACK_FIGURE: "attack", ATTACK_METRICS: "attack",
    GUIDANCE_REPORT: "guidance", GUIDANCE_FIGURE: "guidance", GUIDANCE_DEFENDED_FIGURE: "guidance",
    GUIDANCE_METRICS: "guidance",
    SHAP: "shap",
    DETECTOR: "detect", DETECT_REPORT: "detect", DETECT_METRICS: "detect", DETECT_LIVE: "detect", ROC_DIR: "detect",
    EVAL_RENDER: "eval_render", VAL_RENDER: "eval_render",
    DEFENSE: "calibrate",
    EVALUATE_REPORT: "evaluate", EVALUATE_FIGURE: "evaluate", EVALUATE_METRICS: "evaluate",
    SURROGATE: "surrogate",
    ROBUSTNESS_REPORT: "robustness", ROBUSTNESS_FIGURE: "robustness", ROBUSTNESS_METRICS: "robustness",
    LAB_MODELS: "lab_models", LAB_MODELS_SUMMARY: "lab_models",
    LAB: "lab", LAB_REPORT: "lab", LAB_METRICS: "lab",
    PAGE: "report", SUMMARY: "report", **{path: "report" for path in REPORT_FIGURES.values()},
}

# stage -> the offset added to its base seed (`seed`, or `lab.seed` for lab and lab_models; the evaluate
# schedule adds it to evaluate.seed + the trajectory number), so no two stages draw the same stream
SEED_OFFSET: dict[str, int] = {
    "render": 100, "label": 200, "train": 300, "attack": 400, "guidance": 500, "shap": 500, "detect": 600,
    "lab_models": 700, "robustness": 1500, "lab": 0, "evaluate_schedule": 17,
}
