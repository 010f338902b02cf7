"""The defended chain over a sequence of images (`Chain.track`, `rpod predict --motion`): per frame the
trusted estimate, its protection level and whether the guidance may fly on it.

The per-image chain (rpodguard/api.py) judges each image alone. With the chaser's own motion per frame,
the defense of pipeline/defense/fusion.py runs over the sequence as onboard: the motion filter
(position moved by the commanded displacements, a gate and a sequential test on its innovations)
fused with the detector, as calibrated by `rpod calibrate` (FOLDER/defense.json: its noise model,
thresholds and settings; pipeline/formats/defense.py, read with the chain by pipeline/formats/chain.py). Frames
(pipeline/geometry/trajectories.py):
world axes centred on the target; `rel` is the target's position relative to the chaser camera (m).
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.io.errors import DataError

MOTION_COLUMNS = ("u_x", "u_y", "u_z", *(f"c{j}" for j in range(9)))
"""A motion file's columns: the commanded displacement of rel since the previous frame (world, m; the
first row's is unused) and the camera attitude c0..c8 (camera -> world rotation, row-major)."""
MAX_DISPLACEMENT_M = 1000.0  # m: a commanded displacement between two frames above this along an axis is refused


@dataclass(frozen=True)
class Track:
    """The defended chain over N frames in order (row k: image k). trusted (N, 3): the trusted estimate
    of rel (world frame, m; NaN before the filter starts); pl (N,): its protection level (m; inf where
    it bounds nothing); available (N,) bool: the guidance may fly on it (not holding, PL <= the alert
    limit at the trusted estimate's range); flag (N,) bool: a check flagged the frame; mode (N,): track,
    coast or hold; prediction: the per-image chain's output (camera-frame pose, detector probability)."""

    trusted: np.ndarray
    pl: np.ndarray
    available: np.ndarray
    flag: np.ndarray
    mode: np.ndarray
    prediction: Any

    def records(self) -> list[dict[str, Any]]:
        """One JSON-ready dict per frame (null where there is no trusted estimate or no finite PL)."""

        def finite(v: np.ndarray) -> Any:
            return v.tolist() if np.isfinite(v).all() else None

        return [
            {
                "image": name,
                "trusted_rel_m": finite(self.trusted[k]),
                "pl_m": finite(self.pl[k]),
                "available": bool(self.available[k]),
                "flag": bool(self.flag[k]),
                "mode": str(self.mode[k]),
            }
            for k, name in enumerate(self.prediction.sources)
        ]


def track(
    chain: Any, images: Any, commands: np.ndarray, attitudes: np.ndarray, batch_size: int = 64, camera: Any = None
) -> Track:
    """The defended chain over `images` in time order (see rpodguard.api.Chain.predict for what
    images may be), with the chaser's `commands` (N, 3; world, m: the commanded displacement of rel
    since the previous frame, row 0 unused) and camera `attitudes` (N, 3, 3; camera -> world); `camera` the
    images' camera K (checked as in Chain.predict)."""
    from pipeline.defense.fusion import run_defense
    from pipeline.defense.integrity import alert_limit

    defended = chain.safety.defended
    if defended is None:
        raise DataError(
            f"{chain.files[2]} not found (`rpod calibrate` writes a run's defense: the chain's checks and "
            f"their thresholds)"
        )
    pred = chain.predict(images, batch_size, camera=camera)
    n = len(pred)
    commands, attitudes = np.asarray(commands, np.float64), np.asarray(attitudes, np.float64)
    if commands.shape != (n, 3) or attitudes.shape != (n, 3, 3):
        raise ValueError(
            f"track needs commands (N, 3) and camera attitudes (N, 3, 3) for the N = {n} images, got "
            f"{commands.shape} and {attitudes.shape}"
        )
    if not (np.isfinite(commands).all() and np.isfinite(attitudes).all()):
        raise ValueError("track: commands and camera attitudes must be finite")
    R_pred = _rotations(pred.rotation_6d)
    trace = run_defense(
        defended.settings,
        defended.motion,
        defended.noise,
        pred.position,
        pred.attack_probability,
        attitudes,
        commands,
        R_pred,
        partial(alert_limit, settings=defended.alert),
    )
    return Track(trace.trusted, trace.pl, trace.available, trace.flag, trace.mode, pred)


def _rotations(sixd: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations of (N, 6) 6-D rotations; NaN rows (no target in view) stay NaN."""
    from pipeline.geometry.rotations import sixd_to_matrix

    out = np.full((len(sixd), 3, 3), np.nan)
    seen = np.isfinite(sixd).all(axis=1)
    if seen.any():
        out[seen] = sixd_to_matrix(sixd[seen])
    return out


def read_motion(path: Path | str, frames: int) -> tuple[np.ndarray, np.ndarray]:
    """(commands (N, 3), camera attitudes (N, 3, 3)) from a CSV file with a header naming
        `MOTION_COLUMNS` and one row per frame; a missing file, a missing column, a row count other than
        `frames`, a non-number, a camera matrix that is not a rotation (a mirror, determinant -1, included), a
    displacement over MAX_DISPLACEMENT_M or a file that is not a regular one (a FIFO) is a DataError naming the
    file; a UTF-8 byte-order mark is skipped."""
    from pipeline.io.files import open_regular

    path = Path(path)
    if not path.exists():
        raise DataError(f"{path} not found (a motion CSV with columns {', '.join(MOTION_COLUMNS)})")
    with open_regular(path, "r", "motion CSV", newline="", encoding="utf-8-sig") as f:  # a BOM is not part of u_x
        rows = list(csv.DictReader(f))
    missing = [c for c in MOTION_COLUMNS if not rows or c not in rows[0]]
    if missing:
        raise DataError(f"{path} lacks the column(s) {', '.join(missing)} (one row per image, a header line)")
    if len(rows) != frames:
        raise DataError(f"{path} has {len(rows)} rows for {frames} images (one row per image, in order)")
    try:
        values = np.array([[float(r[c]) for c in MOTION_COLUMNS] for r in rows])
    except ValueError as e:
        raise DataError(f"{path}: {e}") from None
    camera = values[:, 3:].reshape(-1, 3, 3)
    if not np.isfinite(values).all() or not np.allclose(camera @ np.swapaxes(camera, 1, 2), np.eye(3), atol=1e-4):
        raise DataError(f"{path}: every value must be finite and c0..c8 a rotation matrix (row-major) per row")
    mirrored = np.flatnonzero(np.linalg.det(camera) < 0)
    if len(mirrored):
        raise DataError(
            f"{path}: c0..c8 of data row {mirrored[0] + 1} is a mirror (determinant -1), not a rotation "
            f"({len(mirrored)} such rows)"
        )
    far = np.flatnonzero(np.abs(values[1:, :3]).max(axis=1) > MAX_DISPLACEMENT_M) + 1  # row 0 is unused
    if len(far):
        raise DataError(
            f"{path}: data row {far[0] + 1} commands a displacement of "
            f"{', '.join(f'{v:.3g}' for v in values[far[0], :3])} m between two frames (more than "
            f"{MAX_DISPLACEMENT_M:g} m along an axis; u_x, u_y, u_z are metres)"
        )
    return values[:, :3], camera
