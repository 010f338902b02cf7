"""The pose checkpoint (models/pose.pt; format: pipeline/formats/models.py) checked against params.yaml."""
from __future__ import annotations

from pathlib import Path
from typing import Any

from pipeline.formats.models import loss_from_checkpoint, model_from_checkpoint, read_pose
from stages.artifacts.paths import POSE
from stages.config.schema import Params
from stages.errors import StageError


def expected(params: Params) -> dict[str, Any]:
    """The architecture and input size that params.yaml asks for."""
    return {"arch": {"width": float(params.train.width), "dropout": float(params.train.dropout)},
            "input_size": [params.render.height, params.render.width]}


def read_checked(path: Path | str = POSE, params: Params | None = None) -> dict[str, Any]:
    """A pose checkpoint dict (`read_pose`); with params, refuse an architecture/input-size mismatch."""
    path = Path(path)
    ckpt = read_pose(path)
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


def load_pose_model(path: Path | str = POSE, params: Params | None = None, device: str = "cpu") -> Any:
    """The PoseNet of a checkpoint file, in eval mode on `device` (checked against params when given)."""
    return model_from_checkpoint(read_checked(path, params), device)


def load_pose_loss(path: Path | str = POSE, params: Params | None = None) -> Any:
    """The PoseLoss with the learned weights s_p, s_r of a checkpoint file."""
    return loss_from_checkpoint(read_checked(path, params))
