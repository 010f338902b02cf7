"""Rotations in the OpenCV camera frame (x right, y down, z forward).

Conventions: position t = target origin in the camera frame (metres); quaternion
q = (qw, qx, qy, qz), scalar first, rotating target-frame vectors into the camera frame
(the same numbers as SPEED/SPEED+ `q_vbs2tango_true`: pipeline/formats/speed.py); 6-D rotation (Zhou et al.
2019) = first two columns of R, flattened column-wise: (R00, R10, R20, R01, R11, R21).
The numpy functions are batched over leading axes; the `_t` ones are their differentiable torch
counterparts on (B, ...) tensors; the `_list` ones work on one rotation as plain floats and 3x3 nested
lists (the motion filter's per-frame path, pipeline/defense/kalman.py).
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import torch
from torch import Tensor

Mat3 = list[list[float]]
UNIT_TOLERANCE = (
    1e-3  # |norm(q) - 1| of a stored quaternion above this is refused (SPEED labels, mocap), not normalised
)


def normalize_quat(q: np.ndarray) -> np.ndarray:
    """Unit quaternion with a non-negative scalar part (q and -q are the same rotation)."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """(..., 4) scalar-first quaternion -> (..., 3, 3) rotation matrix."""
    w, x, y, z = np.moveaxis(normalize_quat(q), -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrix -> (..., 4) unit quaternion, scalar first, qw >= 0.

    Uses the largest-diagonal branch (Shepperd's method), stable for every rotation.
    """
    R = np.asarray(R, dtype=np.float64)
    m = R.reshape(-1, 3, 3)
    tr = np.trace(m, axis1=1, axis2=2)
    cand = np.stack([tr, m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], 1)
    k = np.argmax(cand, 1)
    q = np.empty((len(m), 4))
    for i, (Ri, ki) in enumerate(zip(m, k)):
        if ki == 0:
            s = 2 * np.sqrt(1 + tr[i])
            q[i] = [s / 4, (Ri[2, 1] - Ri[1, 2]) / s, (Ri[0, 2] - Ri[2, 0]) / s, (Ri[1, 0] - Ri[0, 1]) / s]
        elif ki == 1:
            s = 2 * np.sqrt(1 + Ri[0, 0] - Ri[1, 1] - Ri[2, 2])
            q[i] = [(Ri[2, 1] - Ri[1, 2]) / s, s / 4, (Ri[0, 1] + Ri[1, 0]) / s, (Ri[0, 2] + Ri[2, 0]) / s]
        elif ki == 2:
            s = 2 * np.sqrt(1 - Ri[0, 0] + Ri[1, 1] - Ri[2, 2])
            q[i] = [(Ri[0, 2] - Ri[2, 0]) / s, (Ri[0, 1] + Ri[1, 0]) / s, s / 4, (Ri[1, 2] + Ri[2, 1]) / s]
        else:
            s = 2 * np.sqrt(1 - Ri[0, 0] - Ri[1, 1] + Ri[2, 2])
            q[i] = [(Ri[1, 0] - Ri[0, 1]) / s, (Ri[0, 2] + Ri[2, 0]) / s, (Ri[1, 2] + Ri[2, 1]) / s, s / 4]
    return normalize_quat(q).reshape(R.shape[:-2] + (4,))


def matrix_to_6d(R: np.ndarray) -> np.ndarray:
    """(..., 3, 3) -> (..., 6): first two columns, column-wise."""
    R = np.asarray(R)
    return np.concatenate([R[..., :, 0], R[..., :, 1]], -1)


def sixd_to_matrix(r6: np.ndarray) -> np.ndarray:
    """(..., 6) -> (..., 3, 3) by Gram-Schmidt (Zhou et al. 2019); any 6-vector gives a rotation."""
    r6 = np.asarray(r6, dtype=np.float64)
    a, b = r6[..., :3], r6[..., 3:]
    c0 = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b - np.sum(c0 * b, -1, keepdims=True) * c0
    c1 = b / np.linalg.norm(b, axis=-1, keepdims=True)
    c2 = np.cross(c0, c1)
    return np.stack([c0, c1, c2], -1)


def quat_to_6d(q: np.ndarray) -> np.ndarray:
    return matrix_to_6d(quat_to_matrix(q))


def sixd_to_quat(r6: np.ndarray) -> np.ndarray:
    return matrix_to_quat(sixd_to_matrix(r6))


