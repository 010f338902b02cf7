"""Model checkpoints: the pose model and the LSTM detector, as plain dicts loadable with
`torch.load(weights_only=True)` (pipeline.io.checkpoints), read back safely.

Pose (`POSE_FORMAT`, written by `rpod train`):
    format: "rpodguard-pose/1", arch: {width, dropout}, input_size: [height, width] (pixels),
    K: the 3x3 camera matrix of the training images at the input size (pixels), labels_hash: the
    `file_hash` of the label table it was trained on (both absent in checkpoints written before they were
    recorded), model: the PoseNet state dict, loss: {s_p, s_r, reduction} (the
    learned loss, for attacks), meta: small JSON-like facts (epoch, errors, ...).
Detector (`DETECTOR_FORMAT`, written by `rpod detect`): pipeline.detectors.lstm.to_checkpoint's dict
plus format, threshold, pose_model_hash (the pose file's `file_hash`), background_mean (D,) and
shap_method.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from pipeline.io.checkpoints import load_torch, save_torch
from pipeline.io.errors import DataError

POSE_FORMAT = "rpodguard-pose/1"
DETECTOR_FORMAT = "rpodguard-detector/1"
POSE_REDO = "re-run `rpod train`"      # how a bad pose checkpoint is remade, in messages
DETECTOR_REDO = "re-run `rpod detect`"


def save_pose(path: Path | str, model: Any, loss: Any, input_size: tuple[int, int], meta: dict[str, Any],
              K: Any = None, labels_hash: str | None = None) -> None:
    """Write a pose checkpoint atomically (temporary file + rename); `input_size` = (height, width) pixels,
    `K` the camera matrix (3x3, pixels at that size) of the training images and `labels_hash` the label
    table's file hash, when known."""
    state = {
        "format": POSE_FORMAT,
        "arch": model.arch(),
        "input_size": [int(input_size[0]), int(input_size[1])],
        **({} if K is None else {"K": [[float(v) for v in row] for row in K]}),
        **({} if labels_hash is None else {"labels_hash": labels_hash}),
        "model": {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()},
        "loss": {"s_p": loss.s_p.item(), "s_r": loss.s_r.item(), "reduction": loss.reduction},
        "meta": meta,
    }
    save_torch(path, state)


def read_pose(path: Path | str) -> dict[str, Any]:
    """A pose checkpoint dict, loaded with weights_only=True (a DataError when missing, foreign or non-finite)."""
    return load_torch(path, POSE_FORMAT, POSE_REDO)


def model_from_checkpoint(ckpt: dict[str, Any], device: Any = "cpu", amp: bool = False) -> Any:
    """The PoseNet of a checkpoint dict, in eval mode on `device` (`amp`: bf16 autocast there, CUDA only)."""
    from pipeline.pose.model import PoseNet

    model = PoseNet(**ckpt["arch"])
    model.load_state_dict(ckpt["model"])
    return model.place(device, amp).eval()


def loss_from_checkpoint(ckpt: dict[str, Any]) -> Any:
    """The PoseLoss with the learned weights s_p, s_r of a checkpoint dict (what attacks ascend)."""
    import torch

    from pipeline.pose.loss import PoseLoss

    loss = PoseLoss(ckpt["loss"]["reduction"])
    with torch.no_grad():
        loss.s_p.fill_(ckpt["loss"]["s_p"])
        loss.s_r.fill_(ckpt["loss"]["s_r"])
    return loss


@dataclass(frozen=True)
class Pose:
    """A pose checkpoint loaded: the PoseNet (eval mode), its learned training loss (what attacks ascend), the
    file's hash and the checkpoint's facts without the weights (`checkpoint`: arch, input_size, K, labels_hash,
    meta: best epoch, test errors in m and deg)."""

    model: Any
    loss: Any
    hash: str
    checkpoint: dict[str, Any]

    @property
    def meta(self) -> dict[str, Any]:
        return dict(self.checkpoint.get("meta", {}))


def load_pose(path: Path | str, device: Any = "cpu", amp: bool = False,
              check: Callable[[Path, dict[str, Any]], None] | None = None) -> Pose:
    """The pose checkpoint at `path` read once (`read_pose`; `check(path, checkpoint)` may refuse it before the
    network is built), its network placed on `device` (with `amp`: bf16 autocast on CUDA)."""
    from pipeline.io.atomic import file_hash

    path = Path(path)
    ckpt = read_pose(path)
    if check is not None:
        check(path, ckpt)
    facts = {k: v for k, v in ckpt.items() if k not in ("model", "loss")}
    return Pose(model_from_checkpoint(ckpt, device, amp), loss_from_checkpoint(ckpt), file_hash(path), facts)


def read_detector(path: Path | str, model_hash: str | None = None) -> tuple[Any, dict[str, Any]]:
    """The LSTM detector (eval mode) and its checkpoint dict (threshold, pose_model_hash,
    background_mean (D,) tensor, shap_method, ...). With `model_hash`, refuse a detector trained
    on another pose checkpoint's SHAP values."""
    from pipeline.detectors.lstm import from_checkpoint

    path = Path(path)
    ckpt = load_torch(path, DETECTOR_FORMAT, DETECTOR_REDO)
    if model_hash is not None and ckpt["pose_model_hash"] != model_hash:
        raise DataError(f"{path} was trained for pose checkpoint {ckpt['pose_model_hash']!r}, not {model_hash!r}; "
                        f"re-run `rpod shap` and `rpod detect`")
    return from_checkpoint(ckpt), ckpt
