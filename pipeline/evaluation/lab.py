"""The lab domain: range rescaling, mocap-to-camera timestamp matching (lab images: pipeline/images.py).

Range rescaling (pinhole model)
-------------------------------
A target of size L at range z appears s = f * L / z pixels wide in a camera of focal length f
(pixels). In the lab, the 1/`scale` mock-up (size L / scale) is seen by the ZED camera (K_zed at
1920x1080); its image is resized to the synthetic size (1920 -> 480 at the reference 480x270),
which multiplies the focal length by 480 / 1920: f_lab_eff = 1400.41 / 4 = 350.10 px. The
synthetic camera sees the full-size target (L) with f_syn = 640 px (K_blender at 480x270).
Equal apparent size,

    f_lab_eff * (L / scale) / z_lab = f_syn * L / z_syn,

gives z_syn = z_lab * scale * f_syn / f_lab_eff = z_lab * 9 * 640 / 350.10 = 16.45 * z_lab
(so 3.122 m in the lab is 51.36 m in the synthetic scene). The factor uses the horizontal focal
lengths; it does not depend on the image size the two cameras are compared at, because both K
scale alike with the image. With the default square-pixel K_blender (fy = fx) the match
holds vertically too; with the paper's printed fy = 360 the synthetic pixels are not square
(fx / fy = 16 / 9) while the ZED's are, so the vertical apparent size differs by fy_syn / fx_syn =
9 / 16. Either way we follow the paper and match the horizontal size. The paper's own table uses
cx_zed / cx_blender = 956.29 / 240 for the resize (`paper_lab_factor`), 0.39% off the exact 4. The lateral label
coordinates are chosen so that the target's centre lands on the same pixel in both images
(`lab_to_synthetic_position`).

Motion capture
--------------
`mocap.csv` has one row per body and sample (timestamp s, body, x, y, z m, qw, qx, qy, qz) in the
mocap world frame, 120 Hz; `camera.csv` has (frame, timestamp s) at 30 fps on the same clock. A
body's quaternion rotates body-frame vectors into the world frame. The camera body's frame must be
the optical frame (OpenCV: x right, y down, z forward; a hand-eye calibration folded into the
rigid body) and the target body's frame the target (mesh) frame. The lab's relative position
`d = p_camera - p_target` is expressed in the world frame; our label is the target origin in the
camera frame, t = R_cam^T (p_target - p_camera) = -R_cam^T d, and the label attitude (target
frame -> camera frame) is R = R_cam^T R_target, i.e. q = conj(q_cam) * q_target.
"""

from __future__ import annotations

import os
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation, Slerp

from pipeline.geometry.camera import Intrinsics
from pipeline.geometry.labels import QUAT
from pipeline.geometry.rotations import UNIT_TOLERANCE, matrix_to_quat, normalize_quat, quat_to_matrix

Match = Literal["nearest", "interpolate"]
CAMERA_COLUMNS = ["frame", "timestamp"]
MOCAP_COLUMNS = ["timestamp", "body", "x", "y", "z", *QUAT]


class LabDataError(ValueError):
    """Bad lab recording; the message names the file and the line."""


# ----------------------------------------------------------------------------- range rescaling
def lab_to_synthetic_factor(K_syn: Intrinsics, K_lab: Intrinsics, scale: float) -> float:
    """z_syn / z_lab for equal horizontal apparent size (see the module docstring).

    K_lab is first resized to K_syn's image width (the lab image is resized to the model input).
    """
    if scale <= 0:
        raise ValueError(f"mock-up scale must be positive, got {scale}")
    f_lab_eff = K_lab.fx * K_syn.width / K_lab.width
    return scale * K_syn.fx / f_lab_eff


def paper_lab_factor(K_syn: Intrinsics, K_lab: Intrinsics, scale: float) -> float:
    """z_syn / z_lab as the paper's representative-range table computes it: the 1920 -> 480 resize
    taken as cx_lab / cx_syn (956.29 / 240 = 3.9845) instead of the exact width ratio 4, so its
    synthetic ranges are 4 / 3.9845 = 1.0039x (0.39%) shorter than `lab_to_synthetic_factor`'s."""
    if scale <= 0:
        raise ValueError(f"mock-up scale must be positive, got {scale}")
    return scale * K_syn.fx / K_lab.fx * K_lab.cx / K_syn.cx


