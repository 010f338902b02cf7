"""The params.yaml sections of the evaluation: evaluate, defense, lab and robustness (one frozen dataclass
each; `stages.config.schema.build` fills and checks them). Units and frames are in the field comments.
"""

from __future__ import annotations

import typing
from dataclasses import dataclass
from typing import Annotated, Literal, Optional

from pipeline.defense.gate import MotionSettings
from pipeline.defense.settings import DefenseSettings
from pipeline.settings import In, composed
from stages.config.guards import distinct
from stages.config.sections import (
    Batch,
    Count,
    Direction,
    Eps,
    Focal,
    Metres,
    ParamsError,
    Pixels,
    Principal,
    Probability,
    Scale,
    Seed,
)

Frames = Annotated[int, In("[1, 10000000]", "frames")]
OpenProbability = Annotated[float, In("(0, 1)", "probability")]


@dataclass(frozen=True)
class Evaluate:
    trajectories: Annotated[int, In("[1, 100000]", "trajectories")]
    frames: Frames  # per trajectory
    lateral_range: list[Annotated[float, In("[0, 100000]", "metres")]]  # [low, high] of |x| and |y| at the start
    p_start: Probability  # per-frame probability that an attack starts
    attack_length: Frames  # frames
    eps: list[Eps]
    batch_size: Batch

    def __post_init__(self) -> None:
        if self.trajectories < 1 or self.frames < 2:
            raise ValueError(f"need trajectories >= 1 and frames >= 2, got {self.trajectories} and {self.frames}")
        if len(self.lateral_range) != 2 or not 0 <= self.lateral_range[0] <= self.lateral_range[1]:
            raise ValueError(f"lateral_range must be [low, high] with 0 <= low <= high, got {self.lateral_range}")
        if not 0 <= self.p_start <= 1 or self.attack_length < 1:
            raise ValueError(
                f"p_start must be in [0, 1] and attack_length >= 1, got {self.p_start} and {self.attack_length}"
            )
        distinct(self.eps, "evaluate.eps")
        if not self.eps or not all(0 < e <= 1 for e in self.eps):
            raise ValueError(f"eps must be a non-empty list of values in (0, 1], got {self.eps}")
        if self.batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {self.batch_size}")


@dataclass(frozen=True)
class Shares:
    """Fractions of defense.target_false_alarm per check (they add up to 1)."""

    detector: Annotated[float, In("[0, 1]", "fraction of the budget")]
    gate: Annotated[float, In("[0, 1]", "fraction of the budget")]
    sequential: Annotated[float, In("[0, 1]", "fraction of the budget")]


@composed(DefenseSettings, MotionSettings, runtime=("threshold", "update_below", "cusum_threshold", "correlated_error"))
class Defense:
    """The defense: the chain's settings (pipeline/defense/settings.py `DefenseSettings`) and the motion filter's
    (pipeline/defense/gate.py `MotionSettings`) declare its keys, units, ranges and defaults, less the ones
    `rpod calibrate` sets (the detector's threshold and doubt level, the sequential test's threshold, the
    correlated error); then the calibration's own params. Bad values are refused naming defense.<key>."""

    doubt_share: Optional[OpenProbability]  # of clean validation frames at or above the doubt level (calibrated),
    # from which a frame does not update the filter; None: the detector's threshold
    noise_bins: Annotated[int, In("[2, 1000]", "range bins")]  # of the measurement-noise fit
    target_false_alarm: OpenProbability  # fraction of clean validation frames the defended chain may flag (calibrate)
    shares: Shares  # of target_false_alarm: detector, gate, sequential test
    allow_unmet: bool  # calibrate continues when a check cannot meet its share (reports say so)
    val_trajectories: Annotated[int, In("[1, 100000]", "trajectories")]  # validation approaches the noise is fitted on
    harm_m: Metres  # metres: an attacked frame with a larger position error is harmful

    def __post_init__(self) -> None:
        total = self.shares.detector + self.shares.gate + self.shares.sequential
        if abs(total - 1.0) > 1e-6:
            raise ParamsError(
                f"params.yaml defense.shares must add up to 1 (fractions of target_false_alarm), got {total:g}"
            )


