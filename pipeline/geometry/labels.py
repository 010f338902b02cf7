"""The label columns of every pose table (labels.parquet, the eval-render and lab poses, SPEED imports).

t = target origin in the camera frame (metres), q = target -> camera quaternion, scalar first, and
the 6-D rotation (first two columns of R, column-wise): the conventions of pipeline/geometry/rotations.py.
The pose network's 9 outputs are `TARGET`, in that order.
"""
from __future__ import annotations

import numpy as np

POSITION = ["tx", "ty", "tz"]
QUAT = ["qw", "qx", "qy", "qz"]
SIXD = [f"r{i}" for i in range(6)]
TARGET = POSITION + SIXD


def pose_columns(t: np.ndarray, q: np.ndarray, r6: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """{column: values} for positions t (N, 3) m, quaternions q (N, 4) and optionally 6-D rotations
    r6 (N, 6), in the order tx, ty, tz, qw, qx, qy, qz[, r0..r5] (column views, no copies)."""
    cols = {**{c: t[:, k] for k, c in enumerate(POSITION)}, **{c: q[:, k] for k, c in enumerate(QUAT)}}
    if r6 is not None:
        cols.update({c: r6[:, k] for k, c in enumerate(SIXD)})
    return cols
