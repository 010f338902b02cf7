"""`rpod detect [--model standard|robust]`: train the LSTM attack detector on one pose model's SHAP store and
compare it with baselines.

Per model (stages.artifacts.paths.CHAINS): standard (dvc stage `detect`, the paper's reproduction):
datasets/shap.zarr -> models/detector.pt, reports/detector.md, reports/metrics/detect.json, dvclive/detect/;
robust (stage `detect_robust`, the detector of the chain that ships, run with --no-baselines):
datasets/shap_robust.zarr -> models/detector_robust.pt, reports/detector_robust.md,
reports/metrics/detect_robust.json, dvclive/detect_robust/. Both use the same seed, so the same split.

Reads the SHAP store (refused unless it was made with the model's current checkpoint): clean and FGSM
samples of the same detector-split images, none seen by the pose network (`rpod shap`). Splits its
samples 80/20 into train/test and holds 20% of train out for validation (grouped by source image,
so the clean and the attacked version of an image sit on one side; stratified by eps; seeded), then
fits on the same split:
- lstm: the paper's detector on the SHAP values (pipeline.detectors.lstm), threshold on validation;
- mlp: an MLP on the flattened SHAP values; mahalanobis: Lee et al. 2018 on the GAP features, one
  Gaussian per range bin (train.range_bins) with a shared covariance; lid: Ma et al. 2018 on the GAP
  features; squeeze: Xu et al. 2018 on the input images (rebuilt from their sources, see
  stages/artifacts/readers.py). Every baseline's threshold is chosen on the same validation samples.
Then (unless --no-eval-alarms) the LSTM's false alarms at its own threshold on the clean frames of the
fresh evaluation trajectories (datasets/eval_render), run through the onboard chain: what the SHAP
split's accuracy does not say about a detector in the loop.

Writes the detector (LSTM weights, architecture, threshold, and what the safety chain needs: the pose-model
hash and the SHAP background mean; `pipeline.formats.models.read_detector` reads it), the DVCLive folder (the
detect params, the LSTM's training curves and test metrics, and every detector's ROC on the test split as
plots/sklearn/<name>.json), the report and the metrics.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer

from pipeline.formats.models import DETECTOR_FORMAT
from pipeline.io.atomic import atomic_outputs, atomic_write_text, file_hash
from pipeline.io.checkpoints import save_torch
from pipeline.seeds import seed_for
from stages.artifacts.dvc import write_metrics
from stages.artifacts.models import load_pose, model_option
from stages.artifacts.paths import CHAINS, DETECT_RENDER, ChainFiles, Model
from stages.artifacts.readers import (
    SampleImages,
    check_shap_split,
    read_detect_render,
    read_eval_render,
    read_shap_store,
)
from stages.config.device import torch_device
from stages.config.schema import Params
from stages.config.sections import Detect
from stages.errors import StageError
from stages.pages.detect import detector_page, paper_fraction
from stages.pages.paper import DETECTOR_ACCURACY


def split_indices(
    eps: np.ndarray, source: np.ndarray, test_fraction: float, val_fraction: float, seed: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Train / validation / test indices grouped by source image (all eps versions of a frame on one
    side) and stratified by eps (clean = 0) as far as the groups allow (pipeline.evaluation.splits.grouped_split)."""
    from pipeline.evaluation.splits import grouped_split

    try:
        return grouped_split(source, np.round(eps, 6), test_fraction, val_fraction, seed)
    except ValueError as e:
        raise StageError(
            f"cannot split {len(eps)} SHAP samples from {len(np.unique(source))} source images with "
            f"detect.test_fraction={test_fraction}, detect.val_fraction={val_fraction}: {e} "
            f"(raise shap.normal / shap.per_eps)"
        ) from None