def lab_to_synthetic_position(t_lab: np.ndarray, K_syn: Intrinsics, K_lab: Intrinsics, scale: float) -> np.ndarray:
    """Lab camera-frame positions (..., 3) of the mock-up -> equivalent synthetic positions (m).

    z is multiplied by `lab_to_synthetic_factor`; x and y are set so the target origin projects to
    the same pixel of the lab image resized to K_syn's size as in the synthetic image.
    """
    t = np.asarray(t_lab, dtype=np.float64)
    k = lab_to_synthetic_factor(K_syn, K_lab, scale)
    Kl = K_lab.scaled(K_syn.width, K_syn.height)
    z_syn = k * t[..., 2]
    u = Kl.fx * t[..., 0] / t[..., 2] + Kl.cx
    v = Kl.fy * t[..., 1] / t[..., 2] + Kl.cy
    return np.stack([(u - K_syn.cx) * z_syn / K_syn.fx, (v - K_syn.cy) * z_syn / K_syn.fy, z_syn], -1)


# ----------------------------------------------------------------------------- poses and matching
def relative_pose(
    p_cam: np.ndarray, q_cam: np.ndarray, p_tgt: np.ndarray, q_tgt: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """World poses of camera and target bodies -> label (t in the camera frame (m), q target->camera)."""
    R_cam = quat_to_matrix(q_cam)
    R_tgt = quat_to_matrix(q_tgt)
    d = np.asarray(p_cam, np.float64) - np.asarray(p_tgt, np.float64)  # world frame
    t = -np.einsum("...ji,...j->...i", R_cam, d)
    q = matrix_to_quat(np.swapaxes(R_cam, -1, -2) @ R_tgt)
    return t, q


@dataclass(frozen=True)
class Track:
    """One mocap body: times (M,) s strictly increasing, positions (M, 3) m, quats (M, 4) body->world."""

    times: np.ndarray
    positions: np.ndarray
    quats: np.ndarray


def _line(i: int) -> int:
    """CSV line of data row i (line 1 is the header)."""
    return int(i) + 2


def _numeric(df: pd.DataFrame, cols: list[str], source: str) -> pd.DataFrame:
    out = df.copy()
    for c in cols:
        vals = pd.to_numeric(out[c], errors="coerce")
        bad = np.flatnonzero(~np.isfinite(vals.to_numpy(np.float64)))
        if len(bad):
            what = "is not a number" if np.isnan(vals.iloc[bad[0]]) else "is not finite"
            raise LabDataError(f"{source} line {_line(bad[0])}: column {c!r} {what} ({df[c].iloc[bad[0]]!r})")
        out[c] = vals.astype(np.float64)
    return out


def _require_columns(df: pd.DataFrame, cols: list[str], source: str) -> None:
    missing = [c for c in cols if c not in df.columns]
    if missing:
        raise LabDataError(f"{source}: missing column(s) {missing}; expected {cols}")
    if len(df) == 0:
        raise LabDataError(f"{source}: no data rows")


def parse_camera(df: pd.DataFrame, source: str = "camera.csv") -> tuple[np.ndarray, np.ndarray]:
    """camera.csv rows -> (frame numbers (N,) int, timestamps (N,) s), checked to increase."""
    _require_columns(df, CAMERA_COLUMNS, source)
    df = _numeric(df, CAMERA_COLUMNS, source)
    t = df["timestamp"].to_numpy()
    bad = np.flatnonzero(np.diff(t) <= 0)
    if len(bad):
        i = bad[0] + 1
        raise LabDataError(f"{source} line {_line(i)}: timestamp {t[i]} is not after the previous one ({t[i - 1]})")
    frames = df["frame"].to_numpy().astype(np.int64)
    _, first, counts = np.unique(frames, return_index=True, return_counts=True)
    if (counts > 1).any():
        i = int(first[np.argmax(counts > 1)])
        again = int(np.flatnonzero(frames == frames[i])[1])
        raise LabDataError(f"{source} line {_line(again)}: frame {frames[i]} already appears on line {_line(i)}")
    return frames, t


def parse_mocap(df: pd.DataFrame, bodies: list[str], source: str = "mocap.csv") -> dict[str, Track]:
    """mocap.csv rows -> one Track per requested body; rows of a body must be in time order."""
    _require_columns(df, MOCAP_COLUMNS, source)
    df = _numeric(df, [c for c in MOCAP_COLUMNS if c != "body"], source)
    names = df["body"].astype(str)
    tracks = {}
    for body in bodies:
        rows = np.flatnonzero((names == body).to_numpy())
        if len(rows) == 0:
            raise LabDataError(f"{source}: no rows for body {body!r} (bodies present: {sorted(set(names))})")
        t = df["timestamp"].to_numpy()[rows]
        bad = np.flatnonzero(np.diff(t) <= 0)
        if len(bad):
            i = rows[bad[0] + 1]
            raise LabDataError(
                f"{source} line {_line(i)}: body {body!r} timestamp {t[bad[0] + 1]} is not after "
                f"its previous sample ({t[bad[0]]}); mocap rows must be in time order"
            )
        q = df[QUAT].to_numpy()[rows]
        norm = np.linalg.norm(q, axis=1)
        off = np.flatnonzero(np.abs(norm - 1) > UNIT_TOLERANCE)
        if len(off):
            raise LabDataError(
                f"{source} line {_line(rows[off[0]])}: body {body!r} has a quaternion of norm "
                f"{norm[off[0]]:.6g}, not a unit quaternion"
            )
        tracks[body] = Track(t, df[["x", "y", "z"]].to_numpy()[rows], normalize_quat(q))
    return tracks


def sample_track(
    track: Track, times: np.ndarray, mode: Match, max_gap: float, body: str = "body", source: str = "camera.csv"
) -> tuple[np.ndarray, np.ndarray]:
    """A body's pose at each camera timestamp: (positions (N, 3), quats (N, 4)).

    The gap of a frame is the time to its nearest mocap sample; a frame whose gap exceeds
    `max_gap` (s) is an error naming its line in `source`. "nearest" takes that sample;
    "interpolate" interpolates linearly (position) and by slerp (attitude) between the two
    samples around the frame, or takes the nearest one past either end of the track.
    """
    if mode not in ("nearest", "interpolate"):
        raise ValueError(f"unknown match mode {mode!r}; choose nearest or interpolate")
    times = np.asarray(times, np.float64)
    tt = track.times
    right = np.clip(np.searchsorted(tt, times), 0, len(tt) - 1)
    left = np.clip(right - 1, 0, len(tt) - 1)
    nearest = np.where(np.abs(tt[left] - times) <= np.abs(tt[right] - times), left, right)
    gap = np.abs(tt[nearest] - times)
    bad = np.flatnonzero(gap > max_gap)
    if len(bad):
        i = bad[0]
        raise LabDataError(
            f"{source} line {_line(i)}: no mocap sample of body {body!r} within {max_gap} s of "
            f"timestamp {times[i]} (nearest is {gap[i]:.4f} s away)"
        )
    pos, quat = track.positions[nearest].copy(), track.quats[nearest].copy()
    if mode == "interpolate" and len(tt) > 1:
        inside = (times >= tt[0]) & (times <= tt[-1])
        if inside.any():
            ti = times[inside]
            pos[inside] = np.stack([np.interp(ti, tt, track.positions[:, k]) for k in range(3)], -1)
            rot = Slerp(tt, Rotation.from_quat(track.quats, scalar_first=True))(ti)
            quat[inside] = normalize_quat(rot.as_quat(scalar_first=True))
    return pos, quat


def match_frames(
    camera: pd.DataFrame,
    mocap: pd.DataFrame,
    camera_body: str,
    target_body: str,
    mode: Match,
    max_gap: float,
    camera_source: str = "camera.csv",
    mocap_source: str = "mocap.csv",
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """camera.csv + mocap.csv tables -> (frame numbers (N,), labels t (N, 3) m, q (N, 4))."""
    frames, times = parse_camera(camera, camera_source)
    tracks = parse_mocap(mocap, [camera_body, target_body], mocap_source)
    p_c, q_c = sample_track(tracks[camera_body], times, mode, max_gap, camera_body, camera_source)
    p_t, q_t = sample_track(tracks[target_body], times, mode, max_gap, target_body, camera_source)
    t, q = relative_pose(p_c, q_c, p_t, q_t)
    behind = np.flatnonzero(t[:, 2] <= 0)
    if len(behind):
        i = behind[0]
        raise LabDataError(
            f"{camera_source} line {_line(i)}: the target is behind the camera (z = {t[i, 2]:.3f} m "
            f"in the camera frame); check the mocap bodies and their axes"
        )
    return frames, t, q


def image_names(camera: pd.DataFrame, frames: np.ndarray, source: str = "camera.csv") -> list[str]:
    """The image file name of each camera.csv row: column `image`, else `{frame:06d}.png`."""
    if "image" not in camera.columns:
        return [f"{int(f):06d}.png" for f in frames]
    names = camera["image"].tolist()
    for i, name in enumerate(names):
        if not isinstance(name, str) or not name.strip():
            raise LabDataError(f"{source} line {_line(i)}: column 'image' is empty or not a file name ({name!r})")
    return names


def resolve_inside(folder: Path, name: str, source: str) -> Path:
    """`folder / name` as a regular file inside `folder` (symlinks resolved): no absolute paths, no `..`
    escapes, no FIFOs or devices (which would hang or leak the reader). `source` names the CSV line."""
    base = Path(folder).resolve()
    path = (base / name).resolve()
    if Path(name).is_absolute() or not path.is_relative_to(base):
        raise LabDataError(f"{source}: image {name!r} lies outside the recording folder {folder}")
    try:
        mode = os.stat(path).st_mode
    except OSError:
        raise LabDataError(f"{source}: {Path(folder) / name} not found") from None
    if not stat.S_ISREG(mode):
        raise LabDataError(f"{source}: {Path(folder) / name} is not a regular file")
    return path


def check_target_pixels(images: np.ndarray, tolerance: float, source: str) -> None:
    """Refuse a recording where more than `tolerance` (fraction) of the segmented frames (N, H, W, 3)
    have no target pixel: all-black frames mean a wrong threshold, mask or exposure."""
    empty = np.flatnonzero(images.reshape(len(images), -1).max(axis=1) == 0)
    if len(empty) > tolerance * len(images):
        raise LabDataError(
            f"{source}: {len(empty)} of {len(images)} frames have no target pixels after segmentation "
            f"(first: frame index {empty[0]}), above the tolerance of {tolerance:.0%}; check "
            f"lab.segment_threshold or the masks"
        )


# ----------------------------------------------------------------------------- synthetic recordings
# Mocap world frame of the synthetic lab: z up; the camera looks along world +x from behind the
# target: camera x (right) = world -y, camera y (down) = world -z, camera z (forward) = world +x.
R_WORLD_CAM = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


@dataclass(frozen=True)
class LabRecording:
    """A lab sequence as tables in the real-data layout plus the exact labels at frame times."""

    camera: pd.DataFrame  # frame, timestamp
    mocap: pd.DataFrame  # timestamp, body, x, y, z, qw, qx, qy, qz
    t: np.ndarray  # (N, 3) exact label at each frame time, camera frame, lab metres
    q: np.ndarray  # (N, 4) exact label attitude, target -> camera


def synthetic_recording(
    z_start: float,
    z_end: float,
    n_frames: int,
    fps: float,
    mocap_hz: float,
    q_label: np.ndarray,
    lateral: tuple[float, float] = (0.0, 0.0),
    target_position: tuple[float, float, float] = (1.5, 0.4, 1.2),
    clock_offset: float = 0.0013,
    camera_body: str = "camera",
    target_body: str = "target",
) -> LabRecording:
    """A straight approach along the optical axis from z_start to z_end (lab metres) as mocap data.

    The target body sits still at `target_position` (world, m) with the attitude that gives the
    label attitude `q_label`; the camera moves at constant speed (also before the first and after
    the last frame, so interpolation is exact) with a fixed lateral offset
    (x, y in the camera frame, m). Camera frames are taken at `fps` from time `clock_offset`;
    mocap samples at `mocap_hz` cover the whole recording.
    """
    if n_frames < 1:
        raise ValueError(f"a lab sequence needs at least one frame, got {n_frames}")
    duration = (n_frames - 1) / fps
    frame_t = clock_offset + np.arange(n_frames) / fps
    mocap_t = np.arange(0.0, frame_t[-1] + 2.0 / mocap_hz, 1.0 / mocap_hz)
    p_tgt = np.asarray(target_position, np.float64)
    R_tgt = R_WORLD_CAM @ quat_to_matrix(q_label)
    q_tgt = matrix_to_quat(R_tgt)
    q_cam = matrix_to_quat(R_WORLD_CAM)

    def t_label(time: np.ndarray) -> np.ndarray:
        s = (time - clock_offset) / duration if duration > 0 else np.zeros_like(time)  # moving throughout
        z = z_start + (z_end - z_start) * s
        return np.stack([np.full_like(z, lateral[0]), np.full_like(z, lateral[1]), z], -1)

    def p_cam(time: np.ndarray) -> np.ndarray:  # t = R_cam^T (p_tgt - p_cam)
        return p_tgt - t_label(time) @ R_WORLD_CAM.T

    rows = []
    for body, pos, q in (
        (camera_body, p_cam(mocap_t), np.tile(q_cam, (len(mocap_t), 1))),
        (target_body, np.tile(p_tgt, (len(mocap_t), 1)), np.tile(q_tgt, (len(mocap_t), 1))),
    ):
        rows.append(
            pd.DataFrame(
                {
                    "timestamp": mocap_t,
                    "body": body,
                    "x": pos[:, 0],
                    "y": pos[:, 1],
                    "z": pos[:, 2],
                    **{c: q[:, k] for k, c in enumerate(QUAT)},
                }
            )
        )
    mocap = pd.concat(rows).sort_values("timestamp", kind="stable").reset_index(drop=True)
    camera = pd.DataFrame({"frame": np.arange(n_frames), "timestamp": frame_t})
    return LabRecording(camera, mocap, t_label(frame_t), np.tile(normalize_quat(q_label), (n_frames, 1)))


def loader_errors(recs: list[dict[str, Any]], truth: list[dict[str, Any]]) -> dict[str, dict[str, float]]:
    """Per rendered recording in `truth`: the largest position (m) and attitude (deg) error of the
    loader's labels (`recs`, by name) against the exact poses the images were rendered at."""
    from pipeline.pose.metrics import attitude_error_deg

    out = {}
    for tr in truth:
        rec = next(x for x in recs if x["name"] == tr["name"])
        out[tr["name"]] = {
            "position_max_m": float(np.abs(rec["t_lab"] - tr["t_lab"]).max()),
            "attitude_max_deg": float(attitude_error_deg(rec["q"], tr["q"]).max()),
        }
    return out


def chain_sequences(
    recs: list[dict[str, Any]],
    K_syn: Intrinsics,
    K_lab: Intrinsics,
    scale: float,
    p_start: float,
    length: int,
    seed: int,
) -> tuple[list[Any], list[dict[str, Any]]]:
    """Loaded recordings as safety-chain `Sequence`s (targets: synthetic-frame position in metres, then
    the 6-D rotation; attack schedule seeded with the "lab.schedule" stream of `seed`, pipeline/seeds.py) and their
    range-table rows."""
    from pipeline.attacks.schedule import attack_schedule
    from pipeline.evaluation.sequences import Sequence
    from pipeline.geometry.rotations import quat_to_6d
    from pipeline.seeds import seed_for

    sequences, ranges = [], []
    for i, rec in enumerate(recs):
        t_syn = lab_to_synthetic_position(rec["t_lab"], K_syn, K_lab, scale)
        targets = np.concatenate([t_syn, quat_to_6d(rec["q"])], 1).astype(np.float32)
        sequences.append(
            Sequence(
                name=rec["name"],
                images=rec["images"],
                targets=targets,
                attacked=attack_schedule(len(targets), p_start, length, seed_for(seed, "lab.schedule", i)),
            )
        )
        zl = rec["t_lab"][:, 2]
        ranges.append(
            {
                "sequence": rec["name"],
                "frames": len(zl),
                "lab z start (m)": float(zl[0]),
                "lab z end (m)": float(zl[-1]),
                "synthetic z start (m)": float(t_syn[0, 2]),
                "synthetic z end (m)": float(t_syn[-1, 2]),
            }
        )
    return sequences, ranges