def euler_to_matrix(angles_deg: np.ndarray) -> np.ndarray:
    """(..., 3) rotations about x, y, z in degrees, applied x first: R = Rz @ Ry @ Rx."""
    a = np.deg2rad(np.asarray(angles_deg, dtype=np.float64))
    cx, cy, cz = np.cos(a[..., 0]), np.cos(a[..., 1]), np.cos(a[..., 2])
    sx, sy, sz = np.sin(a[..., 0]), np.sin(a[..., 1]), np.sin(a[..., 2])
    o, z = np.ones_like(cx), np.zeros_like(cx)
    Rx = np.stack([np.stack([o, z, z], -1), np.stack([z, cx, -sx], -1), np.stack([z, sx, cx], -1)], -2)
    Ry = np.stack([np.stack([cy, z, sy], -1), np.stack([z, o, z], -1), np.stack([-sy, z, cy], -1)], -2)
    Rz = np.stack([np.stack([cz, -sz, z], -1), np.stack([sz, cz, z], -1), np.stack([z, z, o], -1)], -2)
    return Rz @ Ry @ Rx


def rotvec_to_matrix(w: Sequence[float] | np.ndarray) -> np.ndarray:
    """Rodrigues: rotation vector (3,, radians) -> rotation matrix. Same as scipy's
    Rotation.from_rotvec(w).as_matrix() (tested), without its per-call overhead (~0.1 ms, more than
    the whole filter's cost per frame)."""
    return np.array(rotmat_list(float_lists(w)))


def rotmat_list(w: Sequence[float]) -> Mat3:
    """`rotvec_to_matrix` on floats, as a nested list: R = I + s W + k W^2, W^2 = w w^T - th^2 I."""
    w0, w1, w2 = w
    th2 = w0 * w0 + w1 * w1 + w2 * w2
    s, k = 1.0, 0.0
    if th2 >= 1e-16:
        th = math.sqrt(th2)
        s, k = math.sin(th) / th, (1.0 - math.cos(th)) / th2
    d = 1.0 - k * th2
    kxy, kxz, kyz = k * w0 * w1, k * w0 * w2, k * w1 * w2
    return [
        [d + k * w0 * w0, kxy - s * w2, kxz + s * w1],
        [kxy + s * w2, d + k * w1 * w1, kyz - s * w0],
        [kxz - s * w1, kyz + s * w0, d + k * w2 * w2],
    ]


def matrix_to_rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation matrix -> rotation vector (3,, radians), angle in [0, pi]; the inverse of
    `rotvec_to_matrix` (tested against scipy)."""
    return np.array(rotvec_list(float_lists(R)))


def rotvec_list(R: Mat3) -> tuple[float, float, float]:
    """`matrix_to_rotvec` of a nested list, as three floats."""
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = R
    th = math.acos(max(-1.0, min(1.0, (r00 + r11 + r22 - 1.0) / 2.0)))
    v0, v1, v2 = r21 - r12, r02 - r20, r10 - r01
    if th >= math.pi - 1e-4:  # near pi: axis from the symmetric part
        B = (np.array(R) + np.eye(3)) / 2.0
        i = int(np.argmax(np.diag(B)))
        axis = B[:, i] / math.sqrt(B[i, i])
        if axis @ np.array([v0, v1, v2]) < 0:
            axis = -axis
        return tuple((axis * th).tolist())
    f = 0.5 if th < 1e-6 else th / (2.0 * math.sin(th))
    return v0 * f, v1 * f, v2 * f


def float_lists(a: Sequence | np.ndarray) -> list:
    """An array (or nested sequence) of numbers as (nested) lists of Python floats."""
    return a.tolist() if isinstance(a, np.ndarray) and a.dtype == np.float64 else np.asarray(a, np.float64).tolist()


def sixd_to_matrix_t(r6: Tensor) -> Tensor:
    """(B, 6) -> (B, 3, 3) rotations by Gram-Schmidt, differentiable (as `sixd_to_matrix`)."""
    a, b = r6[:, :3], r6[:, 3:]
    c0 = a / a.norm(dim=1, keepdim=True)
    c1 = b - (c0 * b).sum(1, keepdim=True) * c0
    c1 = c1 / c1.norm(dim=1, keepdim=True)
    return torch.stack([c0, c1, torch.cross(c0, c1, dim=1)], -1)


def rotvec_t(R: Tensor) -> Tensor:
    """(B, 3, 3) rotations -> (B, 3) rotation vectors (rad), differentiable away from angle 0 and pi
    (angle = atan2(|v| / 2, (trace - 1) / 2) with v the skew part, a tiny epsilon at 0)."""
    v = torch.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], 1)
    s = torch.sqrt((v * v).sum(1) + 1e-12)
    angle = torch.atan2(s / 2, (R.diagonal(dim1=1, dim2=2).sum(1) - 1) / 2)
    return v * (angle / s).unsqueeze(1)
