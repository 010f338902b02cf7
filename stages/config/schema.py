"""Typed params: one dataclass per params.yaml section, built and checked once by `stages.config.params.load`.

`build(params)` turns the params.yaml mapping into a `Params` (types checked field by field: a whole
number where one is expected, lists of numbers, null only where allowed; unknown keys refused with
a suggestion) and runs each section's range checks. Errors are `ParamsError`s naming the key.
Units and frames are in the field comments; conf/config.yaml holds the defaults.
"""
from __future__ import annotations

import dataclasses
import difflib
import re
import types
import typing
from dataclasses import dataclass, field
from typing import Any, Literal, Optional


DEVICE = re.compile(r"auto|cpu|cuda(:\d+)?")   # values of the `device` param


class ParamsError(ValueError):
    """A params problem the user can fix; the message names the file and the key."""


@dataclass(frozen=True)
class Camera:
    ref_width: int          # pixels: the size K is given at
    ref_height: int
    fx: float               # pixels, at the reference size
    fy: float
    cx: float
    cy: float


@dataclass(frozen=True)
class Render:
    width: int              # pixels (also the pose model's input size)
    height: int
    frames_per_sequence: int
    start_range: float      # metres along the approach axis (z)
    end_range: float        # metres
    pointing_jitter_deg: float
    max_target_rotation_deg: float
    samples: int            # Cycles samples per pixel
    denoiser: str           # NONE | OPENIMAGEDENOISE
    denoise_quality: str    # FAST | BALANCED | HIGH
    threads: int            # Blender render threads
    mesh: Optional[str]     # mesh file; inputs/none (or None) = the procedural Jason-1-like target
    source: Optional[str]   # SPEED/SPEED+ folder imported instead of rendering; inputs/none (or None) = render
    source_test: Optional[str]   # its test labels, relative to it; None = synthetic/test.json, ... (stages/artifacts/speed.py)
    mesh_scale: float       # metres per mesh unit
    sun_direction: list[float]   # direction the sunlight travels, target frame
    sun_strength: float
    chunk: int              # frames per zarr chunk
    previews: int


@dataclass(frozen=True)
class Engine:
    workers: Optional[int]  # parallel workers (Ray actors, one Blender scene each); None = the cores; 1 = in-process
    address: Optional[str]  # Ray cluster address host:port; None = $RAY_ADDRESS, else a local Ray for the stage
    store: Optional[str]    # where `rpod render` writes images.zarr: None = datasets/render; else a folder or fsspec URL
    timeout_s: float        # seconds to connect, or without any finished chunk, before the stage stops
    retries: int            # times a chunk is retried on a restarted worker after its worker died

    def __post_init__(self) -> None:
        if self.workers is not None and self.workers < 1:
            raise ValueError(f"workers must be at least 1 (or null = the cores), got {self.workers}")
        if self.timeout_s <= 0 or self.retries < 0:
            raise ValueError(f"need timeout_s > 0 and retries >= 0, got {self.timeout_s} and {self.retries}")


@dataclass(frozen=True)
class Label:
    test_fraction: float    # of the frames, in (0, 1)


@dataclass(frozen=True)
class Augment:
    p: float                # probability of each augmentation
    blur_sigma: list[float]      # pixels, [low, high]
    noise_std: list[float]       # [0, 1] pixel units
    jpeg_quality: list[int]
    brightness: list[float]      # multiplicative


@dataclass(frozen=True)
class Train:
    width: float            # channel-width multiplier of Darknet-19
    batch_size: int
    val_fraction: float     # of the labelled training frames (whole frames, seeded): checkpoint selection, never fitted
    epochs: int
    max_minutes: Optional[float]
    lr_base: float
    lr_max: float
    cycle_epochs: float     # epochs per half cycle
    weight_decay: float
    dropout: float
    channels_last: bool
    compile: bool
    workers: int
    augment: Augment
    range_bins: list[float]      # metres, bin edges of the per-range error tables

    def __post_init__(self) -> None:
        if not 0 < self.val_fraction < 1:
            raise ValueError(f"val_fraction must be in (0, 1), got {self.val_fraction!r}")


