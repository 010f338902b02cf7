"""The calibrated defense file (models/defense.json, written by `rpod calibrate`), read back checked.

Format `DEFENSE_FORMAT` (JSON):
    format: "rpodguard-defense/2"; pose_model_hash: the pose file's `file_hash`; detector_threshold:
    the detector checkpoint's own threshold (chosen on its SHAP split; identifies the detector);
    threshold: the calibrated detector threshold the defended chain uses (on clean validation
    trajectories); noise / fitted_noise: the inflated and the fitted NoiseModel; inflation;
    cusum_threshold: the sequential test's calibrated h; settings: the DefenseSettings and
    MotionSettings fields it was calibrated with (what `defense_from` rebuilds the defense from,
    e.g. for rpodguard.api); alert_limit: the AlertLimitSettings fields of the availability it
    measured; unmet: one line per check that could not meet its share of the false-alarm budget
    (calibrated with defense.allow_unmet; empty otherwise); validation: what it measured there.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pipeline.io.atomic import read_json
from pipeline.io.errors import DataError

DEFENSE_FORMAT = "rpodguard-defense/2"
DEFENSE_REDO = "re-run `rpod calibrate` (`--model standard` for models/defense_standard.json)"


@dataclass(frozen=True)
class Calibration:
    """What models/defense.json holds (see the module docstring); `raw` the whole file."""

    noise: Any                   # pipeline.defense.noise.NoiseModel
    threshold: float
    cusum_threshold: float
    settings: dict[str, Any]
    alert_limit: dict[str, Any]
    unmet: list[str]
    raw: dict[str, Any]


def read_calibration(path: Path | str, model_hash: str, detector_threshold: float) -> Calibration:
    """models/defense.json, refused (DataError naming the file) when foreign, of another format, made
    for another pose model or detector, or holding a bad noise model or threshold."""
    from pipeline.defense.noise import NoiseModel

    path = Path(path)
    cal = read_json(path)
    if not isinstance(cal, dict) or cal.get("format") != DEFENSE_FORMAT:
        raise DataError(f"{path} is not a {DEFENSE_FORMAT} file; {DEFENSE_REDO}")
    if cal.get("pose_model_hash") != model_hash or abs(float(cal.get("detector_threshold", -1)) - detector_threshold) > 1e-9:
        raise DataError(f"{path} was calibrated for another pose model or detector; {DEFENSE_REDO}")
    try:
        noise = NoiseModel(**{k: tuple(v) if isinstance(v, list) else v for k, v in cal["noise"].items()})
        threshold, h = float(cal["threshold"]), float(cal["cusum_threshold"])
        settings, alert, unmet = dict(cal["settings"]), dict(cal["alert_limit"]), list(cal["unmet"])
    except (KeyError, TypeError, ValueError) as e:
        raise DataError(f"{path}: bad calibration ({type(e).__name__}: {e}); {DEFENSE_REDO}") from None
    if not 0 < threshold < 1 or not h > 0:
        raise DataError(f"{path}: threshold {threshold} must be in (0, 1) and cusum_threshold {h} > 0; {DEFENSE_REDO}")
    doubt = settings.get("update_below")
    if doubt is not None and not (isinstance(doubt, (int, float)) and 0 < doubt <= threshold):
        raise DataError(f"{path}: settings.update_below {doubt!r} (the doubt level) must be null or in (0, threshold = "
                        f"{threshold}]; {DEFENSE_REDO}")
    return Calibration(noise, threshold, h, settings, alert, unmet, cal)


def defense_from(cal: Calibration) -> tuple[Any, Any, Any]:
    """(DefenseSettings, MotionSettings, AlertLimitSettings) as `cal` was calibrated: its recorded
    settings with the calibrated detector threshold and CUSUM threshold."""
    from pipeline.defense.fusion import DefenseSettings
    from pipeline.defense.gate import MotionSettings
    from pipeline.defense.integrity import AlertLimitSettings

    def pick(cls: type, values: dict[str, Any], **extra: Any) -> Any:
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{**{k: v for k, v in values.items() if k in names}, **extra})

    try:
        return (pick(DefenseSettings, cal.settings, threshold=cal.threshold),
                pick(MotionSettings, cal.settings, cusum_threshold=cal.cusum_threshold),
                pick(AlertLimitSettings, cal.alert_limit))
    except (TypeError, ValueError) as e:
        raise DataError(f"defense.json: bad settings ({e}); {DEFENSE_REDO}") from None
