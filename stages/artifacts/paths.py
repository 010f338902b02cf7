"""Where every artifact lives: the one table of the outputs (the seeds: pipeline/seeds.py).

One path base. Outputs (datasets/, models/, reports/, dvclive/) are relative to the working folder: the
repository root under `dvc repro` (a stage run elsewhere reads and writes there). Code-side files
(conf/, dvc.yaml, the committed reports/benchmarks.md) are found from the package location, `ROOT`.
Each output is declared with the dvc.yaml stage whose `outs` (or `metrics`) hold it (`WRITTEN_BY`;
tests/test_dvc_ux.py checks it). `ROOT`, conf/ and params.yaml are stages/config/params.py's.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from pathlib import Path

from pipeline.formats.run import MODELS as MODEL_NAMES
from pipeline.formats.run import MODELS_DIR, RUN_FILES
from pipeline.formats.run import PAPER as PAPER_NAME
from pipeline.formats.run import SHIPPED as SHIPPED_NAME
from stages.config.params import ROOT

DVC_YAML = ROOT / "dvc.yaml"
OPTIONAL_DVC_YAML = ROOT / "optional" / "dvc.yaml"  # stages on demand (`dvc repro optional/dvc.yaml`), not `dvc repro`
BENCHMARKS = ROOT / "reports" / "benchmarks.md"  # committed; `rpod report` adds its sections
README = Path("README.md")  # the project README: `rpod report --sync-readme` copies the results block into it
REPORTS = Path("reports")
VARIANCE = REPORTS / "variance.json"  # scripts/variance.py (not a stage): the spread of the headline numbers

WRITTEN_BY: dict[Path, str] = {}  # output -> the dvc.yaml stage that writes it
MODELS = Path(MODELS_DIR)  # the model files, named by pipeline/formats/run.py
_STANDARD, _ROBUST = RUN_FILES["standard"], RUN_FILES["robust"]


def _outputs(stage: str, *paths: str) -> tuple[Path, ...]:
    """The outputs `paths` of dvc.yaml stage `stage`, entered in WRITTEN_BY."""
    out = tuple(Path(p) for p in paths)
    WRITTEN_BY.update(dict.fromkeys(out, stage))
    return out


RENDER, IMAGES, PREVIEWS, RENDER_METRICS = _outputs(
    "render",
    "datasets/render",
    "datasets/render/images.zarr",
    "reports/figures/previews",
    "reports/metrics/render.json",
)
LABELS, DATASET_CARD = _outputs("label", "datasets/labels.parquet", "reports/dataset.md")
POSE, POSE_REPORT, TRAIN_METRICS, TRAIN_LIVE = _outputs(
    "train", str(MODELS / _STANDARD.pose), "reports/pose.md", "reports/metrics/train.json", "dvclive/train"
)
ATTACK, ADV, ATTACK_REPORT, ATTACK_FIGURE, ATTACK_METRICS = _outputs(
    "attack",
    "datasets/attack",
    "datasets/attack/adv.zarr",
    "reports/attack.md",
    "reports/figures/fgsm_example.png",
    "reports/metrics/attack.json",
)
GUIDANCE_REPORT, GUIDANCE_FIGURE, GUIDANCE_DEFENDED_FIGURE, GUIDANCE_METRICS = _outputs(
    "guidance",
    "reports/guidance.md",
    "reports/figures/guidance_trajectories.png",
    "reports/figures/guidance_defended.png",
    "reports/metrics/guidance.json",
)
(SHAP,) = _outputs("shap", "datasets/shap.zarr")
DETECTOR, DETECT_REPORT, DETECT_METRICS, DETECT_LIVE = _outputs(
    "detect", str(MODELS / _STANDARD.detector), "reports/detector.md", "reports/metrics/detect.json", "dvclive/detect"
)
# the same two stages on the robust pose model (`rpod shap --model robust`, `rpod detect --model robust`)
(SHAP_ROBUST,) = _outputs("shap_robust", "datasets/shap_robust.zarr")
DETECTOR_ROBUST, DETECT_ROBUST_REPORT, DETECT_ROBUST_METRICS, DETECT_ROBUST_LIVE = _outputs(
    "detect_robust",
    str(MODELS / _ROBUST.detector),
    "reports/detector_robust.md",
    "reports/metrics/detect_robust.json",
    "dvclive/detect_robust",
)
ROC_DATA = DETECT_LIVE / "plots" / "sklearn"  # DVCLive's log_sklearn_plot("roc", name=D): D.json per detector
# the evaluation trajectories, the defense's validation ones (the mission's kind) and validation frames over the
# pose network's whole envelope (the detector threshold must hold on every kind of clean view)
EVAL_RENDER, VAL_RENDER, VAL_ENVELOPE, EVAL_RENDER_METRICS = _outputs(
    "eval_render",
    "datasets/eval_render",
    "datasets/val_render",
    "datasets/val_envelope",
    "reports/metrics/eval_render.json",
)
# the detector split (`rpod eval_render --detector`): the images `rpod shap` explains, never seen in training
DETECT_RENDER, DETECT_RENDER_METRICS = _outputs(
    "detect_render", "datasets/detect_render", "reports/metrics/detect_render.json"
)
(DEFENSE,) = _outputs("calibrate", str(MODELS / _ROBUST.defense))  # the shipped chain's
(DEFENSE_STANDARD,) = _outputs("calibrate_standard", str(MODELS / _STANDARD.defense))  # the paper chain's
EVALUATE_REPORT, EVALUATE_FIGURE, EVALUATE_METRICS = _outputs(
    "evaluate", "reports/integrated.md", "reports/figures/timeline.png", "reports/metrics/evaluate.json"
)
# the robust pose model (`rpod train --robust`: adversarial training behind a black-level clamp), its page (both
# models clean and under the strongest-attack suite) and each chain's attacker capacity (validation frames)
POSE_ROBUST, ROBUST_REPORT, ROBUST_METRICS, ROBUST_LIVE, CAPACITY = _outputs(
    "robust",
    str(MODELS / _ROBUST.pose),
    "reports/pose_robust.md",
    "reports/metrics/robust.json",
    "dvclive/robust",
    "datasets/capacity",
)
# a second pose model (`rpod train --surrogate`) for black-box transfer
(SURROGATE,) = _outputs("surrogate", str(MODELS / "surrogate.pt"))
ROBUSTNESS_REPORT, ROBUSTNESS_FIGURE, ROBUSTNESS_METRICS, INTEGRITY_FIGURE = _outputs(
    "robustness",
    "reports/robustness.md",
    "reports/figures/robustness.png",
    "reports/metrics/robustness.json",
    "reports/figures/integrity.png",
)
LAB_MODELS, LAB_MODELS_SUMMARY = _outputs("lab_models", "datasets/lab_models", "datasets/lab_models/summary.json")
LAB, LAB_REPORT, LAB_METRICS = _outputs("lab", "datasets/lab", "reports/lab.md", "reports/metrics/lab.json")
# the full strongest-attack suite on every test frame (`rpod suite`): a stage of optional/dvc.yaml
SUITE_REPORT, SUITE_METRICS, SUITE_PARTS = _outputs(
    "suite", "reports/suite.md", "reports/metrics/suite.json", "datasets/suite"
)
# issue 38's 2 x 2 ablation of the paper's detector: a stage of optional/dvc.yaml (`dvc repro optional/dvc.yaml`), not of
# the default `dvc repro`
ABLATION_REPORT, ABLATION_METRICS = _outputs("ablation", "reports/ablation.md", "reports/metrics/ablation.json")
# issue 38's pose trials, also of optional/dvc.yaml: `rpod pose_trial VARIANT` (stage trial_VARIANT) retrains the
# standard recipe on a variant of the data set; `rpod attitude` measures the attitude gap's causes with them (the
# fy360 variant is the camera default's held-out check, `rpod heldout`)
POSE_TRIALS = Path("datasets/pose_trials")
# the variants with a stage (480x270: for a GPU box)
TRIAL_STAGES = ("per_sequence", "320x180", "per_sequence_320x180", "fy360")
for _variant in TRIAL_STAGES:
    _outputs(f"trial_{_variant}", str(POSE_TRIALS / _variant))
ATTITUDE_REPORT, ATTITUDE_METRICS = _outputs("attitude", "reports/attitude.md", "reports/metrics/attitude.json")
# issue 38's "differences from the paper" table (`rpod gaps`, optional/dvc.yaml): read from the attitude, ablation and
# detect metrics; its table is copied into README.md
GAPS_REPORT, GAPS_METRICS = _outputs("gaps", "reports/gaps.md", "reports/metrics/gaps.json")
# issue 38's held-out confirmation of the choices made on reported numbers (`rpod heldout`, optional/dvc.yaml): the
# final held-out trajectories rendered with each camera (datasets/heldout/<camera>), its page and metrics
HELDOUT, HELDOUT_REPORT, HELDOUT_METRICS = _outputs(
    "heldout", "datasets/heldout", "reports/heldout.md", "reports/metrics/heldout.json"
)
# issue 40's integrity bound under the attacker's capacity: a stage of optional/dvc.yaml (`rpod bound`)
BOUND_REPORT, BOUND_METRICS = _outputs("bound", "reports/integrity_bound.md", "reports/metrics/bound.json")
# issue 39's full integrity grid (`rpod integrity`, optional/dvc.yaml): every attacker on every chain, trajectory and eps
# (its per-trajectory shards persist across runs: a killed run resumes from them; stages/artifacts/shards.py)
INTEGRITY_REPORT, INTEGRITY_METRICS, INTEGRITY_SHARDS = _outputs(
    "integrity", "reports/integrity_full.md", "reports/metrics/integrity_full.json", "datasets/integrity_shards"
)
# the headline numbers (what `dvc metrics show` prints), then the report's own figures
PAGE, SUMMARY, *_FIGURES = _outputs(
    "report",
    "reports/README.md",
    "reports/metrics/summary.json",
    *(f"reports/figures/{name}.png" for name in ("pose_errors", "error_vs_eps", "shap_heatmaps", "roc")),
)
REPORT_FIGURES = {path.stem: path for path in _FIGURES}


def trial_summary(variant: str) -> Path:
    """summary.json of a pose trial's folder (`rpod pose_trial VARIANT`)."""
    return POSE_TRIALS / variant / "summary.json"


Model = Enum("Model", [(name, name) for name in MODEL_NAMES], type=str)
Model.__doc__ = """The two pose models (the `--model` option of `rpod shap`, `detect`, `calibrate`): `standard` (`rpod
train`, the paper's reproduction) and `robust` (`rpod train --robust`, the one that ships): pipeline/formats/run.py."""


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
    Model.standard: ChainFiles(
        Model.standard, POSE, SHAP, DETECTOR, DETECT_REPORT, DETECT_METRICS, DETECT_LIVE, DEFENSE_STANDARD
    ),
    Model.robust: ChainFiles(
        Model.robust,
        POSE_ROBUST,
        SHAP_ROBUST,
        DETECTOR_ROBUST,
        DETECT_ROBUST_REPORT,
        DETECT_ROBUST_METRICS,
        DETECT_ROBUST_LIVE,
        DEFENSE,
    ),
}
PAPER = Model(PAPER_NAME)  # the paper's reproduction rows: the standard model and its own detector
SHIPPED = Model(SHIPPED_NAME)  # what ships (rpod predict, rpodguard.load_chain, the weights bundle, every safety row)
