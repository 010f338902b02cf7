"""The data readers the stages share (paths: stages/artifacts/paths.py; models: stages/artifacts/models.py).

Readers check what they read and raise a DataError (or StageError) naming the file and the stage that writes it:
- `read_render_store` (render output), `read_eval_render` (eval_render output, the evaluation or the
  defense's validation trajectories, checked against params), `read_detect_render` (the detector split,
  `rpod eval_render --detector`), `read_heldout` (the final held-out sets of `rpod heldout`), `chaser_motion`
  (what the chaser knows of itself on those),
  `read_shap_store` (checked SHAP store);
- `SampleImages`: the image of a SHAP sample (detector-split index, eps): the clean render, or the same
  FGSM with the same 8-bit quantisation (shared by `rpod shap` and `rpod detect`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Iterator

import numpy as np

from pipeline.formats.renders import read_renders
from pipeline.geometry.labels import POSITION, SIXD
from pipeline.io.store import open_zarr
from stages.artifacts.paths import DETECT_RENDER, EVAL_RENDER, VAL_ENVELOPE, VAL_RENDER
from stages.config.params import (
    detect_render_fingerprint,
    eval_render_fingerprint,
    heldout_fingerprint,
    val_envelope_fingerprint,
    val_render_fingerprint,
)
from stages.config.schema import Params
from stages.errors import StageError

BATCH = 64  # images per forward pass when rebuilding SHAP sample images
PRELOAD_BYTES = 8 << 30  # a detector split up to this size is read into memory at once


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
    folder, fingerprint = (
        (VAL_RENDER, val_render_fingerprint(p)) if validation else (EVAL_RENDER, eval_render_fingerprint(p))
    )
    r = _trajectory_renders(folder, fingerprint, "rpod eval_render", "eval_render", "evaluation")
    return r.images[:], r.poses, r.meta


def read_val_envelope(p: Params) -> tuple[np.ndarray, Any]:
    """The envelope validation frames (`rpod eval_render` -> datasets/val_envelope): (images (N, H, W, 3) uint8,
    poses table), checked against the current params; the detector's calibration reads them beside
    datasets/val_render."""
    r = _trajectory_renders(
        VAL_ENVELOPE, val_envelope_fingerprint(p), "rpod eval_render", "eval_render", "envelope validation"
    )
    return r.images[:], r.poses


def read_heldout(p: Params, folder: Path) -> tuple[np.ndarray, Any]:
    """A final held-out set (`rpod heldout` -> datasets/heldout/<camera>, rendered with `p`'s camera): (images (N,
    H, W, 3) uint8, poses table), checked against `p`."""
    r = _trajectory_renders(folder, heldout_fingerprint(p), "rpod heldout", "heldout", "held-out")
    return r.images[:], r.poses


def read_detect_render(p: Params) -> tuple[Any, Any, dict[str, Any]]:
    """The detector split (`rpod eval_render --detector`): (images: zarr array (N, H, W, 3) uint8, read
    lazily; poses table; meta), checked against the current params."""
    r = _trajectory_renders(
        DETECT_RENDER, detect_render_fingerprint(p), "rpod eval_render --detector", "detect_render", "detector-split"
    )
    return r.images, r.poses, r.meta


def _trajectory_renders(folder: Path, fingerprint: str, command: str, stage: str, what: str) -> Any:
    """A folder of rendered trajectories (pipeline.formats.renders), refused when params changed since;
    `what` names them in messages ("evaluation": evaluation renders, evaluation poses)."""

    def check(meta: dict[str, Any]) -> None:
        if not meta.get("complete") or meta.get("fingerprint") != fingerprint:
            raise StageError(
                f"{folder} was rendered with other params (or is incomplete); run `{command}` (dvc repro {stage})"
            )

    return read_renders(folder, f"{what} renders", f"run `{command}`", poses=f"{what} poses", check=check)


COMMANDS = ["cmd_x", "cmd_y", "cmd_z"]  # eval_render poses: the commanded displacement of rel (world, m)


def chaser_motion(poses: Any) -> tuple[np.ndarray, np.ndarray]:
    """What the chaser knows of itself on an eval_render trajectory table: camera attitudes (N, 3, 3,
    camera -> world) and the commanded displacement of rel since the previous frame (N, 3, world, m;
    zero on each trajectory's first frame): the planned step it commanded (`cmd_*`), not the flown one (the
    truth, `rel_*`, carries the execution error it is not told)."""
    missing = [c for c in COMMANDS if c not in poses.columns]
    if missing:
        raise StageError(
            f"eval_render poses lack the commands {missing} (rendered before execution error); "
            f"run `rpod eval_render` (dvc repro eval_render)"
        )
    R_cam = poses[[f"c{j}" for j in range(9)]].to_numpy(np.float64).reshape(-1, 3, 3)
    u = poses[COMMANDS].to_numpy(np.float64).copy()
    u[np.r_[True, np.diff(poses["trajectory"].to_numpy()) != 0]] = 0.0
    return R_cam, u


def read_shap_store(path: Path, model_hash: str) -> dict[str, Any]:
    """The SHAP store's arrays and attrs, checked: model hash, shapes, NaNs, both classes present."""
    root = open_zarr(path, "SHAP store")
    need = ["values", "features", "is_adversarial", "eps", "source_index"]
    missing = [k for k in need if k not in root]
    if missing:
        raise StageError(f"{path} lacks arrays {missing} (re-run `rpod shap`)")
    attrs = dict(root.attrs)
    if attrs.get("model_hash") != model_hash:
        raise StageError(
            f"{path} was made with another pose checkpoint (hash {attrs.get('model_hash')!r}, "
            f"the pose model's is {model_hash!r}); re-run `rpod shap`"
        )
    values = root["values"]
    n = values.shape[0]
    if values.ndim != 3 or values.shape[1] != 9 or n == 0:
        raise StageError(
            f"{path}/values must be (N, 9, n_features) with N > 0, got {tuple(values.shape)} (re-run `rpod shap`)"
        )
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
            raise StageError(
                f"{path}/{k} has NaN or infinite entries in {int(bad.sum())} samples "
                f"(first: sample {int(np.argmax(bad))}); re-run `rpod shap`"
            )
    y = out["is_adversarial"].astype(bool)
    if y.all() or not y.any():
        raise StageError(
            f"{path} holds only {'adversarial' if y.all() else 'clean'} samples; a detector needs both "
            f"(check shap.normal, shap.per_eps and shap.eps)"
        )
    if not np.array_equal(y, out["eps"] > 0):
        raise StageError(f"{path}: is_adversarial disagrees with eps > 0 (re-run `rpod shap`)")
    return out