@dataclass(frozen=True)
class Zed:
    width: Pixels
    height: Pixels
    fx: Focal
    fy: Focal
    cx: Principal
    cy: Principal


@dataclass(frozen=True)
class DomainShift:
    noise_std: Annotated[float, In("[0, 1]", "pixel units")]
    blur_sigma: Annotated[float, In("[0, 20]", "pixels")]
    sun_direction: list[Direction]
    sun_strength: Annotated[float, In("(0, 10000]", "W/m^2")]
    calib_error: Annotated[float, In("(-1, 1)", "relative focal-length error")]  # of the lab camera


@dataclass(frozen=True)
class Bodies:
    camera: str
    target: str


@dataclass(frozen=True)
class Lab:
    scale: Annotated[float, In("(0, 10000]", "scale factor")]  # the mock-up is 1/scale of the real target
    zed: Zed
    sequences: list[list[Metres]]  # lab z ranges [start, end], metres
    frames: Annotated[int, In("[2, 10000000]", "frames")]
    fps: Annotated[float, In("(0, 100000]", "Hz")]
    mocap_hz: Annotated[float, In("(0, 100000]", "Hz")]
    match: Literal["nearest", "interpolate"]  # how mocap samples are matched to camera frames
    max_gap_s: Annotated[float, In("(0, 3600]", "seconds")]
    attack_length: Frames
    retrain: Literal["auto", "always"]  # always: train synthetic-lab models (`rpod lab_models`)
    mesh: Optional[str]
    mesh_scale: Scale  # metres per mock-up mesh unit
    train_frames_per_sequence: Optional[Annotated[int, In("[2, 10000000]", "frames")]]
    domain_shift: DomainShift
    real_data: Optional[str]  # folder of a real lab recording
    bodies: Bodies
    segment_threshold: Probability  # grey level in [0, 1]
    max_image_pixels: Annotated[
        int, In("[1, 4294967296]", "pixels")
    ]  # largest lab image (W x H), checked before decoding
    empty_frame_tolerance: Probability  # fraction of frames allowed without target pixels after segmentation, [0, 1]
    seed: Seed

    def __post_init__(self) -> None:
        n = self.train_frames_per_sequence
        if n is not None and n < 2:
            raise ValueError(f"train_frames_per_sequence must be null or a whole number >= 2, got {n!r}")
        if self.mesh_scale <= 0 or self.scale <= 0:
            raise ValueError(f"scale and mesh_scale must be > 0, got {self.scale} and {self.mesh_scale}")
        if self.max_gap_s <= 0 or self.frames < 2 or self.attack_length < 1:
            raise ValueError("need max_gap_s > 0, frames >= 2 and attack_length >= 1")
        for z in self.sequences:
            if len(z) != 2 or min(z) <= 0:
                raise ValueError(f"sequences: each entry must be [z_start, z_end] in metres > 0, got {z}")
        if self.max_image_pixels < 1:
            raise ValueError(f"max_image_pixels must be a whole number >= 1, got {self.max_image_pixels}")
        if not 0 <= self.empty_frame_tolerance <= 1:
            raise ValueError(f"empty_frame_tolerance must be in [0, 1], got {self.empty_frame_tolerance}")


AttackMethod = Literal["fgsm", "pgd", "mifgsm"]  # pipeline.attacks.gradient.ATTACKS (tests/test_robustness.py)
AttackLoss = Literal["full", "position", "rotation"]  # pipeline.attacks.gradient.LOSSES


def attack_name(name: str, key: str) -> tuple[str, Optional[str]]:
    """`method[/loss]` -> (method, loss or None = attack.loss); ValueError naming `key` when unknown."""
    method, _, loss = str(name).partition("/")
    if method not in typing.get_args(AttackMethod) or (loss and loss not in typing.get_args(AttackLoss)):
        raise ValueError(
            f"{key}: unknown attack {name!r}; use method[/loss] with method one of "
            f"{', '.join(typing.get_args(AttackMethod))} and loss one of "
            f"{', '.join(typing.get_args(AttackLoss))}"
        )
    return method, loss or None


