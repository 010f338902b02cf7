"""The calibrated defense file (models/defense.json, written by `rpod calibrate`): `DefenseFile`, its schema.

The file is the only source of the defended settings after calibration: the stages, rpodguard's API and
the scripts fly what it records (params -> `rpod calibrate` -> defense.json -> everyone), and a stage refuses
a file whose recorded settings differ from the params it runs with (`check_settings`).

Format `DEFENSE_FORMAT` (JSON), every key required but `tightened`:
    format: "rpodguard-defense/2"; model: the chain's pose model (standard or robust); pose_model_hash: the
    pose file's `file_hash`; detector_threshold: the detector checkpoint's own threshold (chosen on its SHAP
    split; identifies the detector); threshold: the calibrated detector threshold the defended chain flies (on
    clean validation trajectories); cusum_threshold: the sequential test's calibrated h; inflation,
    attitude_inflation: the gate's calibrated widening of the fitted noise; noise / fitted_noise: the inflated
    and the fitted NoiseModel; settings: the DefenseSettings and MotionSettings fields the chain flies (with
    the calibrated threshold, doubt level `update_below` and h); alert_limit: the AlertLimitSettings of its
    availability; unmet: one line per check that could not meet its share of the false-alarm budget
    (calibrated with defense.allow_unmet; empty otherwise); validation: what it measured on the validation
    frames (`Validation`); tightened: how the shares were tightened when the fused chain first overshot.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Literal, Optional

from pipeline.defense.chain import Defended
from pipeline.defense.gate import MotionSettings
from pipeline.defense.integrity import AlertLimitSettings
from pipeline.defense.noise import NoiseModel, inflate
from pipeline.defense.settings import DefenseSettings
from pipeline.formats.run import MODELS
from pipeline.io.atomic import read_json
from pipeline.io.errors import DataError
from pipeline.settings import OPTIONAL, In, Source, typed

DEFENSE_FORMAT = "rpodguard-defense/2"
DEFENSE_REDO = "re-run `rpod calibrate` (`--model standard` for models/defense_standard.json)"
Probability = Annotated[float, In("(0, 1)", "probability")]
Inflation = Annotated[float, In("(0, 1000]", "times the fitted standard deviation")]
# the range of the alert limit's lengths (tolerance, max_step, collision_range, fixed), as params.yaml's metres
AL_RANGE = In("(0, 100000]", "metres")


@dataclass(frozen=True)
class Validation:
    """What calibrate measured on the clean validation frames: the validation set (`trajectories`, `seed`),
    the false-alarm target (`target_pct`, %) and the doubt level's share (`doubt`), which are params of the
    calibration; the rest (each check's rates, the fused chain's false alarms, availability, MI, PL and error
    summaries, the envelope frames' detector alarms) is a record for the reports."""

    trajectories: Annotated[int, In("[1, 100000]", "trajectories")]
    seed: Annotated[int, In("[0, 2147483647]", "random seed")]
    frames: Annotated[int, In("[1, 1000000000]", "frames")]
    target_pct: Annotated[float, In("(0, 100)", "%")]
    doubt: dict[str, Any]
    envelope: dict[str, Any]
    checks: dict[str, Any]
    false_alarms: dict[str, Any]
    availability: dict[str, Any]
    mi: dict[str, Any]
    pl_m: Any
    error_m: Any


@dataclass(frozen=True)
class DefenseFile:
    """models/defense.json, typed (see the module docstring; `settings` and `motion` are the file's one
    `settings` record split between DefenseSettings and MotionSettings). Besides each field's own checks:
    the flown threshold and h are the recorded ones, the noise model is the fitted one times the recorded
    inflations, its floor lies below its largest standard deviation, and the alert limit's lengths are in AL_RANGE."""

    format: Literal[DEFENSE_FORMAT]
    model: Literal[MODELS]
    pose_model_hash: str
    detector_threshold: Probability
    threshold: Probability
    cusum_threshold: Annotated[float, In("(0, 1000000]", "standard deviations")]
    inflation: Inflation
    attitude_inflation: Inflation
    noise: NoiseModel
    fitted_noise: NoiseModel
    settings: DefenseSettings
    motion: MotionSettings
    alert_limit: AlertLimitSettings
    unmet: tuple[str, ...]
    validation: Validation
    tightened: Optional[dict[str, Any]] = field(default=None, metadata=OPTIONAL)

    def __post_init__(self) -> None:
        if self.settings.threshold != self.threshold or self.motion.cusum_threshold != self.cusum_threshold:
            raise ValueError(
                f"settings.threshold {self.settings.threshold!r} and settings.cusum_threshold "
                f"{self.motion.cusum_threshold!r} must be the calibrated threshold {self.threshold!r} "
                f"and cusum_threshold {self.cusum_threshold!r}"
            )
        if self.noise != inflate(self.fitted_noise, self.inflation, self.attitude_inflation):
            raise ValueError(
                f"noise is not fitted_noise inflated by {self.inflation!r} (attitude {self.attitude_inflation!r})"
            )
        for name in ("tolerance", "max_step", "collision_range", "fixed"):
            value = getattr(self.alert_limit, name)
            if value is not None and not AL_RANGE.contains(value):
                raise ValueError(f"alert_limit.{name} must be {AL_RANGE.rule(False)}, got {value!r}")
        for name in ("noise", "fitted_noise"):
            noise = getattr(self, name)
            if noise.knot_std and noise.floor > max(max(row) for row in noise.knot_std):
                raise ValueError(
                    f"{name}.floor {noise.floor!r} must lie below its largest standard deviation (knot_std)"
                )

    @property
    def defended(self) -> Defended:
        """The calibrated defense this file records."""
        return Defended(self.settings, self.motion, self.noise, self.alert_limit)

    def to_json(self) -> dict[str, Any]:
        """The file's JSON record (what `read_defense` reads back into an equal DefenseFile)."""
        out = {
            "format": self.format,
            "model": self.model,
            "pose_model_hash": self.pose_model_hash,
            "detector_threshold": self.detector_threshold,
            "threshold": self.threshold,
            "cusum_threshold": self.cusum_threshold,
            "inflation": self.inflation,
            "attitude_inflation": self.attitude_inflation,
            "noise": self.noise.as_dict(),
            "fitted_noise": self.fitted_noise.as_dict(),
            "settings": {**dataclasses.asdict(self.settings), **dataclasses.asdict(self.motion)},
            "alert_limit": dataclasses.asdict(self.alert_limit),
            "unmet": list(self.unmet),
            "validation": dataclasses.asdict(self.validation),
        }
        return out if self.tightened is None else {**out, "tightened": self.tightened}


def parse_defense(record: Any, where: str) -> DefenseFile:
    """The DefenseFile of a JSON record (`where`: the file, for messages): every key required (but `tightened`),
    no unknown key, each value of its type, finite and in its range; else one DataError line naming the key."""
    source = Source(where, DataError, "key", DEFENSE_REDO)
    if not isinstance(record, dict) or record.get("format") != DEFENSE_FORMAT:
        raise DataError(f"{where} is not a {DEFENSE_FORMAT} file; {DEFENSE_REDO}")
    if "motion" in record:
        raise DataError(f"{where}: unknown key 'motion'; {DEFENSE_REDO}")
    flown = record.get("settings")
    if not isinstance(flown, dict):
        raise DataError(f"{where} settings must be a mapping, got {flown!r}; {DEFENSE_REDO}")
    names = {cls: {f.name for f in dataclasses.fields(cls)} for cls in (DefenseSettings, MotionSettings)}
    unknown = sorted(set(flown) - names[DefenseSettings] - names[MotionSettings])
    if unknown:
        raise DataError(f"{where}: unknown key {'settings.' + str(unknown[0])!r}; {DEFENSE_REDO}")
    split = {
        "settings": typed(
            DefenseSettings, {k: v for k, v in flown.items() if k in names[DefenseSettings]}, source, "settings"
        ),
        "motion": typed(
            MotionSettings, {k: v for k, v in flown.items() if k in names[MotionSettings]}, source, "settings"
        ),
    }
    return typed(DefenseFile, {**record, **split}, source)


def read_defense(path: Path | str, model_hash: str, detector_threshold: float) -> DefenseFile:
    """models/defense.json (`parse_defense`), refused (DataError naming the file) when made for another pose
    model (its file hash `model_hash`) or detector (its checkpoint threshold `detector_threshold`)."""
    path = Path(path)
    cal = parse_defense(read_json(path), str(path))
    if cal.pose_model_hash != model_hash or abs(cal.detector_threshold - detector_threshold) > 1e-9:
        raise DataError(f"{path} was calibrated for another pose model or detector; {DEFENSE_REDO}")
    return cal


def check_settings(
    cal: DefenseFile, where: str, wanted: Defended, doubt: float | None, source: str, keys: dict[str, str]
) -> None:
    """Refuse (one DataError naming both values) a defense file whose recorded settings differ from those a run
    asks for: `wanted`'s settings, motion settings and alert limit (as `source`, e.g. params.yaml, gives them),
    their calibrated fields (the thresholds, h, the doubt level) aside, and a doubt level recorded exactly when
    the run asks for one (`doubt`: its share of the clean frames, None: none). `keys`: setting name (or "doubt")
    -> the key of `source` that gives it, for the message."""
    calibrated = {"threshold", "update_below", "cusum_threshold", "correlated_error"}
    pairs = [
        (f"{part}.{f.name}", getattr(have, f.name), getattr(want, f.name), f.name)
        for part, have, want in (
            ("settings", cal.settings, wanted.settings),
            ("settings", cal.motion, wanted.motion),
            ("alert_limit", cal.alert_limit, wanted.alert),
        )
        for f in dataclasses.fields(want)
        if f.name not in calibrated
    ]
    if (cal.settings.update_below is None) != (doubt is None):
        pairs.append(("settings.update_below", cal.settings.update_below, doubt, "doubt"))
    for key, recorded, asked, name in pairs:
        if recorded != asked:
            raise DataError(
                f"{where} records {key} = {recorded!r} but {source} gives {keys.get(name, name)} = "
                f"{asked!r}: calibrated under other settings; {DEFENSE_REDO}"
            )
