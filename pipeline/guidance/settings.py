"""How the thrusters and the orbit execute a commanded step (pipeline/guidance/dynamics.py): the settings of the
execution errors and of the relative orbit. Declared apart from the dynamics so the params schema (stages/config)
composes them without taking the guidance package's code."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Literal

import numpy as np

from pipeline.settings import In

APPROACHES = ("vbar", "rbar")


@dataclass(frozen=True)
class ExecutionSettings:
    """How a commanded step is executed (see the module docstring): scale_std (fraction, 1-sigma per
    thruster axis and step), noise_std (m, 1-sigma per axis and step), mean_motion (rad/s; 0: no
    orbital motion), frame_interval (s per step), approach ("vbar" or "rbar": how the world axes sit in
    the target's orbit frame) and seed (of the errors' draws)."""

    scale_std: Annotated[float, In("[0, 1]", "fraction of the step")] = 0.02  # 1-sigma per thruster axis and step
    noise_std: Annotated[float, In("[0, 100]", "metres per step")] = 0.01  # 1-sigma per axis, the step-free part
    mean_motion: Annotated[float, In("[0, 0.1]", "rad/s")] = 0.0011  # the target's orbit (Clohessy-Wiltshire); 0: none
    frame_interval: Annotated[float, In("(0, 100000]", "seconds per step")] = 10.0  # per closed-loop step
    approach: Literal[APPROACHES] = "vbar"  # how the world axes sit in the target's orbit frame
    seed: int = 0  # of the errors' draws (pipeline/seeds.py; not a param)

    def __post_init__(self) -> None:
        for name in ("scale_std", "noise_std", "mean_motion"):
            v = float(getattr(self, name))
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"execution {name} must be a finite number >= 0, got {getattr(self, name)!r}")
        if not (math.isfinite(self.frame_interval) and self.frame_interval > 0):
            raise ValueError(f"execution frame_interval (s) must be a finite number > 0, got {self.frame_interval!r}")
        if self.approach not in APPROACHES:
            raise ValueError(f"unknown execution approach {self.approach!r}; choose one of {', '.join(APPROACHES)}")

    def step_std(self, step: float) -> float:
        """The execution error's std per axis (m) of a commanded step of `step` m along that axis (CW aside)."""
        return math.hypot(self.scale_std * float(step), self.noise_std)

    def draws(self) -> np.random.Generator:
        """The generator of the errors' draws (six standard normals per step: `Executor.step`)."""
        return np.random.default_rng(self.seed)
