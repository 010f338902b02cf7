"""The data readers the stages share (paths: stages/artifacts/paths.py; models: stages/artifacts/models.py).

Readers check what they read and raise a DataError (or StageError) naming the file and the stage that writes it:
- `read_render_store` (render output), `read_eval_render` (eval_render output, the evaluation or the
  defense's validation trajectories, checked against params), `chaser_motion` (what the chaser knows of
  itself on those), `read_shap_store` (checked SHAP store);
- `SampleImages`: the image of a SHAP sample (split, label index, eps) from the labelled renders,
  the attack stage's adv.zarr, or the same FGSM (shared by `rpod shap` and `rpod detect`).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Iterator

import numpy as np

from pipeline.formats.renders import read_renders
from pipeline.io.store import open_zarr
from stages.artifacts.data import load_split
from stages.artifacts.paths import ADV, EVAL_RENDER, POSE, VAL_RENDER
from stages.config.params import eval_render_fingerprint, val_render_fingerprint
from stages.config.schema import Params
from stages.errors import StageError

SPLIT_CODES = {"train": 0, "test": 1}   # `split` codes of the SHAP store
BATCH = 64                              # images per forward pass when rebuilding SHAP sample images


def adv_array_name(eps: float) -> str:
    """Name of the adv.zarr array holding the images attacked at `eps` (e.g. eps_0.5)."""
    return f"eps_{float(eps):g}"


def read_render_store(path: Path, what: str = "render output") -> tuple[Any, Any, dict[str, Any]]:
    """The render output folder (pipeline.formats.renders), verified complete and consistent ->
    (images zarr array (N, H, W, 3) uint8, poses table, meta)."""
    r = read_renders(path, what, "re-run `rpod render`", poses=f"{what} poses")
    return r.images, r.poses, r.meta


def read_eval_render(p: Params, validation: bool = False) -> tuple[np.ndarray, Any, dict[str, Any]]:
    """The `eval_render` output: (images (N, H, W, 3) uint8, poses table, meta), checked against the
    current params; the evaluation trajectories, or with `validation` the defense's (datasets/val_render)."""
    folder, fingerprint = (VAL_RENDER, val_render_fingerprint(p)) if validation else (EVAL_RENDER,
                                                                                   eval_render_fingerprint(p))

    def check(meta: dict[str, Any]) -> None:
        if not meta.get("complete") or meta.get("fingerprint") != fingerprint:
            raise StageError(f"{folder} was rendered with other params (or is incomplete); "
                             f"run `rpod eval_render` (dvc repro eval_render)")

    r = read_renders(folder, "evaluation renders", "run `rpod eval_render`", poses="evaluation poses", check=check)
    return r.images[:], r.poses, r.meta


def chaser_motion(poses: Any) -> tuple[np.ndarray, np.ndarray]:
    """What the chaser knows of itself on an eval_render trajectory table: camera attitudes (N, 3, 3,
    camera -> world) and the commanded displacement of rel since the previous frame (N, 3, world, m;
    zero on each trajectory's first frame)."""
    R_cam = poses[[f"c{j}" for j in range(9)]].to_numpy(np.float64).reshape(-1, 3, 3)
    rel = poses[["rel_x", "rel_y", "rel_z"]].to_numpy(np.float64)
    u = np.zeros_like(rel)
    u[1:] = np.diff(rel, axis=0)
    u[np.r_[True, np.diff(poses["trajectory"].to_numpy()) != 0]] = 0.0
    return R_cam, u


def read_shap_store(path: Path, model_hash: str) -> dict[str, Any]:
    """The SHAP store's arrays and attrs, checked: model hash, shapes, NaNs, both classes present."""
    root = open_zarr(path, "SHAP store")
    need = ["values", "features", "is_adversarial", "eps", "source_index", "split"]
    missing = [k for k in need if k not in root]
    if missing:
        raise StageError(f"{path} lacks arrays {missing} (re-run `rpod shap`)")
    attrs = dict(root.attrs)
    if attrs.get("model_hash") != model_hash:
        raise StageError(f"{path} was made with another pose checkpoint (hash {attrs.get('model_hash')!r}, "
                         f"{POSE} is {model_hash!r}); re-run `rpod shap`")
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


def _key(eps: float) -> float:
    """eps as a lookup key: the SHAP store keeps eps as float32, params and adv.zarr as float64."""
    return round(float(eps), 6)


class SampleImages:
    """The image of a SHAP sample (split, label index, eps): the two pose splits, the model and attack
    loss for FGSM, and the usable arrays of adv.zarr (FGSM by this pose model on `attack.loss`)."""

    def __init__(self, params: Params, model: Any, loss_fn: Any, model_hash: str):
        self.model, self.loss_fn = model, loss_fn
        self.splits = {name: load_split(params, name) for name in SPLIT_CODES}
        self.row_of = {name: {int(ix): r for r, ix in enumerate(sp.labels["index"].to_numpy())}
                       for name, sp in self.splits.items()}
        self.stack: dict[float, Any] = {}
        self.stack_row: dict[int, int] = {}
        self.stack_note = "no datasets/attack/adv.zarr"
        if ADV.exists():
            root = open_zarr(ADV, "adversarial store")
            attrs = dict(root.attrs)
            if attrs.get("method") != "fgsm":
                self.stack_note = f"adv.zarr was made with {attrs.get('method')!r}, not FGSM"
            elif attrs.get("model_hash") != model_hash:
                self.stack_note = "adv.zarr was made with another pose checkpoint"
            elif attrs.get("loss") != params.attack.loss:
                self.stack_note = f"adv.zarr attacked the {attrs.get('loss')!r} loss, not attack.loss"
            else:
                self.stack = {_key(e): root[adv_array_name(e)] for e in attrs.get("eps", [])
                              if adv_array_name(e) in root}
                self.stack_row = {int(ix): r for r, ix in enumerate(root["source_index"][:])}
                self.stack_note = f"adv.zarr holds eps {sorted(self.stack)} for {len(self.stack_row)} test images"

    def in_stack(self, split: str, index: int, eps: float) -> bool:
        return split == "test" and _key(eps) in self.stack and index in self.stack_row

    def images(self, split: np.ndarray, index: np.ndarray, eps: np.ndarray) -> np.ndarray:
        """uint8 (N, H, W, 3) images of samples given by split name, label index and eps (0 = clean)."""
        import torch

        from pipeline.attacks.gradient import stored_attack

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
                dev = self.model.device
                x = torch.from_numpy(clean).to(dev).permute(0, 3, 1, 2).float() / 255
                y = torch.as_tensor(data.targets[rows]).to(dev)
                adv = stored_attack(self.model, self.loss_fn, e)(x, y)
                imgs = torch.round(adv * 255).to(torch.uint8).permute(0, 2, 3, 1).cpu().numpy()
            for k, im in zip(ks, imgs):
                out[k] = im
        return np.stack(out)  # type: ignore[arg-type]

    def iter_images(self, split: np.ndarray, index: np.ndarray, eps: np.ndarray,
                    batch: int = BATCH) -> Iterator[tuple[slice, np.ndarray]]:
        for s in range(0, len(index), batch):
            sl = slice(s, s + batch)
            yield sl, self.images(split[sl], index[sl], eps[sl])
