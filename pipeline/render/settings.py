"""What the frames of a share see behind the target (pipeline/render/backgrounds.py draws it): the Earth below,
stars and the sensor's black offset and read noise. Declared apart from the drawing so the params schema
(stages/config) composes them without taking the renderer's code."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import numpy as np

from pipeline.settings import In

Direction = Annotated[float, In("[-1000000, 1000000]", "direction component")]


@dataclass(frozen=True)
class BackgroundSettings:
    """What the frames of the share see behind the target; every other frame stays black."""

    share: Annotated[float, In("[0, 1]")] = 0.0  # of the frames, each drawn on its own; 0 = every frame black (off)
    altitude_km: Annotated[float, In("(0, 100000]", "km")] = 1336.0  # the target's orbit altitude (Jason-1)
    nadir: tuple[Direction, Direction, Direction] = (
        0.0,
        0.848,
        0.530,
    )  # to the Earth's centre, world frame (any length)
    nadir_jitter_deg: Annotated[float, In("[0, 90]", "degrees")] = 10.0  # per frame, uniform within this cone
    stars: Annotated[float, In("[0, 1000]", "stars per square degree")] = 0.0  # mean, Poisson; 0 = none
    star_peak: Annotated[float, In("(0, 1]", "pixel units")] = 0.6  # the brightest star's peak pixel value
    black_offset: Annotated[float, In("[0, 1)", "pixel units")] = 0.0  # sensor black level added to every pixel
    noise_std: Annotated[float, In("[0, 1]", "pixel units")] = 0.0  # sensor read noise (Gaussian std)

    def __post_init__(self) -> None:
        """A ValueError naming the first bad background setting."""
        n = np.asarray(self.nadir, dtype=np.float64)
        if not 0 <= self.share <= 1:
            raise ValueError(f"background.share must be in [0, 1], got {self.share}")
        if not self.altitude_km > 0:
            raise ValueError(f"background.altitude_km must be positive, got {self.altitude_km}")
        if n.shape != (3,) or not np.isfinite(n).all() or not np.linalg.norm(n) > 0:
            raise ValueError(f"background.nadir must be a non-zero 3-vector (world frame), got {self.nadir!r}")
        if not 0 <= self.nadir_jitter_deg <= 90:
            raise ValueError(f"background.nadir_jitter_deg must be in [0, 90] degrees, got {self.nadir_jitter_deg}")
        if not self.stars >= 0 or not 0 < self.star_peak <= 1:
            raise ValueError(
                f"background: need stars >= 0 per square degree and star_peak in (0, 1], got {self.stars} and "
                f"{self.star_peak}"
            )
        if not 0 <= self.black_offset < 1 or not self.noise_std >= 0:
            raise ValueError(
                f"background: need black_offset in [0, 1) and noise_std >= 0 (pixel units), "
                f"got {self.black_offset} and {self.noise_std}"
            )