ModelOption = Annotated[
    Model,
    model_option(
        "Reads datasets/shap.zarr or datasets/shap_robust.zarr; writes "
        "models/detector.pt or models/detector_robust.pt and their report."
    ),
]
EvalAlarmsOption = Annotated[
    bool,
    typer.Option(
        "--eval-alarms/--no-eval-alarms",
        help="Measure the LSTM's false alarms on the clean evaluation "
        "trajectories (datasets/eval_render); off for the lab's synthetic-lab detector.",
    ),
]
BaselinesOption = Annotated[
    bool,
    typer.Option(
        "--baselines/--no-baselines",
        help="Fit detect.baselines on the same split (the paper's comparison); off for the robust model's detector.",
    ),
]


def main(
    params: Params,
    model: ModelOption = Model.standard,
    eval_alarms: EvalAlarmsOption = True,
    baselines: BaselinesOption = True,
) -> None:
    """Train the LSTM detector (and the baselines) on one split of a pose model's SHAP store; write the report."""
    import torch

    from pipeline.detectors.metrics import metrics_by_eps
    from pipeline.evaluation.rates import rates_by_eps
    from pipeline.evaluation.sequences import nan_to_none

    d = params.detect
    torch.set_num_threads(1)  # the LSTM's matrices are small: extra threads cost more than they give
    device = torch_device(params)  # a missing CUDA GPU stops here; the LSTM fit and the squeeze baseline run on it
    seed = seed_for(params.seed, "detect")
    files = CHAINS[model]
    data, model_hash, eps, (y, tr, va, te) = _split_store(params, model, seed)

    result, scores, seconds = _fit_detectors(params, files, data, (y, tr, va, te), seed, device, baselines)
    lstm = result.model
    results = {name: metrics_by_eps(y[te], s, eps[te], thr) for name, (s, thr) in scores.items()}
    rates = rates_by_eps(y[te] == 1, scores["lstm"][0] >= scores["lstm"][1], eps[te])
    alarms = _eval_alarms(params, files, lstm, data["attrs"]) if eval_alarms else None

    ckpt = _checkpoint(result, data["attrs"], model_hash, eps[y == 1], results["lstm"]["all"]["accuracy"])
    counts = _counts(y, tr, va, te)
    metrics = {
        "model": model.value,
        "model_hash": model_hash,
        "counts": counts,
        "threshold": {k: v[1] for k, v in scores.items()},
        "lstm_epochs": len(result.history),
        "lstm_best_epoch": result.best_epoch,
        "seconds": seconds,
        "paper_accuracy": DETECTOR_ACCURACY,
        "detectors": results,
        "composition": {**data["attrs"].get("counts", {}), **data["attrs"].get("source", {})},
        "eval_alarms": alarms,
        "lstm_rates": {k: r.as_json(paper_fraction()) for k, r in rates.items()},
    }
    # detector, metrics, report and the DVCLive folder move into place together, once all are written
    with atomic_outputs(files.detector, files.detect_metrics, files.detect_report, dirs=(files.detect_live,)) as (
        det,
        met,
        rep,
        live_dir,
    ):
        save_torch(det, ckpt)
        write_metrics(met, nan_to_none(metrics), params.profile_name)
        atomic_write_text(
            rep, detector_page(results, scores, counts, result, data["attrs"], _used(d, y[tr]), files, alarms, rates)
        )
        _log_live(live_dir, d, result.history, results["lstm"]["all"], (y[te], {k: v[0] for k, v in scores.items()}))
    print(_closing_line(results["lstm"]["all"]["accuracy"], alarms, files))


def _closing_line(acc: float, alarms: dict[str, Any] | None, files: ChainFiles) -> str:
    """The stage's last line: the LSTM's test accuracy next to the paper's, its false-alarm rate on the clean
    evaluation frames (when measured) and the files written."""
    fa = "" if alarms is None else f"; false alarms on clean evaluation frames {alarms['rate']:.4f}"
    return (
        f"detect: LSTM test accuracy {acc:.4f} (paper {DETECTOR_ACCURACY:.4f}){fa} -> {files.detector}, "
        f"{files.detect_report}"
    )


