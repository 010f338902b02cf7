"""`rpod shap [--model standard|robust]`: DeepSHAP values of one pose model's GAP features for clean and FGSM
images -> datasets/shap.zarr (the standard model's, dvc stage `shap`) or datasets/shap_robust.zarr (the robust
model's, stage `shap_robust`; stages.artifacts.paths.CHAINS). Both use the same seed, so the same images.

Composition (params `shap`, pipeline.shap.sample_plan): `normal` clean samples and `per_eps` FGSM
samples for each eps in `shap.eps`, all from the same source images of the detector split
(datasets/detect_render, `rpod eval_render --detector`: trajectories of their own seed that the pose
network never saw). Each source image is explained clean once and attacked at one eps (every profile
has normal = per_eps x len(eps)), so the clean and the attacked class show the same images and differ
only by the attack. (Until issue 27 clean samples came from the pose test split topped up with
pose-training images, 69% of them at the default size, while every attacked one was a test image: an
unfamiliar image partly read as "attacked".) An adversarial image is FGSM (on `attack.loss`) by the
explained pose model against the image's true pose, stored as 8 bits (as the attack stage stores them).

Background: GAP features of `shap.background` random training images (seed `seed` + 500): one fixed
reference for every sample, clean or attacked.

Store (zarr, written atomically, chunked by `shap.chunk` samples):
- `values` (N, 9, 1000) float32: phi[j, i] for output j (tx, ty, tz, r0..r5) and GAP feature i;
- `features` (N, 1000) float32 GAP features; `outputs` (N, 9) float32 pose outputs;
- `is_adversarial` (N,) bool, `eps` (N,) float32 (0 = clean), `source_index` (N,) int64 = row of the
  source image in datasets/detect_render;
- attrs: model (standard | robust), model_hash (of its checkpoint), background_size, background_seed, background_mean
  (1000 floats), method (exact | deep), eps, attack, attack_loss, counts (clean, per_eps, source
  images, images explained both clean and attacked), source (the detector split and its fingerprint).
"""

from __future__ import annotations

import time
from typing import Annotated, Any

import numpy as np

from pipeline.geometry.labels import TARGET
from pipeline.io.atomic import atomic_dir
from pipeline.io.store import create_array
from pipeline.seeds import seed_for
from stages.artifacts.data import load_split
from stages.artifacts.models import load_pose, model_option
from stages.artifacts.paths import CHAINS, DETECT_RENDER, Model
from stages.artifacts.readers import BATCH, SPLIT_KEY, SampleImages
from stages.config.device import torch_setup
from stages.config.schema import Params
from stages.config.sections import Shap
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
        raise StageError(
            "params.yaml shap: need clean (shap.normal > 0) and adversarial samples "
            "(shap.per_eps > 0 and a non-empty shap.eps) for a detector to learn from"
        )


def main(
    params: Params,
    model: Annotated[Model, model_option("Writes datasets/shap.zarr or datasets/shap_robust.zarr.")] = Model.standard,
) -> None:
    """Explain clean and FGSM images of the detector split with DeepSHAP (closed form for the linear heads)
    into the chosen model's SHAP store."""
    import zarr

    from pipeline.attacks.gradient import attack_loss

    s = params.shap
    check_params(s)
    torch_setup(params)
    seed = seed_for(params.seed, "shap")
    rng = np.random.default_rng(seed)
    files = CHAINS[model]
    out = files.shap
    pose = load_pose(params, files.pose)
    net, model_hash = pose.model, pose.hash
    train = load_split(params, "train")
    if s.background > len(train):
        raise StageError(
            f"params.yaml shap.background = {s.background} but the training split has only {len(train)} images"
        )
    t0 = time.perf_counter()
    explainer, n_features = _explainer(net, train, s, rng)
    src = SampleImages(params, net, attack_loss(params.attack.loss, pose.loss))
    todo = _sample_plan(s, len(src), rng)
    n, clean = len(todo["index"]), todo["eps"] == 0
    sources = np.unique(todo["index"])
    shared = np.intersect1d(todo["index"][clean], todo["index"][~clean])
    print(
        f"shap ({model.value} model): {n} samples ({s.normal} clean + {s.per_eps} x eps {s.eps}) of {len(sources)} "
        f"detector-split images ({len(shared)} both clean and attacked), background {s.background}, method {explainer.method}",
        flush=True,
    )
    with atomic_dir(out) as tmp:
        root = zarr.open_group(str(tmp), mode="w")
        _explain_into(root, src, net, explainer, todo, n_features, s.chunk)
        root.attrs.update(_attrs(params, model, model_hash, seed, explainer, src, (len(sources), len(shared))))
    print(f"shap: {n} samples in {time.perf_counter() - t0:.0f} s -> {out}")


def _explainer(net: Any, train: Any, s: Shap, rng: np.random.Generator) -> tuple[Any, int]:
    """(the SHAP explainer of `net` against the GAP features of shap.background training images drawn with `rng`,
    the number of GAP features)."""
    from pipeline.shap import Explainer, draw_background, gap_features

    bg_rows = draw_background(len(train), s.background, rng)
    bg_features = np.concatenate(
        [
            gap_features(net, np.stack([train.images[r] for r in bg_rows[i : i + BATCH]]))[0]
            for i in range(0, len(bg_rows), BATCH)
        ]
    )
    try:
        explainer = Explainer(net, bg_features, s.method)
    except ValueError as e:
        raise StageError(f"params.yaml shap.method: {e}") from None
    return explainer, bg_features.shape[1]


def _sample_plan(s: Shap, n_images: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """The samples to explain (pipeline.shap.sample_plan: source image index and eps, 0 = clean) of the
    `n_images` detector-split images, drawn with `rng`."""
    from pipeline.shap import sample_plan

    try:
        return sample_plan(s.normal, s.per_eps, s.eps, np.arange(n_images), rng)
    except ValueError as e:
        raise StageError(f"{DETECT_RENDER}: {e}; re-run `rpod eval_render --detector`") from None


def _attrs(
    params: Params,
    model: Model,
    model_hash: str,
    seed: int,
    explainer: Any,
    src: SampleImages,
    counts: tuple[int, int],
) -> dict[str, Any]:
    """The store's attrs: the model and its checkpoint's hash, the background, the method, the attack, the
    composition (`counts`: source images, those explained both clean and attacked) and the source split."""
    s = params.shap
    sources, shared = counts
    return {
        "model": model.value,
        "model_hash": model_hash,
        "background_size": s.background,
        "background_seed": seed,
        "background_mean": explainer.bg_mean.astype(float).tolist(),
        "method": explainer.method,
        "eps": [float(e) for e in s.eps],
        "attack": "fgsm",
        "attack_loss": params.attack.loss,
        "counts": {
            "clean": s.normal,
            "per_eps": s.per_eps,
            "sources": sources,
            "shared": shared,
        },
        "source": {
            "folder": str(DETECT_RENDER),
            "images": len(src),
            "trajectories": int(src.poses["trajectory"].nunique()),
        },
        "outputs": TARGET,
        SPLIT_KEY: src.fingerprint,
    }


def _explain_into(
    root: Any, src: SampleImages, model: Any, explainer: Any, todo: dict[str, np.ndarray], n_features: int, chunk: int
) -> None:
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
        for _, imgs in src.iter_images(todo["index"][sl], todo["eps"][sl]):
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
