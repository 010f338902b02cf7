"""The params.yaml sections of the pose pipeline: camera, render, engine, label, train, attack, guidance,
shap and detect (one frozen dataclass each; `stages.config.schema.build` fills and checks them).

Units and frames are in the field comments; conf/config.yaml holds the defaults.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Optional


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
