"""`rpod detect`: train the LSTM attack detector on the SHAP store (SPEC 7) and compare it with baselines.

Reads datasets/shap.zarr (refused unless it was made with the current models/pose.pt), splits its
samples 80/20 into train/test and holds 20% of train out for validation (grouped by source image,
so the clean and all eps versions of a frame sit on one side; stratified by eps; seeded), then fits
on the same split:
- lstm: the paper's detector on the SHAP values (pipeline.detectors.lstm), threshold on validation;
- mlp: an MLP on the flattened SHAP values; mahalanobis: Lee et al. 2018 on the GAP features, one
  Gaussian per range bin (train.range_bins) with a shared covariance; lid: Ma et al. 2018 on the GAP
  features; squeeze: Xu et al. 2018 on the input images (rebuilt from their sources, see
  stages/shap.py). Every baseline's threshold is chosen on the same validation samples.

Writes models/detector.pt (LSTM weights, architecture, threshold, and what the safety chain needs:
the pose-model hash and the SHAP background mean; `load_detector` reads it), dvclive/detect/
(training curves), reports/detector.md, reports/metrics/detect.json and reports/plots/roc/<name>.csv.
"""
from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from stages import params as params_mod
from stages.io import StageError, atomic_write_text, file_hash, load_torch, open_zarr, save_torch, write_metrics

SHAP = Path("datasets/shap.zarr")
MODEL = Path("models/pose.pt")
DETECTOR = Path("models/detector.pt")
REPORT = Path("reports/detector.md")
METRICS = Path("reports/metrics/detect.json")
ROC_DIR = Path("reports/plots/roc")
LIVE_DIR = "dvclive/detect"
SEED_OFFSET = 600
BASELINES = ("mlp", "mahalanobis", "lid", "squeeze")
PAPER_ACCURACY = 0.9990
FORMAT = "rpodguard-detector/1"


def read_store(path: Path, model_hash: str) -> dict[str, Any]:
    """The SHAP store's arrays and attrs, checked: model hash, shapes, NaNs, both classes present."""
    root = open_zarr(path, "SHAP store")
    need = ["values", "features", "is_adversarial", "eps", "source_index", "split"]
    missing = [k for k in need if k not in root]
    if missing:
        raise StageError(f"{path} lacks arrays {missing} (re-run `rpod shap`)")
    attrs = dict(root.attrs)
    if attrs.get("model_hash") != model_hash:
        raise StageError(f"{path} was made with another pose checkpoint (hash {attrs.get('model_hash')!r}, "
                         f"{MODEL} is {model_hash!r}); re-run `rpod shap`")
    values = root["values"]
    n = values.shape[0]
    if values.ndim != 3 or values.shape[1] != 9 or n == 0:
        raise StageError(f"{path}/values must be (N, 9, n_features) with N > 0, got {tuple(values.shape)} "
                         f"(re-run `rpod shap`)")
    out = {k: root[k][:] for k in need}
    out["attrs"] = attrs
    for k in need[1:]:
        if out[k].shape[0] != n:
            raise StageError(f"{path}/{k} has {out[k].shape[0]} rows but values has {n} (re-run `rpod shap`)")
    if out["features"].shape[1] != values.shape[2]:
        raise StageError(f"{path}/features has {out['features'].shape[1]} columns, values {values.shape[2]} features")
    for k in ("values", "features", "eps"):
        bad = ~np.isfinite(out[k].reshape(n, -1)).all(axis=1)
        if bad.any():
            raise StageError(f"{path}/{k} has NaN or infinite entries in {int(bad.sum())} samples "
                             f"(first: sample {int(np.argmax(bad))}); re-run `rpod shap`")
    y = out["is_adversarial"].astype(bool)
    if y.all() or not y.any():
        raise StageError(f"{path} holds only {'adversarial' if y.all() else 'clean'} samples; a detector needs both "
                         f"(check shap.normal, shap.per_eps and shap.eps)")
    if not np.array_equal(y, out["eps"] > 0):
        raise StageError(f"{path}: is_adversarial disagrees with eps > 0 (re-run `rpod shap`)")
    return out


