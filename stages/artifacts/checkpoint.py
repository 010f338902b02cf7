"""Pose-model checkpoints: weights + architecture + input size, loaded safely and checked against params.

A checkpoint is a plain dict (loadable with `torch.load(weights_only=True)`):
    format: "rpodguard-pose/1", arch: {width, dropout}, input_size: [height, width] (pixels),
    model: the PoseNet state dict, loss: {s_p, s_r, reduction} (the learned loss, for attacks),
    meta: small JSON-like facts (epoch, errors, ...).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

from stages.artifacts.paths import POSE
from stages.config.schema import Params
from stages.io import StageError, load_torch, save_torch

FORMAT = "rpodguard-pose/1"


def expected(params: Params) -> dict[str, Any]:
    """The architecture and input size that params.yaml asks for."""
    return {"arch": {"width": float(params.train.width), "dropout": float(params.train.dropout)},
            "input_size": [params.render.height, params.render.width]}


def save_pose(path: Path | str, model: Any, loss: Any, input_size: tuple[int, int], meta: dict[str, Any]) -> None:
    """Write a checkpoint atomically (temporary file + rename)."""
    state = {
        "format": FORMAT,
        "arch": model.arch(),
        "input_size": [int(input_size[0]), int(input_size[1])],
        "model": {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()},
        "loss": {"s_p": loss.s_p.item(), "s_r": loss.s_r.item(), "reduction": loss.reduction},
        "meta": meta,
    }
    save_torch(path, state)


def read_pose(path: Path | str = POSE, params: Params | None = None) -> dict[str, Any]:
    """Load a checkpoint with weights_only=True; with params, refuse an architecture/input-size mismatch."""
    path = Path(path)
    ckpt = load_torch(path, FORMAT, "train")
    if params is not None:
        want = expected(params)
        have = {"arch": ckpt["arch"], "input_size": list(ckpt["input_size"])}
        diffs = [f"{k}={have['arch'].get(k)} (params: {v})" for k, v in want["arch"].items() if have["arch"].get(k) != v]
        if have["input_size"] != want["input_size"]:
            diffs.append(f"input_size HxW={have['input_size']} (params: {want['input_size']})")
        if diffs:
            raise StageError(f"pose checkpoint {path} does not match params.yaml: {', '.join(diffs)}; "
                             f"re-run `rpod train` or restore the params it was trained with")
    return ckpt


def model_from_checkpoint(ckpt: dict[str, Any], device: Any = "cpu", amp: bool = False):
    """The PoseNet of a checkpoint dict, in eval mode on `device` (`amp`: bf16 autocast there, CUDA only)."""
    from pipeline.pose.model import PoseNet

    model = PoseNet(**ckpt["arch"])
    model.load_state_dict(ckpt["model"])
    return model.place(device, amp).eval()


def loss_from_checkpoint(ckpt: dict[str, Any]):
    """The PoseLoss with the learned weights s_p, s_r of a checkpoint dict (what attacks ascend)."""
    import torch

    from pipeline.pose.loss import PoseLoss

    loss = PoseLoss(ckpt["loss"]["reduction"])
    with torch.no_grad():
        loss.s_p.fill_(ckpt["loss"]["s_p"])
        loss.s_r.fill_(ckpt["loss"]["s_r"])
    return loss


def load_pose_model(path: Path | str = POSE, params: Params | None = None, device: str = "cpu"):
    """The PoseNet of a checkpoint file, in eval mode on `device` (checked against params when given)."""
    return model_from_checkpoint(read_pose(path, params), device)


def load_pose_loss(path: Path | str = POSE, params: Params | None = None):
    """The PoseLoss with the learned weights s_p, s_r of a checkpoint file."""
    return loss_from_checkpoint(read_pose(path, params))
