"""Allocentric attitude: the target's rotation relative to the viewing ray through its centre (camera frame,
OpenCV axes, conventions of pipeline/geometry/rotations.py). A target seen off the optical axis looks rotated by
the ray's angle although its egocentric attitude is unchanged; the allocentric one is what its appearance
shows, the same anywhere in the image (Kundu et al. 2018; used by GDR-Net and other pose networks).
"""

from __future__ import annotations

import numpy as np


def ray_rotation(t: np.ndarray) -> np.ndarray:
    """(..., 3) camera-frame positions (m) -> (..., 3, 3) the smallest rotation taking the optical axis
    (0, 0, 1) onto the viewing ray t / |t| (identity on the axis; Rodrigues about z x ray)."""
    d = np.asarray(t, np.float64) / np.linalg.norm(t, axis=-1, keepdims=True)
    axis = np.stack([-d[..., 1], d[..., 0], np.zeros_like(d[..., 0])], -1)  # z x d
    s, c = np.linalg.norm(axis, axis=-1), d[..., 2]
    k = axis / np.where(s > 1e-12, s, 1.0)[..., None]
    K = np.zeros(k.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -k[..., 2], k[..., 1], -k[..., 0]
    K = K - np.swapaxes(K, -1, -2)
    return np.eye(3) + s[..., None, None] * K + (1 - c)[..., None, None] * (K @ K)


def to_allocentric(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Egocentric attitude R (target -> camera) at camera-frame position t (m) -> allocentric attitude
    (relative to the viewing ray): the same appearance gives the same allocentric R anywhere in the image."""
    return np.swapaxes(ray_rotation(t), -1, -2) @ R


def to_egocentric(R_allo: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Inverse of `to_allocentric`: composes an allocentric attitude with the ray of position t (m)."""
    return ray_rotation(t) @ R_allo
