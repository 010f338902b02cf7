"""The params.yaml sections of the pose pipeline: camera, render, engine, label, train, attack, guidance,
shap and detect (one frozen dataclass each; `stages.config.schema.build` fills and checks them).

Units and frames are in the field comments; conf/config.yaml holds the defaults.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal, Optional

from pipeline.guidance.settings import ExecutionSettings
from pipeline.pose.settings import AugmentConfig
from pipeline.render.settings import BackgroundSettings
from pipeline.settings import In, composed
from stages.config.guards import distinct, odd, range_bins


class ParamsError(ValueError):
    """A params problem the user can fix; the message names the file and the key."""


Seed = Annotated[int, In("[0, 2147483647]", "random seed")]
Count = Annotated[int, In("[1, 1000000000]")]  # how many (frames, samples, epochs, ...)
Batch = Annotated[int, In("[1, 65536]", "samples per batch")]
Pixels = Annotated[int, In("[1, 65536]", "pixels")]
Focal = Annotated[float, In("(0, 1000000]", "pixels")]
Principal = Annotated[float, In("[0, 65536]", "pixels")]
Fraction = Annotated[float, In("(0, 1)")]
Probability = Annotated[float, In("[0, 1]")]
Eps = Annotated[float, In("(0, 1]", "L-inf budget, pixels in [0, 1]")]
Metres = Annotated[float, In("(0, 100000]", "metres")]
Coordinate = Annotated[float, In("[-100000, 100000]", "metres")]
Direction = Annotated[float, In("[-1000000, 1000000]", "direction component")]
Scale = Annotated[float, In("(0, 1000000]", "metres per mesh unit")]
Units = Annotated[int, In("[1, 65536]", "units")]  # network layer sizes


@dataclass(frozen=True)
class Camera:
    ref_width: Pixels  # pixels: the size K is given at
    ref_height: Pixels
    fx: Focal  # pixels, at the reference size
    fy: Focal
    cx: Principal
    cy: Principal


@composed(BackgroundSettings)
class Background:
    """render.background: a share of the frames with the Earth below the target, stars and a sensor black offset
    (pipeline/render/settings.py declares them: units, ranges, defaults); the others stay black. render, eval_render
    and the guidance loop each draw their frames' own; the lab's frames stay black (segmented to black by their
    masks)."""


@dataclass(frozen=True)
class Render:
    width: Annotated[int, In("[8, 8192]", "pixels")]  # also the pose model's input size
    height: Annotated[int, In("[8, 8192]", "pixels")]
    frames_per_sequence: Annotated[int, In("[2, 10000000]", "frames")]
    start_range: Metres  # metres along the approach axis (z)
    end_range: Metres  # metres
    pointing_jitter_deg: Annotated[float, In("[0, 90]", "degrees")]
    max_target_rotation_deg: Annotated[float, In("[0, 180]", "degrees")]
    target_attitude: Literal["per_frame", "per_sequence"]  # rotating sequences: attitude drawn every frame / once
    samples: Annotated[int, In("[1, 65536]", "Cycles samples per pixel")]
    denoiser: str  # NONE | OPENIMAGEDENOISE
    denoise_quality: str  # FAST | BALANCED | HIGH
    threads: Annotated[int, In("[1, 1024]", "Blender threads")]
    device: Literal["cpu", "gpu", "auto"]  # Cycles on the CPU, on a CUDA/OptiX GPU, or the GPU when bpy sees one
    mesh: Optional[str]  # mesh file; inputs/none (or None) = the procedural Jason-1-like target
    source: Optional[str]  # SPEED/SPEED+ folder imported instead of rendering; inputs/none (or None) = render
    source_test: Optional[
        str
    ]  # its test labels, relative to it; None = synthetic/test.json, ... (stages/artifacts/speed.py)
    mesh_scale: Scale  # metres per mesh unit
    sun_direction: list[Direction]  # direction the sunlight travels, target frame
    sun_strength: Annotated[float, In("(0, 10000]", "W/m^2")]
    chunk: Annotated[int, In("[1, 1000000]", "frames per zarr chunk")]
    previews: Annotated[int, In("[1, 1000]", "images")]
    background: Background


@dataclass(frozen=True)
class Engine:
    workers: Optional[Annotated[int, In("[1, 65536]", "workers")]]  # Ray actors, one Blender scene each;
    # None = the cores; 1 = in-process
    address: Optional[str]  # Ray cluster address host:port; None = $RAY_ADDRESS, else a local Ray for the stage
    store: Optional[str]  # where `rpod render` writes images.zarr: None = datasets/render; else a folder or fsspec URL
    timeout_s: Annotated[float, In("(0, 1000000]", "seconds")]  # to connect, or with no chunk finished, before stopping
    retries: Annotated[int, In("[0, 100]", "retries")]  # times a chunk is retried on a restarted worker after it died

    def __post_init__(self) -> None:
        if self.workers is not None and self.workers < 1:
            raise ValueError(f"workers must be at least 1 (or null = the cores), got {self.workers}")
        if self.timeout_s <= 0 or self.retries < 0:
            raise ValueError(f"need timeout_s > 0 and retries >= 0, got {self.timeout_s} and {self.retries}")


@dataclass(frozen=True)
class Label:
    test_fraction: Fraction  # of the frames


@composed(AugmentConfig)
class Augment:
    """train.augment: the photometric augmentation (pipeline/pose/settings.py declares it)."""


@dataclass(frozen=True)
class Adversarial:
    """`rpod train --robust`: the robust pose model (models/pose_robust.pt), PGD-k adversarial training
    behind the black-level clamp."""

    eps: Eps  # L-inf training budget, pixels in [0, 1], reached after ramp_epochs
    steps: Annotated[int, In("[1, 1000]", "PGD steps")]  # k of PGD-k
    ramp_epochs: Annotated[float, In("[0, 1000000]", "epochs")]  # eps ramps linearly from 0
    position_weight: Probability  # weight of the position term in the attack's inner loss
    fraction: Annotated[float, In("(0, 1]", "share of each batch")]  # attacked share of each batch
    attacked_rotation: bool  # fit the rotation of attacked images too (false: their position only)
    black_level: Annotated[float, In("[0, 1)", "pixel units")]  # the input clamp's threshold, > eps
    init: Literal["standard", "scratch"]  # fine-tune models/pose.pt, or train from the seed
    epochs: Annotated[int, In("[1, 1000000]", "epochs")]
    lr_max: Annotated[float, In("(0, 10]", "learning rate")]  # the cosine schedule's peak
    warmup_epochs: Annotated[float, In("[0, 1000000]", "epochs")]
    val_steps: Annotated[int, In("[1, 1000]", "PGD steps")]  # the per-epoch validation attack
    val_frames: Count  # validation images it attacks (seeded subset)
    objectives: list[Literal["position", "range_far", "range_near", "lateral", "attitude"]]  # cycled over attacked rows
    start: Literal["random", "lift"]  # the attack's start in the eps ball
    bpda: bool  # the attack's gradient passes the clamp as the identity
    objective_eps: list[Eps]  # each objective's budget in (0, eps] ([] = eps for every one)
    trades: Annotated[float, In("[0, 1000]", "weight")]  # beta of the TRADES-style consistency term (0: off)
    ablation: bool  # also fine-tune the clamp alone and the attacks alone, and attack both (pose_robust.md)

    def __post_init__(self) -> None:
        unmasked = self.start == "lift" and self.bpda
        if (
            0 < self.eps <= 1 and not self.black_level > self.eps and not unmasked
        ):  # (an eps out of range: its own message)
            raise ValueError(
                f"black_level ({self.black_level}) must exceed eps ({self.eps}) unless start: lift and "
                f"bpda: true: past the clamp a random start and its gradient mask the attack"
            )
        if not self.attacked_rotation and self.fraction == 1:
            raise ValueError("attacked_rotation: false needs fraction < 1 (the rotation is fitted on the clean share)")


@dataclass(frozen=True)
class Train:
    width: Annotated[float, In("(0, 16]", "channel-width multiplier")]  # of Darknet-19
    batch_size: Batch
    val_fraction: Fraction  # of the labelled training frames (whole, seeded): checkpoint selection, never fitted
    epochs: Annotated[int, In("[1, 1000000]", "epochs")]
    max_minutes: Optional[Annotated[float, In("(0, 1000000]", "minutes")]]
    lr_base: Annotated[float, In("(0, 10]", "learning rate")]
    lr_max: Annotated[float, In("(0, 10]", "learning rate")]
    cycle_epochs: Annotated[float, In("(0, 1000000]", "epochs")]  # epochs per half cycle
    schedule: Literal["cyclic", "cosine"]
    lr_min: Annotated[float, In("(0, 10]", "learning rate")]  # the cosine schedule's floor
    warmup_epochs: Annotated[float, In("[0, 1000000]", "epochs")]  # the cosine schedule's warm-up
    ema: Annotated[float, In("[0, 1)", "decay per optimiser step")]  # weights' moving average; 0 = none
    weight_decay: Annotated[float, In("[0, 1]", "L2 weight decay")]
    dropout: Annotated[float, In("[0, 1)", "probability")]
    channels_last: bool
    compile: bool
    workers: Annotated[int, In("[0, 1024]", "processes")]
    augment: Augment
    range_bins: list[Metres]  # metres, bin edges of the per-range error tables
    adversarial: Adversarial

    def __post_init__(self) -> None:
        if not 0 < self.val_fraction < 1:
            raise ValueError(f"val_fraction must be in (0, 1), got {self.val_fraction!r}")
        range_bins(self.range_bins, "train.range_bins")


@dataclass(frozen=True)
class Attack:
    eps: list[Eps]  # L-inf budgets, pixels in [0, 1]
    method: str  # fgsm | pgd | mifgsm
    loss: str  # full | position | rotation
    steps: Annotated[int, In("[1, 100000]", "steps")]
    step_size: Optional[Annotated[float, In("(0, 1]", "pixel units")]]  # None = the method's default
    random_start: bool
    momentum: Annotated[float, In("[0, 10]", "MI-FGSM decay")]
    batch_size: Batch
    max_images: Optional[Count]  # None = the whole test set

    def __post_init__(self) -> None:
        distinct(self.eps, "attack.eps")


@composed(ExecutionSettings, runtime=("seed",))
class Execution:
    """guidance.execution: how the thrusters and the orbit execute a commanded step (pipeline/guidance/settings.py
    declares it); the errors' seed comes from pipeline/seeds.py."""


