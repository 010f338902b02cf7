"""The params.yaml sections of the evaluation: evaluate, defense, lab and robustness (one frozen dataclass
each; `stages.config.schema.build` fills and checks them). Units and frames are in the field comments.
"""
from __future__ import annotations

import typing
from dataclasses import dataclass
from typing import Literal, Optional

from stages.config.sections import ParamsError


@dataclass(frozen=True)
class Evaluate:
    trajectories: int
    frames: int                  # per trajectory
    lateral_range: list[float]   # metres, [low, high] of |x| and |y| at the start
    p_start: float               # per-frame probability that an attack starts
    attack_length: int           # frames
    eps: list[float]
    seed: int
    batch_size: int

    def __post_init__(self) -> None:
        if self.trajectories < 1 or self.frames < 2:
            raise ValueError(f"need trajectories >= 1 and frames >= 2, got {self.trajectories} and {self.frames}")
        if len(self.lateral_range) != 2 or not 0 <= self.lateral_range[0] <= self.lateral_range[1]:
            raise ValueError(f"lateral_range must be [low, high] with 0 <= low <= high, got {self.lateral_range}")
        if not 0 <= self.p_start <= 1 or self.attack_length < 1:
            raise ValueError(f"p_start must be in [0, 1] and attack_length >= 1, got {self.p_start} and "
                             f"{self.attack_length}")
        if not self.eps or not all(0 < e <= 1 for e in self.eps):
            raise ValueError(f"eps must be a non-empty list of values in (0, 1], got {self.eps}")
        if self.batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {self.batch_size}")


@dataclass(frozen=True)
class Defense:
    """The defense (pipeline/defense/kalman.py and pipeline/defense/fusion.py); bad values are refused naming defense.<key>."""

    fusion: Literal["or", "paper", "motion"]   # or: detector or motion gate | paper: detector alone | motion: gate alone
    false_alarm: float           # gate false-alarm probability per frame on consistent motion, in (0, 1)
    position_noise: float        # metres per frame: std of the unmodelled displacement, > 0
    velocity_noise: float        # metres per frame per frame: std of the drift-velocity change, > 0
    attitude_noise_deg: float    # degrees per frame: std of the unmodelled target rotation, > 0
    attitude_rate_noise_deg: float   # degrees per frame per frame: std of the target rate change, > 0
    soft_gate: float             # fraction of the gate's NIS above which accepted frames are down-weighted, (0, 1]
    reacquire_after: int         # frames (M >= 2): agreeing rejected frames that restart the filter
    hold_after: int              # frames (K >= 1): consecutive flags that declare the estimate lost -> hold
    release_after: int           # frames (>= 1): consecutive clean frames that end a hold
    update_below: Optional[float]    # detector probability in (0, 1) from which a frame does not update the
                                     # filter; None: the detector's threshold
    noise_bins: int              # range bins of the measurement-noise fit (>= 2)
    target_false_alarm: float    # fraction of clean validation frames the defended chain may flag; calibrate inflates the noise to it, in (0, 1)
    val_trajectories: int        # validation approaches (own seed) the noise model is fitted on (>= 1)
    val_seed: int                # their seed: never evaluate.seed
    harm_m: float                # metres: an attacked frame with a larger position error is harmful

    def __post_init__(self) -> None:
        def bad(key: str, rule: str) -> ParamsError:
            return ParamsError(f"params.yaml defense.{key} must be {rule}, got {getattr(self, key)!r}")

        for key in ("position_noise", "velocity_noise", "attitude_noise_deg", "attitude_rate_noise_deg"):
            if not getattr(self, key) > 0:
                raise bad(key, "> 0 (a noise std)")
        if not 0 < self.false_alarm < 1:
            raise bad("false_alarm", "a gate probability in (0, 1)")
        if not 0 < self.target_false_alarm < 1:
            raise bad("target_false_alarm", "a fraction in (0, 1)")
        if not 0 < self.soft_gate <= 1:
            raise bad("soft_gate", "in (0, 1]")
        if self.update_below is not None and not 0 < self.update_below < 1:
            raise bad("update_below", "null or a probability in (0, 1)")
        for key, low in (("hold_after", 1), ("release_after", 1), ("reacquire_after", 2), ("noise_bins", 2),
                         ("val_trajectories", 1)):
            if getattr(self, key) < low:
                raise bad(key, f"a whole number >= {low}")
        if not self.harm_m > 0:
            raise bad("harm_m", "> 0 (metres)")


@dataclass(frozen=True)
class Zed:
    width: int                   # pixels
    height: int
    fx: float                    # pixels
    fy: float
    cx: float
    cy: float


@dataclass(frozen=True)
class DomainShift:
    noise_std: float             # [0, 1] pixel units
    blur_sigma: float            # pixels
    sun_direction: list[float]
    sun_strength: float
    calib_error: float           # relative focal-length error of the lab camera


@dataclass(frozen=True)
class Bodies:
    camera: str
    target: str


