"""Chaser-camera trajectories around the target, pure numpy.

Frames. The world frame is centred on the target. `rel` is the position of the target relative to
the chaser camera, in world axes (metres); the nominal approach runs along world +z, so a chaser
"at (x, y, 60)" has rel = (x, y, 60) and the approach ends at rel = (0, 0, 10).
`R_cam` rotates camera-frame vectors (OpenCV: x right, y down, z boresight) into world axes and
`R_target` rotates target-frame vectors into world axes. The labels are then

    t = R_cam^T rel                (target origin in the camera frame, metres)
    R = R_cam^T R_target           (target frame -> camera frame; q = matrix_to_quat(R))

Up convention of `look_at`: the camera y axis (image down) is world +y projected onto the image
plane, so looking along +z gives R_cam = identity (camera axes = world axes).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from pipeline.geometry.rotations import euler_to_matrix

# The 13 sequences' lateral start offsets (x, y) in metres.
FIXED_STARTS = [(0.0, 0.0), (-15.0, -25.0), (-15.0, 25.0), (15.0, 25.0), (15.0, -25.0)]
ROTATING_STARTS = [(-15.0, -10.0), (-15.0, 10.0), (15.0, 10.0), (15.0, -10.0)]


@dataclass(frozen=True)
class Sequence:
    """One trajectory: per-frame arrays of length n (metres, rotation matrices)."""

    sequence: int  # sequence id
    frame: np.ndarray  # (n,) frame index within the sequence
    R: np.ndarray  # (n, 3, 3) target frame -> camera frame (the label rotation)
    t: np.ndarray  # (n, 3) target origin in the camera frame (the label position)
    rel: np.ndarray  # (n, 3) target relative to the chaser, world axes
    R_cam: np.ndarray  # (n, 3, 3) camera frame -> world
    R_target: np.ndarray  # (n, 3, 3) target frame -> world
    commands: np.ndarray | None = None  # (n, 3) commanded displacement of rel per frame (world, m; row 0 zero),
    #                                      when it differs from the flown one (None: u = diff(rel))

    def __len__(self) -> int:
        return len(self.frame)


def look_at(direction: np.ndarray) -> np.ndarray:
    """Camera rotation (camera -> world, (..., 3, 3)) whose boresight +z points along `direction`.

    Camera y (image down) is world +y made orthogonal to the boresight; camera x = y x z.
    A boresight parallel to world y falls back to world +z for the up reference.
    """
    d = np.asarray(direction, dtype=np.float64)
    z = d / np.linalg.norm(d, axis=-1, keepdims=True)
    ref = np.broadcast_to(np.array([0.0, 1.0, 0.0]), z.shape).copy()
    parallel = np.abs(np.sum(z * ref, -1)) > 1 - 1e-9
    ref[parallel] = [0.0, 0.0, 1.0]
    y = ref - np.sum(z * ref, -1, keepdims=True) * z
    y /= np.linalg.norm(y, axis=-1, keepdims=True)
    x = np.cross(y, z)
    return np.stack([x, y, z], -1)


def pose_in_camera(rel: np.ndarray, R_cam: np.ndarray, R_target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World geometry -> label pose: (R target->camera (..., 3, 3), t target origin in camera (..., 3))."""
    R_cam_T = np.swapaxes(R_cam, -1, -2)
    t = np.einsum("...ij,...j->...i", R_cam_T, rel)
    return R_cam_T @ R_target, t


def _jittered_cameras(rel: np.ndarray, jitter_deg: float, rng: np.random.Generator) -> np.ndarray:
    """Cameras pointing at the target, each turned by a uniform random angle in [-jitter, +jitter]
    about its own x and y axes (so the target centre moves by at most about f * tan(jitter) pixels)."""
    n = len(rel)
    ang = np.zeros((n, 3))
    ang[:, :2] = rng.uniform(-jitter_deg, jitter_deg, size=(n, 2))
    return look_at(rel) @ euler_to_matrix(ang)