@dataclass(frozen=True)
class Guidance:
    eps: list[Eps]
    start_ranges: list[Metres]  # metres (S)
    lengths: list[Annotated[int, In("[1, 1000000]", "frames")]]  # attacked frames (K)
    start: list[Coordinate]  # metres, target-centred camera frame
    target: list[Coordinate]  # metres
    tolerance: Metres  # metres
    max_step: Metres  # metres per step per axis
    max_steps: Annotated[int, In("[1, 10000000]", "steps")]
    slack_steps: Annotated[int, In("[0, 10000000]", "steps")]
    variant: str  # paper | true_state: the dynamics of the paper's S x K tables
    method: str
    dynamics: list[Literal["paper", "true_state"]]  # dynamics of the defended comparison
    defenses: list[Literal["hold", "recover"]]  # defended variants flown beside the undefended one
    standard_defenses: list[Literal["hold", "recover"]]  # the standard chain's variants against the in-loop attacker
    execution: Execution  # the truth's executed motion (true_state runs, evaluation and validation trajectories)

    def __post_init__(self) -> None:
        distinct(self.eps, "guidance.eps")
        for key in ("dynamics", "defenses", "standard_defenses"):  # a repeat would fly a block twice under one name
            values = getattr(self, key)
            twice = next((v for i, v in enumerate(values) if v in values[:i]), None)
            if twice is not None:
                raise ValueError(f"guidance.{key} lists {twice!r} twice; give each value once")