@dataclass(frozen=True)
class Corruptions:
    """Benign corruption strengths (pipeline/attacks/corruptions.py applies them; it checks the same ranges)."""

    noise: list[Annotated[float, In("[0, 1]", "Gaussian noise std, pixel units")]]
    blur: list[Annotated[float, In("(0, 20]", "Gaussian blur sigma, pixels")]]
    jpeg: list[Annotated[int, In("[1, 100]", "JPEG quality")]]
    brightness: list[Annotated[float, In("(0, 10]", "exposure gain")]]
    contrast: list[Annotated[float, In("[0, 10]", "factor around the frame's mean grey level")]]

    def __post_init__(self) -> None:
        ok = {
            "noise": lambda s: 0 <= s <= 1,
            "blur": lambda s: 0 < s <= 20,
            "jpeg": lambda s: 1 <= s <= 100,
            "brightness": lambda s: 0 < s <= 10,
            "contrast": lambda s: 0 <= s <= 10,
        }
        for name, inside in ok.items():
            bad = [s for s in getattr(self, name) if not inside(s)]
            if bad:
                raise ValueError(f"{name}: strength {bad[0]!r} is out of range")


@dataclass(frozen=True)
class Robustness:
    frames: Count  # held-out test frames (seeded sample) of the per-frame rows
    harm_m: Metres  # metres: an attacked frame is harmful when its position error exceeds this
    eps: list[Eps]  # L-inf budgets, pixels in [0, 1], of the transfer, adaptive and surrogate rows
    unseen_eps: list[Eps]  # FGSM budgets the detector was not trained on
    transfer: list[str]  # method[/loss]; loss defaults to attack.loss
    steps: Annotated[int, In("[20, 100000]", "steps")]  # PGD steps, plain, adaptive and on the surrogate
    lambdas: list[
        Annotated[float, In("[0, 1000000000]", "weight")]
    ]  # adaptive attack: pose_loss - lambda * detector logit
    surrogate_attacks: list[str]  # method[/loss], crafted on models/surrogate.pt
    surrogate_seed: Seed
    surrogate_epochs: Annotated[int, In("[1, 1000000]", "epochs")]
    batch_size: Batch
    burst_every: Frames  # fused-chain rows: a burst of evaluate.attack_length frames every this many frames
    corruptions: Corruptions

    def __post_init__(self) -> None:
        for key in ("eps", "unseen_eps"):
            values = getattr(self, key)
            if not values:
                raise ValueError(f"{key} must be a non-empty list of values in (0, 1]")
            for e in values:
                if not 0 < e <= 1:
                    raise ValueError(f"{key}: {e!r} is not in (0, 1] (pixels are in [0, 1])")
            distinct(values, f"robustness.{key}")
        if not self.lambdas or not all(0 <= v < float("inf") for v in self.lambdas):
            raise ValueError(f"lambdas must be a non-empty list of finite values >= 0, got {self.lambdas}")
        for key in ("transfer", "surrogate_attacks"):
            for name in getattr(self, key):
                attack_name(name, key)
        if self.steps < 20:
            raise ValueError(
                f"steps must be >= 20 (an adaptive attack with fewer steps understates the attacker), got {self.steps}"
            )
        if not self.harm_m > 0:
            raise ValueError(f"harm_m must be a positive distance in metres, got {self.harm_m}")
        if min(self.frames, self.batch_size, self.surrogate_epochs, self.burst_every) < 1:
            raise ValueError(
                f"frames, batch_size, surrogate_epochs and burst_every must be >= 1, got {self.frames}, "
                f"{self.batch_size}, {self.surrogate_epochs} and {self.burst_every}"
            )


IntegrityAttacker = Literal[
    "burst", "drift/los", "drift/lateral", "capture/los", "capture/lateral"
]  # pipeline.attackers.suite.ATTACKERS[/direction]
InLoopGoal = Literal["collide", "miss", "capture"]  # pipeline.attackers.in_loop.GOALS
Steps = Annotated[int, In("[1, 100000]", "PGD steps")]


