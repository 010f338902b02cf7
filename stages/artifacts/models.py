"""The models the stages load, through the one door to a chain (pipeline/formats/chain.py `load_chain`) and its
pose loader (pipeline/formats/models.py `load_pose`), checked against params.yaml: a chain by the model it is
built on (stages.artifacts.paths.CHAINS: `standard`, the paper's reproduction; `robust`, the chain that ships)
with its calibrated defense, whose recorded settings must be the params' (pipeline.formats.defense.check_settings),
or a pose model alone; each pose checkpoint with the architecture, input size and label table params.yaml asks for.
"""

from __future__ import annotations

import dataclasses
from functools import partial
from pathlib import Path
from typing import Any

from pipeline.formats.models import check_role
from pipeline.io.atomic import file_hash
from stages.artifacts.paths import LABELS, MODELS, POSE, POSE_ROBUST, Model
from stages.config.build import ALERT_LIMIT_KEYS, alert_limit_settings, defense_settings
from stages.config.schema import Params
from stages.errors import StageError


def model_option(outputs: str) -> Any:
    """The `--model` option of the commands that run once per pose model (shap, detect, calibrate); `outputs`:
    what each model's run writes."""
    import typer

    return typer.Option(
        "--model",
        help="The pose model: standard (models/pose.pt, `rpod train`, the paper's "
        f"reproduction) or robust (models/pose_robust.pt, the one that ships). {outputs}",
    )


def expected(params: Params, clamped: bool = False) -> dict[str, Any]:
    """The architecture and input size that params.yaml asks for (`clamped`: of the robust model, whose
    black-level clamp is train.adversarial.black_level)."""
    arch = {"width": float(params.train.width), "dropout": float(params.train.dropout)}
    if clamped:
        arch["black_level"] = float(params.train.adversarial.black_level)
    return {"arch": arch, "input_size": [params.render.height, params.render.width]}


def check_pose(params: Params, path: Path, ckpt: dict[str, Any]) -> None:
    """Refuse a pose checkpoint whose architecture or input size is not the one params.yaml asks for (a clamped
    checkpoint, models/pose_robust.pt, is checked against train.adversarial.black_level too), or that was trained on
    another datasets/labels.parquet than the one there (its recorded hash); models/pose_robust.pt must hold the
    robust (clamped) model and any other pose file a standard one (`check_role`)."""
    check_role(ckpt, Path(path).name == POSE_ROBUST.name, path)
    want = expected(params, "black_level" in ckpt["arch"])
    have = {"arch": ckpt["arch"], "input_size": list(ckpt["input_size"])}
    diffs = [f"{k}={have['arch'].get(k)} (params: {v})" for k, v in want["arch"].items() if have["arch"].get(k) != v]
    if have["input_size"] != want["input_size"]:
        diffs.append(f"input_size HxW={have['input_size']} (params: {want['input_size']})")
    if diffs:
        raise StageError(
            f"pose checkpoint {path} does not match params.yaml: {', '.join(diffs)}; "
            f"re-run `rpod train` or restore the params it was trained with"
        )
    if "labels_hash" in ckpt and LABELS.exists() and file_hash(LABELS) != ckpt["labels_hash"]:
        raise StageError(
            f"pose checkpoint {path} was trained on another {LABELS} (relabelled since); re-run `rpod train`"
        )


def load_pose(params: Params, path: Path | str = POSE) -> Any:
    """models/pose.pt (or another pose checkpoint, e.g. POSE_ROBUST) as a pipeline.formats.models.Pose, checked
    against params (`check_pose`), the network on the `device` param's device (with `amp`); it takes inputs from
    any device and answers on theirs."""
    from pipeline.formats.models import load_pose as read
    from stages.config.device import torch_device

    return read(path, torch_device(params), params.amp, partial(check_pose, params))


def load_trial_pose(trial: Params, folder: Path, device: Any) -> Any:
    """A pose trial's network (`rpod pose_trial`: folder/models/pose.pt; `trial`: its params.yaml), refused unless it
    was trained on its folder's labels at its params' input size."""
    from pipeline.formats.models import load_pose as read

    def check(path: Path, ckpt: dict[str, Any]) -> None:
        if ckpt.get("labels_hash") != file_hash(folder / LABELS):
            raise StageError(f"{path} was not trained on {folder / LABELS}: re-run its pose trial")
        if list(ckpt["input_size"]) != [trial.render.height, trial.render.width]:
            raise StageError(
                f"{path} takes {ckpt['input_size']} (HxW), its params.yaml renders "
                f"{trial.render.height}x{trial.render.width}: re-run its pose trial"
            )

    return read(folder / POSE, device, trial.amp, check).model


def load_chain(params: Params, model: Model | str, root: Path | str = ".", defended: bool = True) -> Any:
    """The pipeline.defense.chain.SafetyChain of one chain (`model`: standard or robust) in ROOT/models/ (the
    working folder, or e.g. datasets/lab_models): its pose model checked against params (`check_pose`) on the
    `device` param's device, its detector and, with `defended`, its calibrated defense, whose recorded settings
    must be those params.yaml gives (else a DataError naming both values)."""
    from pipeline.defense.chain import Defended
    from pipeline.formats.chain import load_chain as open_chain
    from pipeline.formats.defense import check_settings
    from stages.config.device import torch_device

    chain = open_chain(
        Path(root) / MODELS,
        Model(model).value,
        device=torch_device(params),
        amp=params.amp,
        defended=defended,
        check=partial(check_pose, params),
    )
    if defended:
        settings, motion = defense_settings(params.defense, chain.defended.settings.threshold)
        wanted = Defended(settings, motion, chain.defended.noise, alert_limit_settings(params))
        keys = {
            **{f.name: f"defense.{f.name}" for s in (settings, motion) for f in dataclasses.fields(s)},
            **ALERT_LIMIT_KEYS,
            "doubt": "defense.doubt_share",
        }
        check_settings(chain.calibration, str(chain.files[2]), wanted, params.defense.doubt_share, "params.yaml", keys)
    return chain