def split_indices(eps: np.ndarray, source: np.ndarray, test_fraction: float, val_fraction: float,
                  seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Train / validation / test indices grouped by source image (all eps versions of a frame on one
    side) and stratified by eps (clean = 0) as far as the groups allow (pipeline.splits.grouped_split)."""
    from pipeline.splits import grouped_split

    try:
        return grouped_split(source, np.round(eps, 6), test_fraction, val_fraction, seed)
    except ValueError as e:
        raise StageError(f"cannot split {len(eps)} SHAP samples from {len(np.unique(source))} source images with "
                         f"detect.test_fraction={test_fraction}, detect.val_fraction={val_fraction}: {e} "
                         f"(raise shap.normal / shap.per_eps)") from None


def load_detector(path: Path | str = DETECTOR, model_hash: str | None = None) -> tuple[Any, dict[str, Any]]:
    """The LSTM detector (eval mode) and its checkpoint dict (threshold, pose_model_hash,
    background_mean (1000,) tensor, shap_method, ...). With `model_hash`, refuse a detector trained
    on another pose checkpoint's SHAP values."""
    from pipeline.detectors.lstm import from_checkpoint

    path = Path(path)
    ckpt = load_torch(path, FORMAT, "detect")
    if model_hash is not None and ckpt["pose_model_hash"] != model_hash:
        raise StageError(f"{path} was trained for pose checkpoint {ckpt['pose_model_hash']!r}, not {model_hash!r}; "
                         f"re-run `rpod shap` and `rpod detect`")
    return from_checkpoint(ckpt), ckpt


def _clean_nan(obj: Any) -> Any:
    """NaN -> None, recursively (JSON has no NaN)."""
    if isinstance(obj, dict):
        return {k: _clean_nan(v) for k, v in obj.items()}
    if isinstance(obj, float) and math.isnan(obj):
        return None
    return obj


def main() -> None:
    """Train the LSTM detector and the baselines on one split of the SHAP store; write the report."""
    import torch
    from dvclive import Live
    from tqdm import tqdm

    from pipeline.detectors.lstm import LSTMConfig, to_checkpoint, train_lstm
    from pipeline.detectors.metrics import choose_threshold, metrics_by_eps, roc_points

    p = params_mod.load()
    d = p["detect"]
    unknown = [b for b in d["baselines"] if b not in BASELINES]
    if unknown:
        raise StageError(f"params.yaml detect.baselines: unknown {unknown}; choose from {', '.join(BASELINES)}")
    for key in ("test_fraction", "val_fraction"):
        if not 0 < float(d[key]) < 1:
            raise StageError(f"params.yaml detect.{key} must be in (0, 1), got {d[key]!r}")
    torch.set_num_threads(1)  # the LSTM's matrices are small: extra threads cost more than they give
    seed = int(p["seed"]) + SEED_OFFSET
    model_hash = file_hash(MODEL)
    data = read_store(SHAP, model_hash)
    values, feats, eps = data["values"], data["features"], data["eps"].astype(np.float64)
    y = data["is_adversarial"].astype(np.int64)
    tr, va, te = split_indices(eps, data["source_index"], float(d["test_fraction"]), float(d["val_fraction"]), seed)
    print(f"detect: {len(y)} SHAP samples ({int(y.sum())} adversarial) -> train {len(tr)}, validation {len(va)}, "
          f"test {len(te)}", flush=True)

    # the paper's LSTM detector
    config = LSTMConfig(n_rows=values.shape[1], n_features=values.shape[2], hidden=int(d["hidden"]),
                        dense=[int(x) for x in d["dense"]])
    live = Live(dir=LIVE_DIR, dvcyaml=False, save_dvc_exp=False, report=None)
    bar = tqdm(total=int(d["epochs"]), desc="detect: LSTM", unit="epoch")

    def on_epoch(rec: dict[str, float]) -> None:
        for k in ("train_loss", "val_loss", "val_accuracy"):
            live.log_metric(k, rec[k])
        live.next_step()
        bar.update(1)
        bar.set_postfix(val_loss=f"{rec['val_loss']:.4f}", val_acc=f"{rec['val_accuracy']:.3f}")

    t0 = time.perf_counter()
    result = train_lstm(values[tr], y[tr], values[va], y[va], config, epochs=int(d["epochs"]),
                        patience=int(d["patience"]), batch_size=int(d["batch_size"]), lr=float(d["lr"]),
                        seed=seed, on_epoch=on_epoch)
    bar.close()
    lstm_seconds = time.perf_counter() - t0
    lstm = result.model
    scores: dict[str, tuple[np.ndarray, float]] = {
        "lstm": (lstm.predict_proba(values[te]), float(lstm.threshold))}
    seconds = {"lstm": lstm_seconds}

    # baselines, same split, thresholds on the same validation samples
    for name in d["baselines"]:
        t0 = time.perf_counter()
        s_val, s_test = _baseline(name, p, data, y, tr, va, te, seed)
        scores[name] = (s_test, choose_threshold(s_val, y[va]))
        seconds[name] = time.perf_counter() - t0
        print(f"detect: {name} baseline in {seconds[name]:.1f} s", flush=True)

    results = {name: metrics_by_eps(y[te], s, eps[te], thr) for name, (s, thr) in scores.items()}
    for k, v in results["lstm"]["all"].items():
        live.log_metric(f"test/{k}", v, plot=False)
    live.end()

    ckpt = to_checkpoint(lstm, {
        "format": FORMAT, "pose_model_hash": model_hash, "shap_method": data["attrs"].get("method"),
        "background_mean": torch.tensor(data["attrs"]["background_mean"], dtype=torch.float32),
        "background_size": int(data["attrs"]["background_size"]),
        "eps": sorted({float(e) for e in eps[y == 1]}, reverse=True),
        "best_epoch": result.best_epoch, "test_accuracy": results["lstm"]["all"]["accuracy"]})
    save_torch(DETECTOR, ckpt)
    ROC_DIR.mkdir(parents=True, exist_ok=True)
    for name, (s, _) in scores.items():
        roc = roc_points(y[te], s)
        lines = ["fpr,tpr"] + [f"{a:.6f},{b:.6f}" for a, b in zip(roc["fpr"], roc["tpr"])]
        atomic_write_text(ROC_DIR / f"{name}.csv", "\n".join(lines) + "\n")
    for stale in ROC_DIR.glob("*.csv"):
        if stale.stem not in scores:
            stale.unlink()
    counts = {"samples": int(len(y)), "train": int(len(tr)), "validation": int(len(va)), "test": int(len(te)),
              "test_clean": int((y[te] == 0).sum()), "test_adversarial": int(y[te].sum())}
    metrics = {"model_hash": model_hash, "counts": counts, "threshold": {k: v[1] for k, v in scores.items()},
               "lstm_epochs": len(result.history), "lstm_best_epoch": result.best_epoch,
               "seconds": seconds, "paper_accuracy": PAPER_ACCURACY, "detectors": results}
    write_metrics(METRICS, _clean_nan(metrics), p)
    atomic_write_text(REPORT, _report(results, scores, counts, result, data["attrs"], d))
    acc = results["lstm"]["all"]["accuracy"]
    print(f"detect: LSTM test accuracy {acc:.4f} (paper {PAPER_ACCURACY:.4f}) -> {DETECTOR}, {REPORT}")


def _baseline(name: str, p: dict[str, Any], data: dict[str, Any], y: np.ndarray, tr: np.ndarray,
              va: np.ndarray, te: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Validation and test scores of one baseline fitted on the training indices."""
    d = p["detect"]
    values, feats = data["values"], data["features"]
    if name == "mlp":
        from pipeline.detectors.mlp import MLPDetector

        det = MLPDetector(hidden=tuple(int(h) for h in d["mlp_hidden"]), seed=seed).fit(values[tr], y[tr])
        return det.score(values[va]), det.score(values[te])
    if name == "mahalanobis":
        from pipeline.detectors.mahalanobis import MahalanobisDetector
        from stages.data import load_labels

        labels = load_labels().set_index("index")
        try:
            ranges = labels.loc[data["source_index"], "range"].to_numpy(np.float64)
        except KeyError:
            raise StageError(f"{SHAP}/source_index names images missing from datasets/labels.parquet "
                             f"(re-run `rpod shap`)") from None
        groups = np.digitize(ranges, np.sort(np.asarray(p["train"]["range_bins"], dtype=np.float64)))
        clean_tr = tr[y[tr] == 0]
        det = MahalanobisDetector().fit(feats[clean_tr], groups[clean_tr])
        return det.score(feats[va]), det.score(feats[te])
    if name == "lid":
        from pipeline.detectors.lid import LIDDetector

        det = LIDDetector(k=int(d["lid_k"]), batch_size=int(d["lid_batch"]), seed=seed).fit(feats[tr], y[tr])
        return det.score(feats[va]), det.score(feats[te])
    return _squeeze(p, data, y, tr, va, te)


def _squeeze(p: dict[str, Any], data: dict[str, Any], y: np.ndarray, tr: np.ndarray, va: np.ndarray,
             te: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Feature squeezing needs the images and the pose model: rebuild each sample's image from its
    source (stages.shap.Sources: clean split image, adv.zarr, or the same FGSM) and score it."""
    import torch
    from tqdm import tqdm

    from pipeline.attacks import attack_loss
    from pipeline.detectors.squeeze import SqueezeDetector
    from stages.checkpoint import load_pose_loss, load_pose_model
    from stages.shap import SPLIT_CODES, Sources

    d = p["detect"]
    model = load_pose_model(MODEL, p)
    src = Sources(p, model, attack_loss(p["attack"]["loss"], load_pose_loss(MODEL, p)), file_hash(MODEL))
    names = {v: k for k, v in SPLIT_CODES.items()}
    split = np.array([names[int(c)] for c in data["split"]])
    index, eps = data["source_index"], data["eps"].astype(np.float64)

    def predict(images: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return model(torch.from_numpy(np.ascontiguousarray(images)).permute(0, 3, 1, 2).float() / 255).numpy()

    det = SqueezeDetector(predict, bits=int(d["squeeze_bits"]), median_size=int(d["squeeze_median"]))
    clean_tr = tr[y[tr] == 0][:512]
    det.fit(src.images(split[clean_tr], index[clean_tr], eps[clean_tr]))

    def score(rows: np.ndarray, what: str) -> np.ndarray:
        out = np.zeros(len(rows))
        for sl, imgs in tqdm(src.iter_images(split[rows], index[rows], eps[rows]), desc=f"detect: squeeze ({what})",
                             total=-(-len(rows) // 64), unit="batch", leave=False):
            out[sl] = det.score(imgs)
        return out

    return score(va, "validation"), score(te, "test")


def _report(results: dict[str, dict[str, dict[str, float]]], scores: dict[str, Any], counts: dict[str, int],
            result: Any, attrs: dict[str, Any], d: dict[str, Any]) -> str:
    from pipeline.report import markdown_table

    def row(m: dict[str, float]) -> dict[str, Any]:
        return {"n": m["n"], "accuracy": m["accuracy"], "precision": m["precision"], "recall": m["recall"],
                "FPR": m["fpr"], "ROC-AUC": m["roc_auc"], "TPR @ 1% FPR": m["tpr_at_1pct_fpr"]}

    def nan_dash(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
        return [{k: ("-" if isinstance(v, float) and math.isnan(v) else v) for k, v in r.items()} for r in rows]

    lstm = results["lstm"]
    lstm_rows = [{"eps": k, **row(m)} for k, m in lstm.items()]
    lstm_table = markdown_table(nan_dash(lstm_rows), decimals=4)
    names = {"lstm": "LSTM on SHAP (paper)", "mlp": "MLP on SHAP", "mahalanobis": "Mahalanobis on GAP features",
             "lid": "LID on GAP features", "squeeze": "feature squeezing on images"}
    comp = [{"detector": names[k], **row(r["all"])} for k, r in results.items()]
    eps_keys = [k for k in lstm if k != "all"]
    recall_rows = [{"detector": names[k], **{f"eps {e}": r[e]["recall"] for e in eps_keys},
                    "FPR": r["all"]["fpr"]} for k, r in results.items()]
    best = max(results, key=lambda k: results[k]["all"]["accuracy"])
    rates = ", ".join(f"{e}: {lstm[e]['recall']:.0%}" for e in eps_keys)
    reading = (f"Detection rate of the LSTM by eps: {rates}; false alarms on clean images: {lstm['all']['fpr']:.1%}. "
               f"Highest test accuracy of all detectors here: {names[best]} ({results[best]['all']['accuracy']:.2%}).")
    paper = f"{PAPER_ACCURACY * 100:.2f}%"
    ours = f"{lstm['all']['accuracy'] * 100:.2f}%"
    return f"""# Attack detector

The paper's detector (SPEC 7) reads the DeepSHAP values of the pose network's 1000 GAP features
for its 9 outputs (a 9 x 1000 sequence per image, `rpod shap`) and says whether the image was
attacked: an LSTM of {d['hidden']} units with ReLU, dense layers {d['dense']}, one sigmoid output,
Adadelta (lr {d['lr']}), early stopping after {d['patience']} epochs without a lower validation loss.

**Test accuracy: {ours}** (paper: {paper} on its 30,000 SHAP samples).
{reading}

Data: {counts['samples']} SHAP samples (`datasets/shap.zarr`, method `{attrs.get('method')}`, background
of {attrs.get('background_size')} training images). Split {1 - d['test_fraction']:.0%}/{d['test_fraction']:.0%} train/test with
{d['val_fraction']:.0%} of train held out for validation (grouped by source image: the clean and every eps version of
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
- **LID** (Ma et al. 2018): LID of the GAP features from the k = {d['lid_k']} nearest clean neighbours
  in minibatches of {d['lid_batch']}, then logistic regression; test frames against clean training minibatches.
- **Feature squeezing** (Xu et al. 2018): pose change (L1 over the 9 outputs, each divided by its
  clean standard deviation) under {d['squeeze_bits']}-bit colour depth and a {d['squeeze_median']}x{d['squeeze_median']}
  median filter; score = the larger change. Needs the image and two extra pose passes per frame.

What the SHAP detectors see: with the linear heads, row j of a sample's SHAP values is
`W[j] * (a - mean_background)` (pipeline/explain.py), an element-wise rescaling of the GAP features.
The SHAP signature therefore carries the same information as the GAP features, weighted by how much
each feature moves each output; the SHAP detectors and the GAP-feature baselines differ in the model
they fit, not in what they can know.

ROC curves: `dvc plots show` (reports/plots/roc/). Training curves: dvclive/detect/.
"""