@dataclass(frozen=True)
class Lab:
    scale: float                 # the mock-up is 1/scale of the real target
    zed: Zed
    sequences: list[list[float]]  # lab z ranges [start, end], metres
    frames: int
    fps: float
    mocap_hz: float
    match: Literal["nearest", "interpolate"]   # how mocap samples are matched to camera frames
    max_gap_s: float             # seconds
    attack_length: int           # frames
    retrain: Literal["auto", "always"]   # always: train synthetic-lab models (`rpod lab_models`)
    mesh: Optional[str]
    mesh_scale: float            # metres per mock-up mesh unit
    train_frames_per_sequence: Optional[int]
    domain_shift: DomainShift
    real_data: Optional[str]     # folder of a real lab recording
    bodies: Bodies
    segment_threshold: float     # grey level in [0, 1]
    max_image_pixels: int        # largest lab image accepted (width x height, pixels), checked before decoding
    empty_frame_tolerance: float  # fraction of frames allowed without target pixels after segmentation, [0, 1]
    seed: int

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


AttackMethod = Literal["fgsm", "pgd", "mifgsm"]        # pipeline.attacks.gradient.ATTACKS (tests/test_robustness.py)
AttackLoss = Literal["full", "position", "rotation"]   # pipeline.attacks.gradient.LOSSES


def attack_name(name: str, key: str) -> tuple[str, Optional[str]]:
    """`method[/loss]` -> (method, loss or None = attack.loss); ValueError naming `key` when unknown."""
    method, _, loss = str(name).partition("/")
    if method not in typing.get_args(AttackMethod) or (loss and loss not in typing.get_args(AttackLoss)):
        raise ValueError(f"{key}: unknown attack {name!r}; use method[/loss] with method one of "
                         f"{', '.join(typing.get_args(AttackMethod))} and loss one of "
                         f"{', '.join(typing.get_args(AttackLoss))}")
    return method, loss or None


@dataclass(frozen=True)
class Corruptions:
    """Benign corruption strengths (pipeline/attacks/corruptions.py applies them; it checks the same ranges)."""

    noise: list[float]           # Gaussian noise std, [0, 1] pixel units, in [0, 1]
    blur: list[float]            # Gaussian blur sigma, pixels, in (0, 20]
    jpeg: list[int]              # JPEG quality, 1..100
    brightness: list[float]      # exposure gain, in (0, 10]
    contrast: list[float]        # factor around the frame's mean grey level, in [0, 10]

    def __post_init__(self) -> None:
        ok = {"noise": lambda s: 0 <= s <= 1, "blur": lambda s: 0 < s <= 20, "jpeg": lambda s: 1 <= s <= 100,
              "brightness": lambda s: 0 < s <= 10, "contrast": lambda s: 0 <= s <= 10}
        for name, inside in ok.items():
            bad = [s for s in getattr(self, name) if not inside(s)]
            if bad:
                raise ValueError(f"{name}: strength {bad[0]!r} is out of range")


@dataclass(frozen=True)
class Robustness:
    frames: int                  # held-out test frames (seeded sample) of the per-frame rows
    harm_m: float                # metres: an attacked frame is harmful when its position error exceeds this
    eps: list[float]             # L-inf budgets, pixels in [0, 1], of the transfer, adaptive and surrogate rows
    unseen_eps: list[float]      # FGSM budgets the detector was not trained on
    transfer: list[str]          # method[/loss]; loss defaults to attack.loss
    steps: int                   # PGD steps, plain, adaptive and on the surrogate (>= 20)
    lambdas: list[float]         # adaptive attack: pose_loss - lambda * detector logit, lambda >= 0
    surrogate_attacks: list[str]  # method[/loss], crafted on models/surrogate.pt
    surrogate_seed: int
    surrogate_epochs: int
    batch_size: int
    burst_every: int             # fused-chain rows: a burst of evaluate.attack_length frames every this many frames
    corruptions: Corruptions

    def __post_init__(self) -> None:
        for key in ("eps", "unseen_eps"):
            values = getattr(self, key)
            if not values:
                raise ValueError(f"{key} must be a non-empty list of values in (0, 1]")
            for e in values:
                if not 0 < e <= 1:
                    raise ValueError(f"{key}: {e!r} is not in (0, 1] (pixels are in [0, 1])")
        if not self.lambdas or not all(0 <= v < float("inf") for v in self.lambdas):
            raise ValueError(f"lambdas must be a non-empty list of finite values >= 0, got {self.lambdas}")
        for key in ("transfer", "surrogate_attacks"):
            for name in getattr(self, key):
                attack_name(name, key)
        if self.steps < 20:
            raise ValueError(f"steps must be >= 20 (an adaptive attack with fewer steps understates the attacker), "
                             f"got {self.steps}")
        if not self.harm_m > 0:
            raise ValueError(f"harm_m must be a positive distance in metres, got {self.harm_m}")
        if min(self.frames, self.batch_size, self.surrogate_epochs, self.burst_every) < 1:
            raise ValueError(f"frames, batch_size, surrogate_epochs and burst_every must be >= 1, got {self.frames}, "
                             f"{self.batch_size}, {self.surrogate_epochs} and {self.burst_every}")



@dataclass(frozen=True)
class Integrity:
    """Integrity metrics (pipeline/evaluation/integrity.py; the alert limit's other constants are guidance's)."""

    collision_range_m: float     # metres: a true range below this is a collision, > 0

    def __post_init__(self) -> None:
        if not self.collision_range_m > 0:
            raise ParamsError(f"params.yaml integrity.collision_range_m must be > 0 (metres), "
                              f"got {self.collision_range_m!r}")