@dataclass(frozen=True)
class Attack:
    eps: list[float]        # L-inf budgets, pixels in [0, 1]
    method: str             # fgsm | pgd | mifgsm
    loss: str               # full | position | rotation
    steps: int
    step_size: Optional[float]   # pixel units; None = the method's default
    random_start: bool
    momentum: float
    batch_size: int
    max_images: Optional[int]    # None = the whole test set


@dataclass(frozen=True)
class Guidance:
    eps: list[float]
    start_ranges: list[float]    # metres (S)
    lengths: list[int]           # attacked frames (K)
    start: list[float]           # metres, target-centred camera frame
    target: list[float]          # metres
    tolerance: float             # metres
    max_step: float              # metres per step per axis
    max_steps: int
    slack_steps: int
    variant: str                 # paper | true_state: the dynamics of the paper's S x K tables
    method: str
    dynamics: list[Literal["paper", "true_state"]]   # dynamics of the defended comparison
    defenses: list[Literal["hold", "recover"]]       # defended variants flown beside the undefended one


@dataclass(frozen=True)
class Shap:
    background: int
    normal: int
    per_eps: int
    eps: list[float]
    method: str                  # auto | exact | deep
    chunk: int


@dataclass(frozen=True)
class Detect:
    hidden: int
    dense: list[int]
    epochs: int
    patience: int
    batch_size: int
    lr: float
    val_fraction: float
    test_fraction: float
    baselines: list[Literal["mlp", "mahalanobis", "lid", "squeeze"]]
    mlp_hidden: list[int]
    lid_k: int
    lid_batch: int
    squeeze_bits: int
    squeeze_median: int          # pixels, odd

    def __post_init__(self) -> None:
        for key in ("test_fraction", "val_fraction"):
            if not 0 < getattr(self, key) < 1:
                raise ValueError(f"{key} must be in (0, 1), got {getattr(self, key)!r}")


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
class Report:
    pass


@dataclass(frozen=True)
class Params:
    profile_name: str
    seed: int
    threads: Optional[int]       # torch CPU threads of every torch stage; None = every core
    device: str                  # auto | cpu | cuda | cuda:N (stages.config.params.torch_device resolves it)
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
    report: Report = field(default_factory=Report)

    def __post_init__(self) -> None:
        if self.threads is not None and self.threads < 1:
            raise ValueError(f"threads must be null or a whole number >= 1, got {self.threads}")
        if not DEVICE.fullmatch(self.device):
            raise ValueError(f"device must be auto, cpu, cuda or cuda:N, got {self.device!r}")
        if self.defense.val_seed == self.evaluate.seed:
            raise ValueError("defense.val_seed must differ from evaluate.seed: the defense is fitted on "
                             "validation trajectories, never on the evaluation ones")


def _check(value: Any, hint: Any, key: str) -> Any:
    """`value` converted to the type `hint` (ints accepted for floats), or a ParamsError naming `key`."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
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
    return float(value) if hint is float else value


def _build(cls: type, section: Any, key: str) -> Any:
    if not isinstance(section, dict):
        if key:   # a section replaced by a value (e.g. `-S train=1`)
            raise ParamsError(f"params.yaml: {key!r} must be a section of parameters, got {section!r}")
        raise ParamsError(f"params.yaml top level must be a mapping, got {section!r}")
    hints = typing.get_type_hints(cls)
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
        return cls(**values)
    except ParamsError:
        raise                        # already names its key in full
    except ValueError as e:
        raise ParamsError(f"params.yaml {key + ': ' if key else ''}{e}") from None


def build(params: dict[str, Any]) -> Params:
    """The typed, checked params of a params.yaml mapping."""
    return _build(Params, params, "")