ATTITUDES = ("per_frame", "per_sequence")  # the rotating sequences' target attitude: drawn every frame / once


def _sequence(
    seq_id: int,
    rel: np.ndarray,
    jitter_deg: float,
    max_rot_deg: float,
    rng: np.random.Generator,
    attitude: str = "per_frame",
    commands: np.ndarray | None = None,
) -> Sequence:
    n = len(rel)
    R_cam = _jittered_cameras(rel, jitter_deg, rng)
    if max_rot_deg > 0 and attitude == "per_sequence":
        R_target = np.broadcast_to(euler_to_matrix(rng.uniform(-max_rot_deg, max_rot_deg, size=3)), (n, 3, 3)).copy()
    elif max_rot_deg > 0:
        R_target = euler_to_matrix(rng.uniform(-max_rot_deg, max_rot_deg, size=(n, 3)))
    else:
        R_target = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    R, t = pose_in_camera(rel, R_cam, R_target)
    return Sequence(seq_id, np.arange(n), R, t, rel, R_cam, R_target, commands)


def _check(frames: int, start_range: float, end_range: float, jitter_deg: float) -> None:
    if frames < 2:
        raise ValueError(f"frames per sequence must be at least 2, got {frames}")
    if not 0 < end_range < start_range:
        raise ValueError(f"need 0 < end_range < start_range, got {end_range} and {start_range} m")
    if not 0 <= jitter_deg < 45:
        raise ValueError(f"pointing jitter must be in [0, 45) degrees, got {jitter_deg}")


def approach_sequences(
    frames_per_sequence: int,
    start_range: float = 60.0,
    end_range: float = 10.0,
    jitter_deg: float = 2.0,
    max_rot_deg: float = 10.0,
    seed: int = 0,
    attitude: str = "per_frame",
) -> list[Sequence]:
    """The 13 approach sequences of the training set.

    Each runs in a straight line, in equal steps, from rel = (x, y, start_range) to
    (0, 0, end_range). Sequences 0-4 start at FIXED_STARTS with the target attitude fixed (identity);
    sequences 5-12 start at ROTATING_STARTS (twice) with a random target attitude, uniform in
    +-max_rot_deg about each target axis (x, then y, then z): `attitude` "per_frame" draws a fresh one on
    every frame, "per_sequence" (paper-like labels: the paper's Table 1 gives each sequence one fixed
    attitude, 0 or +-10 deg) draws one per sequence and holds it. Every frame the camera points at the
    target, turned by a uniform random pointing jitter of up to +-jitter_deg about its x and y axes.
    Seeded: the same arguments give the same sequences (and "per_frame" the ones it always gave).
    """
    _check(frames_per_sequence, start_range, end_range, jitter_deg)
    if attitude not in ATTITUDES:
        raise ValueError(f"target attitude must be one of {', '.join(ATTITUDES)}, got {attitude!r}")
    rng = np.random.default_rng(seed)
    s = np.linspace(0.0, 1.0, frames_per_sequence)[:, None]
    end = np.array([0.0, 0.0, end_range])
    starts = [(xy, 0.0) for xy in FIXED_STARTS] + [(xy, max_rot_deg) for xy in ROTATING_STARTS * 2]
    out = []
    for i, ((x, y), rot) in enumerate(starts):
        rel = (1 - s) * np.array([x, y, start_range]) + s * end
        out.append(_sequence(i, rel, jitter_deg, rot, rng, attitude))
    return out


def attitude_groups(sequence: np.ndarray) -> np.ndarray:
    """The target-attitude group of each frame of `approach_sequences` from its sequence id: "fixed" for
    sequences 0-4 (FIXED_STARTS, attitude identity), "rotating" for 5-12 (attitude drawn per frame or per
    sequence)."""
    return np.where(np.asarray(sequence) < len(FIXED_STARTS), "fixed", "rotating")


PATHS = ("projectile", "straight")


