"""The photometric augmentation's settings (pipeline/pose/augment.py applies them). Declared apart from the
augmentations so the params schema (stages/config) composes them without taking OpenCV."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from pipeline.settings import In

Sigma = Annotated[float, In("[0, 20]", "pixels")]
Noise = Annotated[float, In("[0, 1]", "pixel units")]
Quality = Annotated[int, In("[1, 100]", "JPEG quality")]
Gain = Annotated[float, In("(0, 10]", "gain")]


@dataclass(frozen=True)
class AugmentConfig:
    """Ranges are sampled uniformly. Units: blur sigma in pixels, noise std in [0, 1] pixel units,
    JPEG quality 0-100, brightness as a multiplicative gain."""

    p: Annotated[float, In("[0, 1]")] = 0.5  # probability of each augmentation
    blur_sigma: tuple[Sigma, Sigma] = (0.3, 1.2)  # [low, high]
    noise_std: tuple[Noise, Noise] = (0.0, 0.03)
    jpeg_quality: tuple[Quality, Quality] = (40, 95)
    brightness: tuple[Gain, Gain] = (0.7, 1.3)  # multiplicative

    def __post_init__(self) -> None:
        if not 0 <= self.p <= 1:
            raise ValueError(f"augment p must be in [0, 1], got {self.p}")
        for name in ("blur_sigma", "noise_std", "jpeg_quality", "brightness"):
            lo, hi = getattr(self, name)
            if lo > hi or lo < 0:
                raise ValueError(f"augment {name} must be a range [low, high] with 0 <= low <= high, got {[lo, hi]}")
        if self.jpeg_quality[1] > 100:
            raise ValueError(f"augment jpeg_quality must be within 0..100, got {list(self.jpeg_quality)}")
