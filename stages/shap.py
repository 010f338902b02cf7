"""`rpod shap`: DeepSHAP values of the GAP features for clean and FGSM images -> datasets/shap.zarr.

Composition (params `shap`): `normal` clean images and `per_eps` adversarial images for each eps in
`shap.eps`. Source images come from the test split (never seen in training); clean ones are drawn
without replacement from it, and when `normal` exceeds the test split (paper scale: 15,000 vs
6,500) the rest come from training images outside the background. Each eps draws its `per_eps`
sources the same way, independently of the clean draw, so an image can appear clean and attacked
(as in the paper's pool of 32,500 images). An adversarial image is read from the attack stage's
`datasets/attack/adv.zarr` when that stack holds the eps, was made with FGSM by the current model
and holds the source image; otherwise it is computed here with the same FGSM (on `attack.loss`)
and the same uint8 quantisation, so both paths give the same image.

Background: GAP features of `shap.background` random training images (seed `seed` + 500).

Store (zarr, written atomically, chunked by `shap.chunk` samples):
- `values` (N, 9, 1000) float32: phi[j, i] for output j (tx, ty, tz, r0..r5) and GAP feature i;
- `features` (N, 1000) float32 GAP features; `outputs` (N, 9) float32 pose outputs;
- `is_adversarial` (N,) bool, `eps` (N,) float32 (0 = clean), `source_index` (N,) int64 = label
  `index` of the source image, `split` (N,) int8 (attrs `split_codes`: train 0, test 1),
  `from_stack` (N,) bool (adversarial image read from adv.zarr rather than computed here);
- attrs: model_hash (of models/pose.pt), background_size, background_seed, background_mean
  (1000 floats), method (exact | deep), eps, attack, attack_loss, counts.
"""
from __future__ import annotations

import time
from typing import Any

import numpy as np

from pipeline.io.atomic import atomic_dir
from pipeline.io.store import create_array
from pipeline.pose.labels import TARGET
from stages.artifacts.paths import SEED_OFFSET, SHAP as OUT
from stages.artifacts.readers import BATCH, SPLIT_CODES, SampleImages
from stages.artifacts.models import load_pose
from stages.config.device import torch_setup
from stages.config.sections import Shap
from stages.config.schema import Params
from stages.errors import StageError


def check_params(s: Shap) -> None:
    """Refuse bad `shap` params before any work, naming the key (stages.config.schema checked the types)."""
    for key in ("background", "normal", "per_eps", "chunk"):
        v, low = getattr(s, key), 1 if key in ("background", "chunk") else 0
        if v < low:
            raise StageError(f"params.yaml shap.{key} must be a whole number >= {low}, got {v!r}")
    if not all(0 < e <= 1 for e in s.eps):
        raise StageError(f"params.yaml shap.eps must be a list of numbers in (0, 1], got {s.eps!r}")
    if s.method not in ("auto", "exact", "deep"):
        raise StageError(f"params.yaml shap.method must be auto, exact or deep, got {s.method!r}")
    if s.normal == 0 or (s.per_eps == 0 or not s.eps):
        raise StageError("params.yaml shap: need clean (shap.normal > 0) and adversarial samples "
                         "(shap.per_eps > 0 and a non-empty shap.eps) for a detector to learn from")


