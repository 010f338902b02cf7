"""Typed params: `Params`, one dataclass per params.yaml section, built and checked once by
`stages.config.params.load`.

`build(params)` turns the params.yaml mapping into a `Params` (pipeline.settings.typed: types checked field
by field: a whole number where one is expected, a finite number where a float is, lists of numbers, null only
where allowed; unknown keys refused with a suggestion), runs each section's own checks, then the one rule of
every numeric field: its documented range (`In`, declared beside the field). Errors are `ParamsError`s
naming the key.
A value keeps the type YAML gave it: a whole number where a float is expected stays an int (PEP 484's
numeric tower), so `dataclasses.asdict` of a section is the mapping params.yaml holds, and the
fingerprints and reports that hash or echo it are those of the YAML. The sections live in
stages/config/sections.py (pose pipeline) and stages/config/evaluation.py (evaluation).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Annotated, Any, Optional

from pipeline.settings import In, Source, typed
from pipeline.settings import ranges as settings_ranges
from stages.config.ablation import Ablation
from stages.config.bound import Bound
from stages.config.evaluation import Defense, Evaluate, Integrity, Lab, Robustness
from stages.config.sections import (
    Attack,
    Camera,
    Detect,
    Engine,
    Guidance,
    Label,
    ParamsError,
    Render,
    Seed,
    Shap,
    Train,
)
from stages.config.suite import Suite

DEVICE = re.compile(r"auto|cpu|cuda(:\d+)?")  # values of the `device` param


@dataclass(frozen=True)
class Report:
    pass


@dataclass(frozen=True)
class Params:
    profile_name: str
    seed: Seed
    threads: Optional[
        Annotated[int, In("[1, 65536]", "threads")]
    ]  # torch CPU threads per torch stage; None = all cores
    device: str  # auto | cpu | cuda | cuda:N (stages.config.device.torch_device resolves it)
    amp: bool  # bf16 autocast of the pose network on CUDA; no effect on CPU
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
    bound: Bound
    ablation: Ablation
    suite: Suite
    report: Report = field(default_factory=Report)

    def __post_init__(self) -> None:
        if self.threads is not None and self.threads < 1:
            raise ValueError(f"threads must be null or a whole number >= 1, got {self.threads}")
        if not DEVICE.fullmatch(self.device):
            raise ValueError(f"device must be auto, cpu, cuda or cuda:N, got {self.device!r}")
        goal = sum(float(v) ** 2 for v in self.guidance.target) ** 0.5
        if not self.integrity.collision_range_m < goal:
            raise ValueError(
                f"integrity.collision_range_m must be below the goal range |guidance.target| = {goal:g} m, "
                f"got {self.integrity.collision_range_m!r}"
            )


PARAMS_SOURCE = Source("params.yaml", ParamsError, "parameter", "run `rpod params <profile>`", required=False)


def build(params: dict[str, Any]) -> Params:
    """The typed, checked params of a params.yaml mapping."""
    return typed(Params, params, PARAMS_SOURCE)


def ranges() -> dict[str, In]:
    """Dotted params.yaml key -> the `In` range of that numeric param (of each element, for a list), e.g.
    {"render.width": In("[8, 8192]", "pixels"), ...}: what `rpod <stage> --help` shows beside each param."""
    return settings_ranges(Params)
