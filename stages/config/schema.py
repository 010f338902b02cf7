"""Typed params: `Params`, one dataclass per params.yaml section, built and checked once by
`stages.config.params.load`.

`build(params)` turns the params.yaml mapping into a `Params` (types checked field by field: a whole
number where one is expected, a finite number where a float is, lists of numbers, null only where
allowed; unknown keys refused with a suggestion), runs each section's own checks, then the one rule of
every numeric field: its documented range (`In`, declared beside the field). Errors are `ParamsError`s
naming the key.
A value keeps the type YAML gave it: a whole number where a float is expected stays an int (PEP 484's
numeric tower), so `dataclasses.asdict` of a section is the mapping params.yaml holds, and the
fingerprints and reports that hash or echo it are those of the YAML. The sections live in
stages/config/sections.py (pose pipeline) and stages/config/evaluation.py (evaluation).
"""
from __future__ import annotations

import dataclasses
import difflib
import math
import re
import types
import typing
from dataclasses import dataclass, field
from typing import Annotated, Any, Literal, Optional

from stages.config.ablation import Ablation
from stages.config.evaluation import Defense, Evaluate, Integrity, Lab, Robustness
from stages.config.sections import (Attack, Camera, Detect, Engine, Guidance, In, Label, ParamsError, Render, Seed,
                                    Shap, Train)

DEVICE = re.compile(r"auto|cpu|cuda(:\d+)?")   # values of the `device` param


@dataclass(frozen=True)
class Report:
    pass


@dataclass(frozen=True)
class Params:
    profile_name: str
    seed: Seed
    threads: Optional[Annotated[int, In("[1, 65536]", "threads")]]   # torch CPU threads per torch stage; None = all cores
    device: str                  # auto | cpu | cuda | cuda:N (stages.config.device.torch_device resolves it)
    amp: bool                    # bf16 autocast of the pose network on CUDA; no effect on CPU
    camera: Camera
    render: Render
    engine: Engine
    label: Label
    train: Train
    attack: Attack
    guidance: Guidance
    shap: Shap
    detect: Detect
    evaluate: Evaluate
    defense: Defense
    lab: Lab
    robustness: Robustness
    integrity: Integrity
    ablation: Ablation
    report: Report = field(default_factory=Report)

    def __post_init__(self) -> None:
        if self.threads is not None and self.threads < 1:
            raise ValueError(f"threads must be null or a whole number >= 1, got {self.threads}")
        if not DEVICE.fullmatch(self.device):
            raise ValueError(f"device must be auto, cpu, cuda or cuda:N, got {self.device!r}")
        if self.defense.val_seed == self.evaluate.seed:
            raise ValueError("defense.val_seed must differ from evaluate.seed: the defense is fitted on "
                             "validation trajectories, never on the evaluation ones")
        goal = sum(float(v) ** 2 for v in self.guidance.target) ** 0.5
        if not self.integrity.collision_range_m < goal:
            raise ValueError(f"integrity.collision_range_m must be below the goal range |guidance.target| = {goal:g} m, "
                             f"got {self.integrity.collision_range_m!r}")
        i = self.integrity
        if i.drift_start + i.drift_frames > self.evaluate.frames:
            raise ValueError(f"integrity.drift_start + integrity.drift_frames ({i.drift_start} + {i.drift_frames}) must "
                             f"be at most evaluate.frames = {self.evaluate.frames}: the drift is held inside a trajectory")