def main(params: Params) -> None:
    """Explain clean and FGSM images with DeepSHAP (closed form for the linear heads) into datasets/shap.zarr."""
    import zarr

    from pipeline.attacks.gradient import attack_loss
    from pipeline.shap import Explainer, draw_background, gap_features, sample_plan

    s = params.shap
    check_params(s)
    torch_setup(params)
    seed = params.seed + SEED_OFFSET["shap"]
    rng = np.random.default_rng(seed)
    pose = load_pose(params)
    model, model_hash = pose.model, pose.hash
    src = SampleImages(params, model, attack_loss(params.attack.loss, pose.loss), model_hash)
    train = src.splits["train"]
    if s.background > len(train):
        raise StageError(f"params.yaml shap.background = {s.background} but the training split has only "
                         f"{len(train)} images")
    t0 = time.perf_counter()
    bg_rows = draw_background(len(train), s.background, rng)
    bg_features = np.concatenate([gap_features(model, np.stack([train.images[r] for r in bg_rows[i:i + BATCH]]))[0]
                                  for i in range(0, len(bg_rows), BATCH)])
    try:
        explainer = Explainer(model, bg_features, s.method)
    except ValueError as e:
        raise StageError(f"params.yaml shap.method: {e}") from None
    train_index = train.labels["index"].to_numpy(np.int64)
    try:
        todo = sample_plan(s.normal, s.per_eps, s.eps, src.splits["test"].labels["index"].to_numpy(np.int64),
                           np.setdiff1d(train_index, train_index[bg_rows]), rng)
    except ValueError as e:
        raise StageError(f"params.yaml shap: {e}; lower shap.normal / shap.per_eps") from None
    n = len(todo["index"])
    from_stack = np.array([e > 0 and src.in_stack(sp, int(ix), float(e))
                           for sp, ix, e in zip(todo["split"], todo["index"], todo["eps"])], dtype=bool)
    print(f"shap: {n} samples ({s.normal} clean + {s.per_eps} x eps {s.eps}), background "
          f"{s.background}, method {explainer.method}; {src.stack_note}; "
          f"{int(from_stack.sum())} adversarial images from adv.zarr, "
          f"{int(((todo['eps'] > 0) & ~from_stack).sum())} by FGSM here", flush=True)
    with atomic_dir(OUT) as tmp:
        root = zarr.open_group(str(tmp), mode="w")
        _explain_into(root, src, model, explainer, todo, bg_features.shape[1], s.chunk)
        create_array(root, "from_stack", data=from_stack)
        root.attrs.update({
            "model_hash": model_hash, "background_size": s.background, "background_seed": seed,
            "background_mean": explainer.bg_mean.astype(float).tolist(), "method": explainer.method,
            "eps": [float(e) for e in s.eps], "attack": "fgsm", "attack_loss": params.attack.loss,
            "split_codes": SPLIT_CODES, "counts": {"clean": s.normal, "per_eps": s.per_eps},
            "outputs": TARGET,
        })
    print(f"shap: {n} samples in {time.perf_counter() - t0:.0f} s -> {OUT}")


def _explain_into(root: Any, src: SampleImages, model: Any, explainer: Any, todo: dict[str, np.ndarray],
                  n_features: int, chunk: int) -> None:
    """Explain the planned samples into the zarr group `root` (values, features, outputs and the sample
    columns), `chunk` samples at a time so that every write fills whole zarr chunks."""
    from tqdm import tqdm

    from pipeline.shap import gap_features

    n = len(todo["index"])
    c = min(chunk, n)
    values = create_array(root, "values", shape=(n, 9, n_features), chunks=(c, 9, n_features), dtype="float32")
    features = create_array(root, "features", shape=(n, n_features), chunks=(c, n_features), dtype="float32")
    outputs = create_array(root, "outputs", shape=(n, 9), chunks=(c, 9), dtype="float32")
    bar = tqdm(total=n, desc=f"shap ({explainer.method})", unit="img")
    for start in range(0, n, c):
        sl = slice(start, min(start + c, n))
        f_parts, o_parts = [], []
        for _, imgs in src.iter_images(todo["split"][sl], todo["index"][sl], todo["eps"][sl]):
            f, o = gap_features(model, imgs)
            f_parts.append(f)
            o_parts.append(o)
            bar.update(len(imgs))
        f = np.concatenate(f_parts)
        values[sl] = explainer(f)
        features[sl] = f
        outputs[sl] = np.concatenate(o_parts)
    bar.close()
    create_array(root, "is_adversarial", data=todo["eps"] > 0)
    create_array(root, "eps", data=todo["eps"])
    create_array(root, "source_index", data=todo["index"])
    create_array(root, "split", data=np.array([SPLIT_CODES[x] for x in todo["split"]], dtype=np.int8))
