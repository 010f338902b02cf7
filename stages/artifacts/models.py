"""The models the stages load: the pose checkpoint checked against params.yaml, the pose model with its
attack loss, the onboard chain (pose model + its detector) and the defense calibrated for it, each by the
model it is built on (stages.artifacts.paths.CHAINS: `standard`, the paper's reproduction; `robust`, the
chain that ships). File formats: pipeline/formats/models.py; paths: stages/artifacts/paths.py."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pipeline.formats.models import check_role, loss_from_checkpoint, model_from_checkpoint, read_pose
from pipeline.io.atomic import file_hash
from stages.artifacts.paths import CHAINS, LABELS, POSE, POSE_ROBUST, Model
from stages.config.build import defense_settings
from stages.config.schema import Params
from stages.errors import StageError

def model_option(outputs: str) -> Any:
    """The `--model` option of the commands that run once per pose model (shap, detect, calibrate); `outputs`:
    what each model's run writes."""
    import typer

    return typer.Option("--model", help="The pose model: standard (models/pose.pt, `rpod train`, the paper's "
                                        f"reproduction) or robust (models/pose_robust.pt, the one that ships). {outputs}")


def expected(params: Params, clamped: bool = False) -> dict[str, Any]:
    """The architecture and input size that params.yaml asks for (`clamped`: of the robust model, whose
    black-level clamp is train.adversarial.black_level)."""
    arch = {"width": float(params.train.width), "dropout": float(params.train.dropout)}
    if clamped:
        arch["black_level"] = float(params.train.adversarial.black_level)
    return {"arch": arch, "input_size": [params.render.height, params.render.width]}


def read_checked(path: Path | str = POSE, params: Params | None = None) -> dict[str, Any]:
    """A pose checkpoint dict (`read_pose`); with params, refuse an architecture/input-size mismatch (a
    clamped checkpoint, models/pose_robust.pt, is checked against train.adversarial.black_level too) and a
    model trained on another datasets/labels.parquet than the one there (its recorded hash)."""
    path = Path(path)
    ckpt = read_pose(path)
    check_role(ckpt, path.name == POSE_ROBUST.name, path)   # the robust model's file holds a clamped one, no other
    if params is not None:
        want = expected(params, "black_level" in ckpt["arch"])
        have = {"arch": ckpt["arch"], "input_size": list(ckpt["input_size"])}
        diffs = [f"{k}={have['arch'].get(k)} (params: {v})" for k, v in want["arch"].items() if have["arch"].get(k) != v]
        if have["input_size"] != want["input_size"]:
            diffs.append(f"input_size HxW={have['input_size']} (params: {want['input_size']})")
        if diffs:
            raise StageError(f"pose checkpoint {path} does not match params.yaml: {', '.join(diffs)}; "
                             f"re-run `rpod train` or restore the params it was trained with")
        if "labels_hash" in ckpt and LABELS.exists() and file_hash(LABELS) != ckpt["labels_hash"]:
            raise StageError(f"pose checkpoint {path} was trained on another {LABELS} (relabelled since); "
                             f"re-run `rpod train`")
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


def load_pose_chain(params: Params, model: Model | str, root: Path | str = ".") -> tuple[Pose, Any]:
    """(Pose, OnboardChain) of one chain (`model`: standard or robust, stages.artifacts.paths.CHAINS): its pose
    model and the detector trained on that model's SHAP values (refused when it names another model's hash),
    read from `root` (the working folder, or e.g. datasets/lab_models)."""
    from pipeline.defense.chain import load_onboard_chain

    files = CHAINS[Model(model)]
    pose_path, detector_path = Path(root) / files.pose, Path(root) / files.detector
    pose = load_pose(params, pose_path)
    return pose, load_onboard_chain(pose.model, pose.hash, pose_path, detector_path)


def load_chain(params: Params, model: Model | str, root: Path | str = ".") -> tuple[Any, Any, str]:
    """(OnboardChain, attack loss function on `attack.loss`, pose model hash) of one chain (`load_pose_chain`)."""
    from pipeline.attacks.gradient import attack_loss

    pose, chain = load_pose_chain(params, model, root)
    return chain, attack_loss(params.attack.loss, pose.loss), pose.hash


@dataclass(frozen=True)
class DefenseModel:
    """The calibrated defense (models/defense.json): settings from params.defense with the calibrated
    detector threshold and CUSUM threshold, the measurement-noise model fitted on validation
    trajectories, and the alert limit (params.guidance, params.integrity) its availability is judged by."""

    settings: Any        # pipeline.defense.fusion.DefenseSettings
    motion: Any          # pipeline.defense.gate.MotionSettings
    noise: Any           # pipeline.defense.noise.NoiseModel
    calibration: dict[str, Any]
    alert: Any = None    # pipeline.evaluation.integrity.AlertLimitSettings

    def new(self, fusion: str | None = None) -> Any:
        """A fresh pipeline.defense.fusion.Defense (one per trajectory or closed-loop run), optionally with
        another fusion; its availability is judged against the alert limit."""
        import dataclasses
        from functools import partial

        from pipeline.defense.fusion import Defense
        from pipeline.evaluation.integrity import alert_limit

        s = self.settings if fusion is None else dataclasses.replace(self.settings, fusion=fusion)
        return Defense(s, self.motion, self.noise, None if self.alert is None else partial(alert_limit, settings=self.alert))


def load_defense(p: Params, model_hash: str, threshold: float, model: Model | str) -> DefenseModel:
    """The defense calibrated for one chain (`model`: models/defense.json for the robust one that ships,
    models/defense_standard.json for the standard one) checked against the pose model and detector
    (checkpoint `threshold`) it was calibrated with, and params; the detector threshold, the doubt level
    (`update_below`) and the CUSUM threshold as calibrated."""
    import dataclasses

    from pipeline.formats.defense import read_calibration
    from stages.config.build import alert_limit_settings

    cal = read_calibration(CHAINS[Model(model)].defense, model_hash, threshold)
    settings, motion = defense_settings(p.defense, cal.threshold, cal.settings.get("update_below"))
    return DefenseModel(settings, dataclasses.replace(motion, cusum_threshold=cal.cusum_threshold), cal.noise,
                        cal.raw, alert_limit_settings(p))