def _check(value: Any, hint: Any, key: str) -> Any:
    """`value` converted to the type `hint` (ints accepted for floats), or a ParamsError naming `key`."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin is Annotated:
        rules = [r for r in args[1:] if isinstance(r, In)]
        if rules and isinstance(value, float) and not math.isfinite(value):
            raise rules[0].refusal(key, value, whole=args[0] is int)
        return _check(value, args[0], key)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        return _check(value, next(a for a in args if a is not type(None)), key)
    if origin is list:
        if not isinstance(value, list):
            raise ParamsError(f"params.yaml {key} must be a list, got {value!r}")
        return [_check(v, args[0], f"{key}[{i}]") for i, v in enumerate(value)]
    if origin is Literal:
        if value not in args:
            raise ParamsError(f"params.yaml {key} must be one of {', '.join(map(str, args))}, got {value!r}")
        return value
    if dataclasses.is_dataclass(hint):
        return _build(hint, value, key)
    ok = {int: isinstance(value, int) and not isinstance(value, bool),
          float: isinstance(value, (int, float)) and not isinstance(value, bool),
          bool: isinstance(value, bool), str: isinstance(value, str)}[hint]
    if not ok:
        what = {int: "a whole number", float: "a number", bool: "true or false", str: "a string"}[hint]
        raise ParamsError(f"params.yaml {key} must be {what}, got {value!r}")
    if isinstance(value, float) and not math.isfinite(value):
        raise ParamsError(f"params.yaml {key} must be a finite number, got {value!r}")
    return value   # an int stays an int where a float is expected (see the module's docstring)


def _build(cls: type, section: Any, key: str) -> Any:
    if not isinstance(section, dict):
        if key:   # a section replaced by a value (e.g. `-S train=1`)
            raise ParamsError(f"params.yaml: {key!r} must be a section of parameters, got {section!r}")
        raise ParamsError(f"params.yaml top level must be a mapping, got {section!r}")
    hints = typing.get_type_hints(cls, include_extras=True)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    prefix = f"{key}." if key else ""
    for name in section:
        if name not in fields:
            hint = difflib.get_close_matches(name, list(fields), n=1)
            raise ParamsError(f"params.yaml: unknown parameter {prefix + name!r}"
                              + (f" (did you mean {prefix + hint[0]!r}?)" if hint else ""))
    values = {}
    for name, f in fields.items():
        sub = f"{key}.{name}" if key else name
        if name not in section:
            if f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
                continue
            raise ParamsError(f"params.yaml: missing parameter {sub!r} (run `rpod params <profile>`)")
        values[name] = _check(section[name], hints[name], sub)
    try:
        built = cls(**values)
    except ParamsError:
        raise                        # already names its key in full
    except ValueError as e:
        raise ParamsError(f"params.yaml {key + ': ' if key else ''}{e}") from None
    for name, value in values.items():   # after the section's own checks, so their messages come first
        _check_range(value, hints[name], f"{prefix}{name}")
    return built


def _check_range(value: Any, hint: Any, key: str) -> None:
    """A ParamsError naming `key` when a number (or a list's element) lies outside its field's `In` range."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if value is None or dataclasses.is_dataclass(value):
        return
    if origin in (typing.Union, types.UnionType):
        _check_range(value, next(a for a in args if a is not type(None)), key)
    elif origin is list:
        for i, v in enumerate(value):
            _check_range(v, args[0], f"{key}[{i}]")
    elif origin is Annotated:
        for rule in args[1:]:
            if isinstance(rule, In) and not rule.contains(value):
                raise rule.refusal(key, value, whole=args[0] is int)


def build(params: dict[str, Any]) -> Params:
    """The typed, checked params of a params.yaml mapping."""
    return _build(Params, params, "")


def ranges(cls: type = Params, prefix: str = "") -> dict[str, In]:
    """Dotted params.yaml key -> the `In` range of that numeric param (of each element, for a list), e.g.
    {"render.width": In("[8, 8192]", "pixels"), ...}: what `rpod <stage> --help` shows beside each param."""
    out: dict[str, In] = {}
    for name, hint in typing.get_type_hints(cls, include_extras=True).items():
        if dataclasses.is_dataclass(hint):
            out.update(ranges(hint, f"{prefix}{name}."))
            continue
        while typing.get_origin(hint) in (typing.Union, types.UnionType, list):
            hint = next(a for a in typing.get_args(hint) if a is not type(None))
        rule = next((r for r in typing.get_args(hint)[1:] if isinstance(r, In)), None)
        if typing.get_origin(hint) is Annotated and rule is not None:
            out[f"{prefix}{name}"] = rule
    return out
