"""Pinhole camera in the OpenCV frame (x right, y down, z forward), pixel centres at integers."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels for an image of width x height pixels."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")

    @classmethod
    def from_K(cls, K: Any, width: int, height: int) -> "Intrinsics":
        """The camera of a 3x3 pinhole matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (pixels) at width x height
        pixels (ValueError for any other matrix: skewed, transposed, not finite, fx or fy <= 0)."""
        k = np.asarray(K, dtype=np.float64)
        if k.shape != (3, 3) or not np.isfinite(k).all() or k[0, 1] != 0 or k[1, 0] != 0 or list(k[2]) != [0, 0, 1]:
            raise ValueError(
                f"must be a 3x3 pinhole matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew; not transposed), got {K!r}"
            )
        if k[0, 0] <= 0 or k[1, 1] <= 0:
            raise ValueError(f"must have focal lengths fx, fy > 0 (pixels), got {K!r}")
        return cls(width, height, float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]))

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    def scaled(self, width: int, height: int) -> "Intrinsics":
        """The same camera resampled to width x height (pixel-centre convention kept exact)."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(
            width, height, self.fx * sx, self.fy * sy, (self.cx + 0.5) * sx - 0.5, (self.cy + 0.5) * sy - 0.5
        )

    @property
    def fov_deg(self) -> tuple[float, float]:
        """Full horizontal and vertical field of view in degrees."""
        return (
            float(np.rad2deg(2 * np.arctan(self.width / (2 * self.fx)))),
            float(np.rad2deg(2 * np.arctan(self.height / (2 * self.fy)))),
        )


def camera_difference(a: Intrinsics, b: Intrinsics) -> float:
    """How far camera `b` is from `a`, both at a's image size (b scaled to it): the largest relative difference
    of fx and fy (over a's) and of cx and cy (over the image width and height); 0 for the same camera."""
    b = b.scaled(a.width, a.height)
    return max(
        abs(b.fx - a.fx) / a.fx, abs(b.fy - a.fy) / a.fy, abs(b.cx - a.cx) / a.width, abs(b.cy - a.cy) / a.height
    )


def reference_intrinsics(
    width: int = 480, height: int = 270, fx: float = 640.0, fy: float = 360.0, cx: float = 240.0, cy: float = 135.0
) -> Intrinsics:
    """The paper's synthetic camera as printed, K given at 480x270. Its fy = 360 is most
    likely a slip for fy = fx (square pixels); the params default (`camera.fy`) is fy = fx."""
    return Intrinsics(width, height, fx, fy, cx, cy)


def project(points_cam: np.ndarray, K: Intrinsics) -> np.ndarray:
    """(..., 3) camera-frame points (metres, z > 0) -> (..., 2) pixel coordinates (u, v)."""
    p = np.asarray(points_cam, dtype=np.float64)
    z = p[..., 2]
    if np.any(z <= 0):
        raise ValueError("cannot project points at or behind the camera (z <= 0)")
    return np.stack([K.fx * p[..., 0] / z + K.cx, K.fy * p[..., 1] / z + K.cy], -1)


def transform(points_obj: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Target-frame points (..., 3) -> camera frame with rotation R (3, 3) and translation t (3,)."""
    return np.asarray(points_obj) @ np.asarray(R).T + np.asarray(t)
