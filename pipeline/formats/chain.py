"""The one door to a trained chain: `load_chain(folder, model)` -> pipeline.defense.chain.SafetyChain, used by the
stages (stages/artifacts/models.py adds their params checks), rpodguard's API, the benchmarks and the scripts.

Where the files are (pipeline/formats/run.py names them): with `model` (standard or robust), a run's models/ folder
(`RUN_FILES[model]`); without, the folder rpodguard is given: a run's models/ folder (or a project root holding
it), whose shipped chain it reads (models/pose_robust.pt, detector_robust.pt, defense.json), or a folder holding one
chain (`BUNDLE_FILES`: pose.pt, detector.pt, defense.json), e.g. a weights bundle. A folder holding a bundle manifest
(pipeline/formats/bundle.py) has every file's sha256 checked first.

What is checked: the detector must have been trained on this pose model's SHAP values (its checkpoint names the
pose file's hash), the pose head must be affine (exact SHAP), and the defense file (pipeline/formats/defense.py)
must have been calibrated for this pose model and detector, and be whole and sound. Each is a DataError naming
the file.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

import numpy as np

from pipeline.defense.chain import OnboardChain, SafetyChain
from pipeline.formats.bundle import MANIFEST, check_bundle
from pipeline.formats.defense import read_defense
from pipeline.formats.models import check_role, load_pose, read_detector
from pipeline.formats.run import BUNDLE_FILES, MODELS, MODELS_DIR, RUN_FILES, SHIPPED, ChainNames
from pipeline.io.errors import DataError


def chain_files(folder: Path | str, model: str | None = None) -> tuple[Path, ChainNames, str]:
    """(the folder, the names of the chain's files there, the chain's name) of chain `model` in a run's models/
    `folder`, or without `model` of the chain rpodguard reads from `folder` (see the module docstring)."""
    folder = Path(folder)
    if model is not None:
        if model not in MODELS:
            raise ValueError(f"unknown chain {model!r}; choose one of {', '.join(MODELS)}")
        return folder, RUN_FILES[model], model
    shipped = RUN_FILES[SHIPPED]
    if not any((folder / n).exists() for n in (BUNDLE_FILES.pose, shipped.pose)) and (folder / MODELS_DIR).is_dir():
        folder = folder / MODELS_DIR
    if (folder / shipped.pose).exists():  # a run's models/: the shipped chain's names there
        return folder, shipped, SHIPPED
    return folder, BUNDLE_FILES, SHIPPED


def load_chain(
    folder: Path | str,
    model: str | None = None,
    *,
    device: Any = "cpu",
    amp: bool = False,
    defended: bool | None = True,
    bundle: bool = False,
    check: Callable[[Path, dict[str, Any]], None] | None = None,
) -> SafetyChain:
    """The SafetyChain `model` of `folder` (`chain_files`), its pose network on `device` (`amp`: bf16 autocast on
    CUDA). `defended`: read its defense file (True), not (False: e.g. to calibrate it), or when present (None).
    `bundle` (or a manifest in the folder): check the weights bundle's sha256 first. `check(path, checkpoint)`
    may refuse the pose checkpoint before its network is built (the stages' params checks)."""
    folder, names, name = chain_files(folder, model)
    manifest = check_bundle(folder) if bundle or (folder / MANIFEST).exists() else None
    pose_path, detector_path, defense_path = (folder / n for n in names)

    def checked(path: Path, ckpt: dict[str, Any]) -> None:
        if names != BUNDLE_FILES:  # a run's models/: pose_robust.pt holds the clamped model, pose.pt a standard one
            check_role(ckpt, name == SHIPPED, path)
        if check is not None:
            check(path, ckpt)

    pose = load_pose(pose_path, device, amp, checked)
    detector, ckpt = read_detector(detector_path, model_hash=pose.hash)
    try:
        onboard = OnboardChain.from_model(
            pose.model, np.asarray(ckpt["background_mean"]), detector, threshold=float(ckpt["threshold"])
        )
    except ValueError as err:
        raise DataError(f"{pose_path}: {err}") from None
    read = defended or (defended is None and defense_path.exists())
    calibration = read_defense(defense_path, pose.hash, onboard.threshold) if read else None
    if calibration is not None and model is not None and calibration.model != name:
        raise DataError(
            f"{defense_path} was calibrated for the {calibration.model} chain, not the {name} one; "
            f"re-run `rpod calibrate --model {name}`"
        )
    facts = {**pose.checkpoint, **({} if manifest is None else {"manifest": manifest})}
    return SafetyChain(
        name,
        onboard,
        pose.loss,
        pose.hash,
        facts,
        (pose_path, detector_path, defense_path),
        None if calibration is None else calibration.defended,
        calibration,
    )
