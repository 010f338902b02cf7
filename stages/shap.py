"""`rpod shap`: DeepSHAP values of the GAP features for clean and FGSM images (SPEC 6) -> datasets/shap.zarr.

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
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from stages import params as params_mod
from stages.io import StageError, atomic_dir, create_array, file_hash

MODEL = Path("models/pose.pt")
ADV = Path("datasets/attack/adv.zarr")
OUT = Path("datasets/shap.zarr")
SEED_OFFSET = 500
SPLIT_CODES = {"train": 0, "test": 1}
BATCH = 64  # images per forward pass


def check_params(s: dict[str, Any]) -> None:
    """Refuse bad `shap` params before any work, naming the key."""
    for key in ("background", "normal", "per_eps", "chunk"):
        v = s.get(key)
        if not isinstance(v, int) or isinstance(v, bool) or v < (1 if key in ("background", "chunk") else 0):
            raise StageError(f"params.yaml shap.{key} must be a whole number >= "
                             f"{1 if key in ('background', 'chunk') else 0}, got {v!r}")
    eps = s.get("eps")
    if not isinstance(eps, list) or not all(isinstance(e, (int, float)) and 0 < e <= 1 for e in eps):
        raise StageError(f"params.yaml shap.eps must be a list of numbers in (0, 1], got {eps!r}")
    if s.get("method") not in ("auto", "exact", "deep"):
        raise StageError(f"params.yaml shap.method must be auto, exact or deep, got {s.get('method')!r}")
    if s["normal"] == 0 or (s["per_eps"] == 0 or not eps):
        raise StageError("params.yaml shap: need clean (shap.normal > 0) and adversarial samples "
                         "(shap.per_eps > 0 and a non-empty shap.eps) for a detector to learn from")


def _key(eps: float) -> float:
    """eps as a lookup key: the store keeps eps as float32, params and adv.zarr as float64."""
    return round(float(eps), 6)


class Sources:
    """Everything needed to produce the image of a sample (split, label index, eps): the two pose
    splits, the model and attack loss for FGSM, and the usable arrays of adv.zarr."""

    def __init__(self, params: dict[str, Any], model: Any, loss_fn: Any, model_hash: str):
        from stages.data import load_split

        self.model, self.loss_fn = model, loss_fn
        self.splits = {name: load_split(params, name) for name in SPLIT_CODES}
        self.row_of = {name: {int(ix): r for r, ix in enumerate(sp.labels["index"].to_numpy())}
                       for name, sp in self.splits.items()}
        self.stack: dict[float, Any] = {}
        self.stack_row: dict[int, int] = {}
        self.stack_note = "no datasets/attack/adv.zarr"
        if ADV.exists():
            from stages.io import open_zarr

            root = open_zarr(ADV, "adversarial store")
            attrs = dict(root.attrs)
            if attrs.get("method") != "fgsm":
                self.stack_note = f"adv.zarr was made with {attrs.get('method')!r}, not FGSM"
            elif attrs.get("model_hash") != model_hash:
                self.stack_note = "adv.zarr was made with another pose checkpoint"
            elif attrs.get("loss") != params["attack"]["loss"]:
                self.stack_note = f"adv.zarr attacked the {attrs.get('loss')!r} loss, not attack.loss"
            else:
                self.stack = {_key(e): root[f"eps_{float(e):g}"] for e in attrs.get("eps", [])
                              if f"eps_{float(e):g}" in root}
                self.stack_row = {int(ix): r for r, ix in enumerate(root["source_index"][:])}
                self.stack_note = f"adv.zarr holds eps {sorted(self.stack)} for {len(self.stack_row)} test images"

    def in_stack(self, split: str, index: int, eps: float) -> bool:
        return split == "test" and _key(eps) in self.stack and index in self.stack_row

    def images(self, split: np.ndarray, index: np.ndarray, eps: np.ndarray) -> np.ndarray:
        """uint8 (N, H, W, 3) images of samples given by split name, label index and eps (0 = clean)."""
        import torch

        from pipeline.attacks import fgsm, quantize

        out: list[np.ndarray | None] = [None] * len(index)
        todo: dict[tuple[str, float], list[int]] = {}
        for k, (sp, ix, e) in enumerate(zip(split, index, eps)):
            if e > 0 and self.in_stack(sp, int(ix), float(e)):
                out[k] = np.asarray(self.stack[_key(e)][self.stack_row[int(ix)]])
            else:
                todo.setdefault((sp, _key(e)), []).append(k)
        for (sp, e), ks in todo.items():
            rows = [self.row_of[sp][int(index[k])] for k in ks]
            data = self.splits[sp]
            clean = np.stack([np.asarray(data.images[r]) for r in rows])
            if e == 0:
                imgs = clean
            else:
                x = torch.from_numpy(clean).permute(0, 3, 1, 2).float() / 255
                y = torch.as_tensor(data.targets[rows])
                imgs = quantize(fgsm(self.model, x, y, e, self.loss_fn), x).permute(0, 2, 3, 1).numpy()
            for k, im in zip(ks, imgs):
                out[k] = im
        return np.stack(out)  # type: ignore[arg-type]

    def iter_images(self, split: np.ndarray, index: np.ndarray, eps: np.ndarray,
                    batch: int = BATCH) -> Iterator[tuple[slice, np.ndarray]]:
        for s in range(0, len(index), batch):
            sl = slice(s, s + batch)
            yield sl, self.images(split[sl], index[sl], eps[sl])


def plan(s: dict[str, Any], test_index: np.ndarray, train_pool: np.ndarray,
         rng: np.random.Generator) -> dict[str, np.ndarray]:
    """The samples to explain: clean then each eps; test images first, training images to fill up."""
    def draw(n: int) -> tuple[list[str], np.ndarray]:
        n_test = min(n, len(test_index))
        if n - n_test > len(train_pool):
            raise StageError(f"params.yaml shap: {n} images asked for but only {len(test_index)} test and "
                             f"{len(train_pool)} spare training images exist; lower shap.normal / shap.per_eps")
        idx = np.concatenate([rng.choice(test_index, n_test, replace=False),
                              rng.choice(train_pool, n - n_test, replace=False)])
        return ["test"] * n_test + ["train"] * (n - n_test), idx

    split, index, eps = [], [], []
    for e, n in [(0.0, int(s["normal"]))] + [(float(e), int(s["per_eps"])) for e in s["eps"]]:
        sp, ix = draw(n)
        split += sp
        index.append(ix)
        eps += [e] * n
    return {"split": np.array(split), "index": np.concatenate(index).astype(np.int64),
            "eps": np.array(eps, dtype=np.float32)}


def gap_features(model: Any, images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """GAP features (N, 1000) and pose outputs (N, 9) of uint8 images (N, H, W, 3)."""
    import torch

    with torch.no_grad():
        x = torch.from_numpy(np.ascontiguousarray(images)).permute(0, 3, 1, 2).float() / 255
        f = model.forward_features(x)
        return f.numpy(), model.forward_head(f).numpy()


def main() -> None:
    """Explain clean and FGSM images with DeepSHAP (closed form for the linear heads) into datasets/shap.zarr."""
    import torch
    import zarr
    from tqdm import tqdm

    from pipeline.attacks import attack_loss
    from pipeline.explain import Explainer
    from stages.checkpoint import load_pose_loss, load_pose_model

    p = params_mod.load()
    s = p["shap"]
    check_params(s)
    torch.set_num_threads(2)
    seed = int(p["seed"]) + SEED_OFFSET
    rng = np.random.default_rng(seed)
    model = load_pose_model(MODEL, p)
    loss_fn = attack_loss(p["attack"]["loss"], load_pose_loss(MODEL, p))
    model_hash = file_hash(MODEL)
    src = Sources(p, model, loss_fn, model_hash)
    train = src.splits["train"]
    if s["background"] > len(train):
        raise StageError(f"params.yaml shap.background = {s['background']} but the training split has only "
                         f"{len(train)} images")
    t0 = time.perf_counter()
    bg_rows = np.sort(rng.choice(len(train), s["background"], replace=False))
    bg_features = np.concatenate([gap_features(model, np.stack([train.images[r] for r in bg_rows[i:i + BATCH]]))[0]
                                  for i in range(0, len(bg_rows), BATCH)])
    try:
        explainer = Explainer(model, bg_features, s["method"])
    except ValueError as e:
        raise StageError(f"params.yaml shap.method: {e}") from None
    train_index = train.labels["index"].to_numpy(np.int64)
    todo = plan(s, src.splits["test"].labels["index"].to_numpy(np.int64),
                np.setdiff1d(train_index, train_index[bg_rows]), rng)
    n, chunk = len(todo["index"]), int(s["chunk"])
    from_stack = np.array([e > 0 and src.in_stack(sp, int(ix), float(e))
                           for sp, ix, e in zip(todo["split"], todo["index"], todo["eps"])], dtype=bool)
    print(f"shap: {n} samples ({s['normal']} clean + {s['per_eps']} x eps {s['eps']}), background "
          f"{s['background']}, method {explainer.method}; {src.stack_note}; "
          f"{int(from_stack.sum())} adversarial images from adv.zarr, "
          f"{int(((todo['eps'] > 0) & ~from_stack).sum())} by FGSM here", flush=True)
    with atomic_dir(OUT) as tmp:
        root = zarr.open_group(str(tmp), mode="w")
        c = min(chunk, n)
        values = create_array(root, "values", shape=(n, 9, bg_features.shape[1]), chunks=(c, 9, bg_features.shape[1]),
                              dtype="float32")
        features = create_array(root, "features", shape=(n, bg_features.shape[1]), chunks=(c, bg_features.shape[1]),
                                dtype="float32")
        outputs = create_array(root, "outputs", shape=(n, 9), chunks=(c, 9), dtype="float32")
        # write whole zarr chunks at a time: explain `chunk` samples, then store them
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
        create_array(root, "from_stack", data=from_stack)
        root.attrs.update({
            "model_hash": model_hash, "background_size": int(s["background"]), "background_seed": seed,
            "background_mean": explainer.bg_mean.astype(float).tolist(), "method": explainer.method,
            "eps": [float(e) for e in s["eps"]], "attack": "fgsm", "attack_loss": p["attack"]["loss"],
            "split_codes": SPLIT_CODES, "counts": {"clean": int(s["normal"]), "per_eps": int(s["per_eps"])},
            "outputs": ["tx", "ty", "tz", "r0", "r1", "r2", "r3", "r4", "r5"],
        })
    print(f"shap: {n} samples in {time.perf_counter() - t0:.0f} s -> {OUT}")
