"""The models the stages load: the pose checkpoint checked against params.yaml, the pose model with its
attack loss, the onboard chain (pose model + detector), and the calibrated defense (models/defense.json).
File formats: pipeline/formats/models.py; paths: stages/artifacts/paths.py."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pipeline.formats.models import loss_from_checkpoint, model_from_checkpoint, read_pose
from pipeline.io.atomic import file_hash, read_json
from stages.artifacts.paths import DEFENSE, DETECTOR, POSE
from stages.config.build import defense_settings
from stages.config.schema import Params
from stages.errors import StageError

DEFENSE_FORMAT = "rpodguard-defense/1"


def expected(params: Params, clamped: bool = False) -> dict[str, Any]:
    """The architecture and input size that params.yaml asks for (`clamped`: of the robust model, whose
    black-level clamp is train.adversarial.black_level)."""
    arch = {"width": float(params.train.width), "dropout": float(params.train.dropout)}
    if clamped:
        arch["black_level"] = float(params.train.adversarial.black_level)
    return {"arch": arch, "input_size": [params.render.height, params.render.width]}


def read_checked(path: Path | str = POSE, params: Params | None = None) -> dict[str, Any]:
    """A pose checkpoint dict (`read_pose`); with params, refuse an architecture/input-size mismatch (a
    clamped checkpoint, models/pose_robust.pt, is checked against train.adversarial.black_level too)."""
    path = Path(path)
    ckpt = read_pose(path)
    if params is not None:
        want = expected(params, "black_level" in ckpt["arch"])
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


@dataclass
class Pose:
    """The pose model (eval mode), its learned training loss (what attacks ascend), the file's hash and
    the checkpoint's facts (`meta`: best epoch, test errors in m and deg)."""

    model: Any
    loss: Any
    hash: str
    meta: dict[str, Any]


def load_pose(params: Params, path: Path | str = POSE) -> Pose:
    """models/pose.pt (or the robust model, `path` = POSE_ROBUST) read once, checked against params
    (architecture, input size), the network placed on the `device` param's device (with `amp`); it takes
    inputs from any device and answers on theirs."""
    from stages.config.device import torch_device

    ckpt = read_checked(path, params)
    model = model_from_checkpoint(ckpt, torch_device(params), params.amp)
    return Pose(model, loss_from_checkpoint(ckpt), file_hash(path), dict(ckpt.get("meta", {})))


def load_chain(params: Params, pose_path: Path | str = POSE,
               detector_path: Path | str = DETECTOR) -> tuple[Any, Any, str]:
    """(OnboardChain, attack loss function on `attack.loss`, pose model hash) from a pose model and its detector."""
    from pipeline.attacks.gradient import attack_loss
    from pipeline.defense.chain import load_onboard_chain

    pose = load_pose(params, pose_path)
    chain = load_onboard_chain(pose.model, pose.hash, pose_path, detector_path)
    return chain, attack_loss(params.attack.loss, pose.loss), pose.hash


@dataclass(frozen=True)
class DefenseModel:
    """The calibrated defense (models/defense.json): settings from params.defense, the detector's
    threshold and the measurement-noise model fitted on validation trajectories."""

    settings: Any        # pipeline.defense.fusion.DefenseSettings
    motion: Any          # pipeline.defense.gate.MotionSettings
    noise: Any           # pipeline.defense.noise.NoiseModel
    calibration: dict[str, Any]

    def new(self, fusion: str | None = None) -> Any:
        """A fresh pipeline.defense.fusion.Defense (one per trajectory or closed-loop run), optionally with another fusion."""
        import dataclasses

        from pipeline.defense.fusion import Defense

        s = self.settings if fusion is None else dataclasses.replace(self.settings, fusion=fusion)
        return Defense(s, self.motion, self.noise)


def load_defense(p: Params, model_hash: str, threshold: float) -> DefenseModel:
    """models/defense.json checked against the pose model and detector it was calibrated with, and params."""
    from pipeline.defense.noise import NoiseModel

    cal = read_json(DEFENSE)
    if cal.get("format") != DEFENSE_FORMAT:
        raise StageError(f"{DEFENSE} is not a {DEFENSE_FORMAT} file; re-run `rpod calibrate`")
    if cal.get("pose_model_hash") != model_hash or abs(float(cal.get("threshold", -1)) - threshold) > 1e-9:
        raise StageError(f"{DEFENSE} was calibrated for another pose model or detector; re-run `rpod calibrate`")
    try:
        noise = NoiseModel(**{k: tuple(v) if isinstance(v, list) else v for k, v in cal["noise"].items()})
    except (KeyError, TypeError, ValueError) as e:
        raise StageError(f"{DEFENSE}: bad noise model ({e}); re-run `rpod calibrate`") from None
    settings, motion = defense_settings(p.defense, threshold)
    return DefenseModel(settings, motion, noise, cal)