def approach_trajectory(
    n_frames: int,
    start_xy: tuple[float, float],
    start_range: float = 60.0,
    end_range: float = 10.0,
    seed: int = 0,
    jitter_deg: float = 0.0,
    max_rot_deg: float = 0.0,
    sequence: int = 0,
    path: str = "projectile",
    execute: Callable[[np.ndarray], np.ndarray] | None = None,
) -> Sequence:
    """A fresh approach: uniform z steps from start_range to end_range (metres) while the lateral offset
    goes from start_xy to 0, arriving at (0, 0, end_range). `path` "projectile" (the evaluation
    trajectories): xy(s) = start_xy * (1 - s)^2 for s in [0, 1], bending in with zero lateral velocity at
    the end; "straight": xy(s) = start_xy * (1 - s), a straight line as in the training sequences (seen
    obliquely until the end). Camera pointing (optional jitter, degrees) and target attitude (uniform in
    +-max_rot_deg about each axis, drawn afresh every frame) as in `approach_sequences`. Seeded.
    `execute` maps the planned rel (n, 3) to the rel actually flown (n, 3), e.g. with execution error
    (pipeline.guidance.dynamics.execute_plan): the labels and the camera follow the flown rel and
    `Sequence.commands` holds the planned steps, what the chaser commanded and its chain is told.
    """
    _check(n_frames, start_range, end_range, jitter_deg)
    if path not in PATHS:
        raise ValueError(f"path must be one of {PATHS}, got {path!r}")
    rng = np.random.default_rng(seed)
    s = np.linspace(0.0, 1.0, n_frames)
    decay = (1 - s) ** 2 if path == "projectile" else 1 - s
    xy = np.asarray(start_xy, dtype=np.float64)[None, :] * decay[:, None]
    z = start_range + s * (end_range - start_range)
    rel = np.column_stack([xy, z])
    if execute is None:
        return _sequence(sequence, rel, jitter_deg, max_rot_deg, rng)
    flown = np.asarray(execute(rel), np.float64)
    if flown.shape != rel.shape:
        raise ValueError(
            f"approach_trajectory: execute must return the flown rel of shape {rel.shape}, got {flown.shape}"
        )
    return _sequence(
        sequence, flown, jitter_deg, max_rot_deg, rng, commands=np.vstack([np.zeros(3), np.diff(rel, axis=0)])
    )


def poses_table(idx: np.ndarray, seq: np.ndarray, frm: np.ndarray, R: np.ndarray, t: np.ndarray):
    """The poses of rendered frames as a DataFrame: index, sequence, frame, t (tx, ty, tz; m),
    q (qw, qx, qy, qz; target -> camera) and range (m)."""
    import pandas as pd

    from pipeline.geometry.labels import pose_columns
    from pipeline.geometry.rotations import matrix_to_quat

    q = matrix_to_quat(R)
    return pd.DataFrame(
        {"index": idx, "sequence": seq, "frame": frm, **pose_columns(t, q), "range": np.linalg.norm(t, axis=1)}
    )


def preview_picks(sequence: np.ndarray, index: np.ndarray, n_previews: int) -> list[int]:
    """The `index` values of preview frames: the first (60 m) and last (10 m) frame of sequence 0,
    then max(2, n_previews) - 2 frames spread evenly over the rotating sequences (5 and up); each frame once
    (fewer picks when there are fewer frames than that)."""
    s0 = index[sequence == 0]
    picks = [int(s0[0]), int(s0[-1])]
    others = index[sequence >= 5]
    extra = max(2, n_previews) - 2
    if extra and len(others):
        picks += [int(i) for i in others[np.linspace(0, len(others) - 1, extra).round().astype(int)]]
    return list(dict.fromkeys(picks))


def flatten(seqs: list[Sequence]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Sequences as flat per-frame arrays: sequence id, frame, R (N, 3, 3), t (N, 3)."""
    return (
        np.concatenate([np.full(len(s), s.sequence) for s in seqs]),
        np.concatenate([s.frame for s in seqs]),
        np.concatenate([s.R for s in seqs]),
        np.concatenate([s.t for s in seqs]),
    )