@dataclass(frozen=True)
class Integrity:
    """Integrity metrics and the chain-level attackers (pipeline/defense/integrity.py, pipeline/attackers/,
    pipeline/evaluation/measures.py; the alert limit's other constants are guidance's)."""

    collision_range_m: Metres  # metres: a true range below this is a collision, > 0
    alert_limit_m: Optional[Metres]  # metres: a fixed AL instead of AL(range) from the guidance law; None: derived
    alert_limit_kind: Literal["single_frame", "persistent"]  # pipeline.defense.integrity.KINDS: the AL judged against
    eps: list[Eps]  # L-inf budgets of the integrity attacks, pixels in [0, 1], increasing: the breaking point's grid
    attackers: list[IntegrityAttacker]  # run on every chain: the shipped one, the standard one, the undefended control
    trajectories: Optional[Annotated[int, In("[1, 100000]", "trajectories")]]  # rpod robustness: the first N
    # eval_render trajectories the shipped chain flies; None: all
    comparison_trajectories: Optional[Annotated[int, In("[1, 100000]", "trajectories")]]  # the first N the standard
    # chain and the undefended control fly; None: all
    stop_at_break: bool  # a chain's eps ladder stops after the eps where it breaks (its breaking point)
    capture_initial: list[Metres]  # metres: capture biases held from acquisition, one capture per value and direction
    capture_rate: Annotated[float, In("[0, 1000]", "metres per frame")]  # growth of the capture bias; 0: held
    burst_length: Frames  # frames per burst (one every robustness.burst_every frames of each trajectory)
    burst_steps: Steps  # PGD steps per restart and lambda
    burst_restarts: Annotated[int, In("[1, 1000]", "random starts")]
    burst_lambdas: list[Annotated[float, In("[0, 1000000000]", "weight")]]  # searched in increasing order
    burst_cap: Annotated[float, In("(0, 1000]", "units of AL")]  # the objective's ceiling
    burst_objective: Literal["error", "error_al", "error_pl"]  # pipeline.attackers.burst.OBJECTIVES
    burst_hinge: Optional[Annotated[float, In("[0, 1000]", "margin units")]]  # stop paying for stealth this far
    # under each threshold; None: softplus margins
    drift_start: Literal["acquisition", "after_trusted", "both"]  # pipeline.attackers.drift.STARTS: first drifted
    # frame; both: one drift from each (the full grid's)
    undefended_drift_rate: Annotated[float, In("(0, 1000]", "metres per frame")]  # the drift's growth against the
    # undefended control, which no check bounds
    frame_steps: Steps  # targeted PGD steps per attacked frame of the drift and the capture
    drift_gate_fraction: Annotated[float, In("(0, 1]", "fraction of the gate")]
    in_loop_goals: list[InLoopGoal]
    in_loop_eps: list[Eps]  # L-inf budgets of the in-loop attacker (rpod guidance)
    in_loop_start_ranges: list[Metres]  # metres: collide / miss attack every frame from the first step at range <= S
    in_loop_steps: Steps  # targeted PGD steps per attacked closed-loop frame

    def __post_init__(self) -> None:
        if not self.collision_range_m > 0:
            raise ParamsError(
                f"params.yaml integrity.collision_range_m must be > 0 (metres), got {self.collision_range_m!r}"
            )
        if self.alert_limit_m is not None and not self.alert_limit_m > 0:
            raise ParamsError(
                f"params.yaml integrity.alert_limit_m must be null or > 0 (metres), got {self.alert_limit_m!r}"
            )
        for key in (
            "eps",
            "attackers",
            "burst_lambdas",
            "capture_initial",
            "in_loop_goals",
            "in_loop_eps",
            "in_loop_start_ranges",
        ):
            values = getattr(self, key)
            if not values or len(set(values)) != len(values):
                raise ParamsError(
                    f"params.yaml integrity.{key} must be a non-empty list without repeats, got {values!r}"
                )
        for key in ("eps", "in_loop_eps"):
            bad = [e for e in getattr(self, key) if not 0 < e <= 1]
            if bad:
                raise ParamsError(f"params.yaml integrity.{key}: {bad[0]!r} is not in (0, 1] (pixels are in [0, 1])")
        if list(self.eps) != sorted(self.eps):
            raise ParamsError(
                f"params.yaml integrity.eps must be increasing (the breaking point's grid), got {self.eps!r}"
            )