@dataclass(frozen=True)
class Shap:
    background: Annotated[int, In("[1, 10000000]", "images")]
    normal: Annotated[int, In("[1, 1000000000]", "samples")]
    per_eps: Annotated[int, In("[1, 1000000000]", "samples")]
    eps: list[Eps]
    method: str  # auto | exact | deep
    chunk: Annotated[int, In("[1, 1000000]", "samples per zarr chunk")]
    frames: Annotated[int, In("[2, 10000000]", "frames per detector trajectory")]
    seed: Seed  # of the detector split's trajectories (datasets/detect_render)

    def __post_init__(self) -> None:
        distinct(self.eps, "shap.eps")


@dataclass(frozen=True)
class Detect:
    hidden: Units
    dense: list[Units]
    epochs: Annotated[int, In("[1, 1000000]", "epochs")]
    patience: Annotated[int, In("[1, 1000000]", "epochs")]
    batch_size: Batch
    lr: Annotated[float, In("(0, 100]", "Adadelta learning rate")]
    val_fraction: Fraction
    test_fraction: Fraction
    baselines: list[Literal["mlp", "mahalanobis", "lid", "squeeze"]]
    mlp_hidden: list[Units]
    lid_k: Annotated[int, In("[1, 100000]", "neighbours")]
    lid_batch: Annotated[int, In("[2, 1000000]", "samples")]
    squeeze_bits: Annotated[int, In("[1, 8]", "bits per channel")]
    squeeze_median: Annotated[int, In("[1, 99]", "pixels, odd")]

    def __post_init__(self) -> None:
        for key in ("test_fraction", "val_fraction"):
            if not 0 < getattr(self, key) < 1:
                raise ValueError(f"{key} must be in (0, 1), got {getattr(self, key)!r}")
        odd(self.squeeze_median, "detect.squeeze_median")