def _split_store(
    params: Params, model: Model, seed: int
) -> tuple[dict[str, Any], str, np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """The model's SHAP store (checked against its checkpoint and the detector split), the checkpoint's hash, the
    samples' eps (0 = clean) and (labels, 1 = attacked; train, validation and test indices); prints the sizes."""
    d = params.detect
    files = CHAINS[model]
    model_hash = file_hash(files.pose)
    data = read_shap_store(files.shap, model_hash)
    check_shap_split(data["attrs"], params, files.shap)  # explains this detector split (after shap.seed changed: not)
    eps = data["eps"].astype(np.float64)
    y = data["is_adversarial"].astype(np.int64)
    tr, va, te = split_indices(eps, data["source_index"], float(d.test_fraction), float(d.val_fraction), seed)
    print(
        f"detect ({model.value} model): {len(y)} SHAP samples ({int(y.sum())} adversarial) -> train {len(tr)}, "
        f"validation {len(va)}, test {len(te)}",
        flush=True,
    )
    return data, model_hash, eps, (y, tr, va, te)


def _fit_detectors(
    params: Params,
    files: ChainFiles,
    data: dict[str, Any],
    split: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    seed: int,
    device: Any,
    baselines: bool,
) -> tuple[Any, dict[str, tuple[np.ndarray, float]], dict[str, float]]:
    """The paper's LSTM and (with `baselines`) detect.baselines fitted on `split` (labels; train, validation, test
    indices): (the LSTM's fit result, each detector's (test scores, threshold), each fit's seconds)."""
    d = params.detect
    values = data["values"]
    y, tr, va, te = split
    result, lstm_seconds = _train_lstm(values, y, tr, va, d, seed, device)  # the paper's LSTM detector
    lstm = result.model
    scores: dict[str, tuple[np.ndarray, float]] = {"lstm": (lstm.predict_proba(values[te]), float(lstm.threshold))}
    seconds = {"lstm": lstm_seconds}
    for name in d.baselines if baselines else []:  # same split, thresholds on the same validation samples
        scores[name], seconds[name] = _fit_baseline(name, params, files, data, (y, tr, va, te), seed)
    return result, scores, seconds


def _counts(y: np.ndarray, tr: np.ndarray, va: np.ndarray, te: np.ndarray) -> dict[str, int]:
    """Sample counts: all, per split, and the test split's clean and adversarial ones."""
    return {
        "samples": int(len(y)),
        "train": int(len(tr)),
        "validation": int(len(va)),
        "test": int(len(te)),
        "test_clean": int((y[te] == 0).sum()),
        "test_adversarial": int(y[te].sum()),
    }


def _used(d: Detect, train_labels: np.ndarray) -> Detect:
    """The detect params as the baselines ran: detect.lid_k capped by LID's minibatches (the report states that)."""
    import dataclasses

    from pipeline.detectors.lid import neighbours

    k = neighbours(d.lid_k, train_labels, d.lid_batch)
    return dataclasses.replace(d, lid_k=k) if 1 <= k < d.lid_k else d


def _checkpoint(
    result: Any, attrs: dict[str, Any], model_hash: str, attacked_eps: np.ndarray, accuracy: float
) -> dict[str, Any]:
    """models/detector.pt's content: the LSTM and what the safety chain needs (pose-model hash, SHAP background mean)."""
    import torch

    from pipeline.detectors.lstm import to_checkpoint

    return to_checkpoint(
        result.model,
        {
            "format": DETECTOR_FORMAT,
            "pose_model_hash": model_hash,
            "shap_method": attrs.get("method"),
            "background_mean": torch.tensor(attrs["background_mean"], dtype=torch.float32),
            "background_size": int(attrs["background_size"]),
            "eps": sorted({float(e) for e in attacked_eps}, reverse=True),
            "best_epoch": result.best_epoch,
            "test_accuracy": accuracy,
        },
    )


def _eval_alarms(p: Params, files: ChainFiles, lstm: Any, attrs: dict[str, Any]) -> dict[str, Any]:
    """The LSTM's false alarms at its own threshold on every frame of the clean evaluation trajectories
    (datasets/eval_render), through the onboard chain (pose -> exact SHAP -> LSTM; no motion filter):
    the rate with its Wilson interval over frames (optimistic: frames of a trajectory are correlated)
    and the count per trajectory."""
    from tqdm import tqdm

    from pipeline.defense.chain import OnboardChain, run_sequence
    from pipeline.stats import rate

    images, poses, _ = read_eval_render(p)
    pose = load_pose(p, files.pose)
    try:
        chain = OnboardChain.from_model(pose.model, np.asarray(attrs["background_mean"]), lstm, float(lstm.threshold))
    except ValueError as e:
        raise StageError(f"{files.pose}: {e}") from None
    n = len(images)
    res = run_sequence(
        chain,
        images,
        np.zeros((n, 9), np.float32),
        np.zeros(n, bool),
        None,
        p.evaluate.batch_size,
        progress=lambda r: tqdm(r, desc="detect: clean evaluation frames", unit="batch", leave=False),
    )
    traj = poses["trajectory"].to_numpy()
    r = rate(res.flag)
    return {
        "frames": n,
        "trajectories": int(len(np.unique(traj))),
        "false_alarms": int(res.flag.sum()),
        "rate": r.value,
        "rate_ci95": r.ci(),
        "threshold": float(lstm.threshold),
        "per_trajectory": {str(int(t)): int(res.flag[traj == t].sum()) for t in np.unique(traj)},
    }


def _train_lstm(
    values: np.ndarray, y: np.ndarray, tr: np.ndarray, va: np.ndarray, d: Detect, seed: int, device: Any
) -> tuple[Any, float]:
    """Fit the LSTM on the training indices with early stopping on the validation ones; returns the fit
    result and its seconds. Bad settings or a diverged fit are a StageError (nothing is written)."""
    from pipeline.detectors.lstm import LSTMConfig, train_lstm

    config = LSTMConfig(n_rows=values.shape[1], n_features=values.shape[2], hidden=d.hidden, dense=list(d.dense))
    t0 = time.perf_counter()
    try:
        result = train_lstm(
            values[tr],
            y[tr],
            values[va],
            y[va],
            config,
            epochs=d.epochs,
            patience=d.patience,
            batch_size=d.batch_size,
            lr=float(d.lr),
            seed=seed,
            progress="detect: LSTM",
            device=device,
        )
    except ValueError as e:  # also DivergenceError
        raise StageError(f"params.yaml detect: {e} (the detector and its reports were left as they were)") from None
    return result, time.perf_counter() - t0


def _log_live(
    folder: Path,
    d: Detect,
    history: list[dict[str, float]],
    test: dict[str, float],
    roc: tuple[np.ndarray, dict[str, np.ndarray]],
) -> None:
    """Into a DVCLive folder (for `dvc plots show`; dvc.yaml's `plots` draw them): the detect params, the
    LSTM's per-epoch curves and test metrics, and each detector's ROC curve on the test split (`roc`: the
    test labels, 1 = attacked, and each detector's scores) as DVCLive's plots/sklearn/<detector>.json."""
    import dataclasses
    import json

    from dvclive import Live

    live = Live(dir=str(folder), dvcyaml=False, save_dvc_exp=False, report=None)
    live.log_params(json.loads(json.dumps(dataclasses.asdict(d))))  # plain lists, as params.yaml has them
    labels, scores = roc
    for name, score in scores.items():
        live.log_sklearn_plot("roc", labels, score, name=name)
    for rec in history:
        for k in ("train_loss", "val_loss", "val_accuracy"):
            live.log_metric(k, rec[k])
        live.next_step()
    for k, v in test.items():
        if not isinstance(v, list):  # intervals stay in reports/metrics/detect.json
            live.log_metric(f"test/{k}", v, plot=False)
    live.end()


def _fit_baseline(
    name: str,
    p: Params,
    files: ChainFiles,
    data: dict[str, Any],
    split: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    seed: int,
) -> tuple[tuple[np.ndarray, float], float]:
    """((test scores, threshold chosen on the validation scores), seconds) of one baseline."""
    from pipeline.detectors.metrics import choose_threshold

    t0 = time.perf_counter()
    s_val, s_test = _baseline(name, p, files, data, split, seed)
    seconds = time.perf_counter() - t0
    print(f"detect: {name} baseline in {seconds:.1f} s", flush=True)
    return (s_test, choose_threshold(s_val, split[0][split[2]])), seconds


def _baseline(
    name: str,
    p: Params,
    files: ChainFiles,
    data: dict[str, Any],
    split: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    seed: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Validation and test scores of one baseline fitted on the training indices (`split`: labels, then the
    train, validation and test indices)."""
    d = p.detect
    y, tr, va, te = split
    values, feats = data["values"], data["features"]
    if name == "mlp":
        from pipeline.detectors.mlp import MLPDetector

        det = MLPDetector(hidden=tuple(d.mlp_hidden), seed=seed).fit(values[tr], y[tr])
        return det.score(values[va]), det.score(values[te])
    if name == "mahalanobis":
        from pipeline.detectors.mahalanobis import MahalanobisDetector

        poses = read_detect_render(p)[1]
        if data["source_index"].max() >= len(poses):
            raise StageError(
                f"{files.shap}/source_index names images missing from {DETECT_RENDER} (re-run `rpod shap`)"
            )
        ranges = poses["range"].to_numpy(np.float64)[data["source_index"]]
        groups = np.digitize(ranges, np.sort(np.asarray(p.train.range_bins, dtype=np.float64)))
        clean_tr = tr[y[tr] == 0]
        det = MahalanobisDetector().fit(feats[clean_tr], groups[clean_tr])
        return det.score(feats[va]), det.score(feats[te])
    if name == "lid":
        from pipeline.detectors.lid import LIDDetector

        det = LIDDetector(k=d.lid_k, batch_size=d.lid_batch, seed=seed).fit(feats[tr], y[tr])
        return det.score(feats[va]), det.score(feats[te])
    return _squeeze(p, files, data, y, tr, va, te)


def _squeeze(
    p: Params, files: ChainFiles, data: dict[str, Any], y: np.ndarray, tr: np.ndarray, va: np.ndarray, te: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Feature squeezing needs the images and the pose model: rebuild each sample's image from its
    source (stages.artifacts.readers.SampleImages: the detector-split render, or the same FGSM) and score it."""
    from tqdm import tqdm

    from pipeline.attacks.gradient import attack_loss
    from pipeline.detectors.squeeze import SqueezeDetector, model_predictor, score_batches

    d = p.detect
    pose = load_pose(p, files.pose)
    src = SampleImages(p, pose.model, attack_loss(p.attack.loss, pose.loss))
    keys = (data["source_index"], data["eps"].astype(np.float64))
    det = SqueezeDetector(model_predictor(pose.model), bits=d.squeeze_bits, median_size=d.squeeze_median)
    clean_tr = tr[y[tr] == 0][:512]
    det.fit(src.images(*(k[clean_tr] for k in keys)))

    def score(rows: np.ndarray, what: str) -> np.ndarray:
        return score_batches(
            det,
            tqdm(
                src.iter_images(*(k[rows] for k in keys)),
                desc=f"detect: squeeze ({what})",
                total=-(-len(rows) // 64),
                unit="batch",
                leave=False,
            ),
            len(rows),
        )

    return score(va, "validation"), score(te, "test")