SPLIT_KEY = "detect_render_fingerprint"  # SHAP store attribute: the fingerprint of the detector split it explains


def check_shap_split(attrs: dict[str, Any], params: Params, path: Path) -> None:
    """Refuse a SHAP store (its `attrs`) made from another detector split than params.yaml's (its fingerprint,
    recorded by `rpod shap`): its source_index rows would name other images."""
    want = detect_render_fingerprint(params)
    if attrs.get(SPLIT_KEY) != want:
        raise StageError(
            f"{path} explains another detector split than {DETECT_RENDER} of params.yaml (fingerprint "
            f"{attrs.get(SPLIT_KEY) or 'not recorded'}, params give {want}); re-run "
            f"`rpod shap --model {attrs.get('model', 'standard')}`"
        )


def _key(eps: float) -> float:
    """eps as the attack takes it: the SHAP store keeps eps as float32, params as float64 (0.05, not 0.0500000007)."""
    return round(float(eps), 6)


class SampleImages:
    """The image of a SHAP sample (row of the detector split, eps): the clean render of
    datasets/detect_render, or its FGSM at eps by the pose model on `attack.loss`, stored as 8 bits
    (`pipeline.attacks.gradient.stored_attack`, as a camera would deliver it)."""

    def __init__(self, params: Params, model: Any, loss_fn: Any):
        self.model, self.loss_fn = model, loss_fn
        images, self.poses, meta = read_detect_render(params)
        self.fingerprint = meta["fingerprint"]  # of the detector split: what a SHAP store records (SPLIT_KEY)
        self.clean = images[:] if int(np.prod(images.shape)) <= PRELOAD_BYTES else images
        self.targets = self.poses[POSITION + SIXD].to_numpy(np.float32)  # (N, 9): m, 6-D

    def __len__(self) -> int:
        return len(self.targets)

    def images(self, index: np.ndarray, eps: np.ndarray) -> np.ndarray:
        """uint8 (N, H, W, 3) images of samples given by detector-split row and eps (0 = clean)."""
        import torch

        from pipeline.attacks.gradient import stored_attack

        index, keys = np.asarray(index, dtype=np.int64), np.array([_key(x) for x in eps])
        out = np.stack([np.asarray(self.clean[int(i)]) for i in index])
        for e in sorted(set(keys.tolist()) - {0.0}):
            ks = np.flatnonzero(keys == e)
            dev = self.model.device
            x = torch.from_numpy(out[ks]).to(dev).permute(0, 3, 1, 2).float() / 255
            y = torch.as_tensor(self.targets[index[ks]]).to(dev)
            adv = stored_attack(self.model, self.loss_fn, e)(x, y)
            out[ks] = torch.round(adv * 255).to(torch.uint8).permute(0, 2, 3, 1).cpu().numpy()
        return out

    def iter_images(self, index: np.ndarray, eps: np.ndarray, batch: int = BATCH) -> Iterator[tuple[slice, np.ndarray]]:
        for s in range(0, len(index), batch):
            sl = slice(s, s + batch)
            yield sl, self.images(index[sl], eps[sl])
