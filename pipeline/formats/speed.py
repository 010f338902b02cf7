"""SPEED and SPEED+ labels and cameras (Sharma and D'Amico 2019; Park et al. 2022) in our pose convention.

Frames. Both datasets use the camera frame we use (x right, y down, z along the boresight; pixels =
K @ (x/z, y/z, 1)). `r_Vo2To_vbs_true` is the target (Tango) origin in the camera (VBS) frame, in metres:
our `t`. `q_vbs2tango_true` (SPEED+) or `q_vbs2tango` (SPEED) = (q0, q1, q2, q3), scalar first. Its
direction cosine matrix, as the datasets' own tools build it (`quat2dcm`), maps camera-frame coordinates
into target-frame coordinates, hence "vbs2tango"; the same tools project target points as
x_cam = quat2dcm(q).T @ x_target + r. quat2dcm(q).T is the Hamilton rotation matrix of the same four
numbers, i.e. the rotation of target-frame vectors into the camera frame: our `q`
(`pipeline.geometry.rotations.quat_to_matrix`). The numbers therefore carry over unchanged; we only normalise
and choose the sign with qw >= 0 (q and -q are one attitude).

camera.json (SPEED+, and what `rpod export speed` writes): `cameraMatrix` = 3x3 K in pixels, `Nu`, `Nv` =
image width and height in pixels, `distCoeffs` = OpenCV (k1, k2, p1, p2, k3), and physical `fx`, `fy`
(focal length, m), `ppx`, `ppy` (pixel pitch, m), `ccx`, `ccy` (principal point, px). SPEED ships no
camera.json; its camera is `SPEED_CAMERA` (1920 x 1200 px, f = 17.6 mm, 5.86 um pixels, centred).
Our renders have no physical sensor: the export gives them SPEED+'s 5.86 um pixel pitch (`PIXEL_PITCH`)
and fx = K's focal length in pixels times it, so fx / ppx and the field of view are exact.
Nothing here reads files: records and camera dicts come parsed from JSON, errors are ValueErrors that
name the field (the caller adds the file).
"""

from __future__ import annotations

import posixpath
from typing import Any

import numpy as np

from pipeline.geometry.camera import Intrinsics
from pipeline.geometry.labels import MAX_RANGE_M
from pipeline.geometry.rotations import UNIT_TOLERANCE, normalize_quat

POSITION_KEY = "r_Vo2To_vbs_true"
QUAT_KEYS = ("q_vbs2tango_true", "q_vbs2tango")  # SPEED+, SPEED
PIXEL_PITCH = 5.86e-6  # m per pixel: SPEED+'s sensor, given to exported cameras
DIST_LENGTHS = (4, 5, 8, 12, 14)  # the distCoeffs lengths OpenCV accepts
SPEED_CAMERA = {"Nu": 1920, "Nv": 1200, "fx": 0.0176, "fy": 0.0176, "ppx": 5.86e-6, "ppy": 5.86e-6}


def to_speed(filenames: list[str], t: np.ndarray, q: np.ndarray) -> list[dict[str, Any]]:
    """Labels as SPEED+ JSON records: `filename`, `q_vbs2tango_true` (= our q), `r_Vo2To_vbs_true` (= t, m); a
    ValueError naming the file when a q is not a unit quaternion (an all-zero one would be written as NaN)."""
    q = np.asarray(q, np.float64)
    bad = np.flatnonzero(~(np.abs(np.linalg.norm(q, axis=1) - 1) <= UNIT_TOLERANCE))
    if len(bad):
        raise ValueError(
            f"{filenames[bad[0]]}: quaternion {q[bad[0]].tolist()} is not a unit quaternion ({len(bad)} such labels)"
        )
    return [
        {"filename": str(f), QUAT_KEYS[0]: [float(v) for v in qi], POSITION_KEY: [float(v) for v in ti]}
        for f, ti, qi in zip(filenames, np.asarray(t, np.float64), normalize_quat(q))
    ]


def _vector(record: dict[str, Any], key: str, n: int, where: str) -> np.ndarray:
    raw = record[key]
    if not isinstance(raw, list) or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in raw):
        raise ValueError(f"{where}: {key} must be a list of {n} numbers, got {raw!r}")
    v = np.asarray(raw, dtype=np.float64)
    if v.shape != (n,) or not np.isfinite(v).all():
        raise ValueError(f"{where}: {key} must be {n} finite numbers, got {raw!r}")
    return v


def _record(record: Any, i: int) -> tuple[str, np.ndarray, np.ndarray]:
    where = f"record {i}"
    if not isinstance(record, dict):
        raise ValueError(f"{where}: expected an object with filename, {QUAT_KEYS[0]} and {POSITION_KEY}")
    if not isinstance(record.get("filename"), str) or not record["filename"]:
        raise ValueError(f"{where}: missing key 'filename' (the image's file name)")
    where = f"record {i} ({record['filename']})"
    name = relative_name(record["filename"], where)
    qkeys = [k for k in QUAT_KEYS if k in record]
    if not qkeys:
        raise ValueError(f"{where}: missing key '{QUAT_KEYS[0]}' (SPEED+) or '{QUAT_KEYS[1]}' (SPEED)")
    if len(qkeys) > 1:
        raise ValueError(
            f"{where}: has both '{QUAT_KEYS[0]}' (SPEED+) and '{QUAT_KEYS[1]}' (SPEED); a record gives "
            f"its attitude once"
        )
    if POSITION_KEY not in record:
        raise ValueError(f"{where}: missing key '{POSITION_KEY}'")
    qkey = qkeys[0]
    q = _vector(record, qkey, 4, where)
    if not abs(np.linalg.norm(q) - 1) <= UNIT_TOLERANCE:
        raise ValueError(f"{where}: {qkey} has norm {np.linalg.norm(q):.6g}, not a unit quaternion")
    t = _vector(record, POSITION_KEY, 3, where)
    if not t[2] > 0:
        raise ValueError(
            f"{where}: {POSITION_KEY} {t.tolist()} puts the target behind the camera or in its plane "
            f"(z <= 0; z is along the boresight)"
        )
    if not np.linalg.norm(t) <= MAX_RANGE_M:
        raise ValueError(
            f"{where}: {POSITION_KEY} {t.tolist()} puts the target more than {MAX_RANGE_M:g} m away (metres expected)"
        )
    return name, t, q


def relative_name(name: str, where: str) -> str:
    """`name` normalised (`./a.png` -> `a.png`); a ValueError when it is absolute or leaves its folder (`..`)."""
    norm = posixpath.normpath(name)
    if posixpath.isabs(norm) or (len(norm) > 1 and norm[1] == ":") or norm.split("/")[0] == "..":
        raise ValueError(f"{where}: filename must be a path inside the dataset folder, got {name!r}")
    return norm


def from_speed(records: Any) -> tuple[list[str], np.ndarray, np.ndarray]:
    """SPEED or SPEED+ JSON records -> (filenames, normalised and inside the folder; t (N, 3) m; q (N, 4) unit,
    qw >= 0), checked record by record; a ValueError names the record, its file name and the field."""
    if not isinstance(records, list) or not records:
        raise ValueError("expected a non-empty JSON list of label records")
    parsed = [_record(r, i) for i, r in enumerate(records)]
    names = [n for n, _, _ in parsed]
    dup = sorted({n for n in names if names.count(n) > 1}) if len(set(names)) < len(names) else []
    if dup:
        raise ValueError(f"filename {dup[0]!r} is labelled more than once")
    return names, np.stack([t for _, t, _ in parsed]), normalize_quat(np.stack([q for _, _, q in parsed]))


def _number(cam: dict[str, Any], key: str) -> float:
    try:
        v = float(cam[key])
    except KeyError:
        raise ValueError(f"missing key '{key}'") from None
    except (TypeError, ValueError):
        raise ValueError(f"{key} must be a number, got {cam[key]!r}") from None
    if not np.isfinite(v) or v <= 0:
        raise ValueError(f"{key} must be a positive number, got {cam[key]!r}")
    if key in ("Nu", "Nv") and not v.is_integer():
        raise ValueError(f"{key} must be a whole number of pixels, got {cam[key]!r}")
    return v


def _checked(K: Intrinsics) -> Intrinsics:
    """K when its focal lengths are at least a pixel and its principal point lies inside the image."""
    if min(K.fx, K.fy) < 1:
        raise ValueError(f"focal lengths must be at least 1 pixel, got fx={K.fx:g}, fy={K.fy:g}")
    if not (0 <= K.cx <= K.width and 0 <= K.cy <= K.height):
        raise ValueError(f"principal point ({K.cx:g}, {K.cy:g}) lies outside the {K.width}x{K.height} image")
    return K


def camera_from_json(cam: Any, size: tuple[int, int] | None = None) -> Intrinsics:
    """Intrinsics (pixels, at Nu x Nv) from a camera.json dict: `cameraMatrix` (3x3 K) when present, else
    the physical fx, fy (m) over ppx, ppy (m per pixel) with ccx, ccy or the image centre. `size` =
    (width, height) of the images stands in for missing Nu, Nv. ValueError names the missing field."""
    if not isinstance(cam, dict):
        raise ValueError("expected a JSON object")
    if size is not None and ("Nu" not in cam or "Nv" not in cam):
        cam = {"Nu": size[0], "Nv": size[1], **cam}
    w, h = int(_number(cam, "Nu")), int(_number(cam, "Nv"))
    if "cameraMatrix" in cam:
        try:
            K = Intrinsics.from_K(cam["cameraMatrix"], w, h)
        except (TypeError, ValueError) as e:
            raise ValueError(f"cameraMatrix {e}") from None
        return _checked(K)
    if not {"fx", "ppx"} <= set(cam):
        raise ValueError(
            "no camera matrix: needs 'cameraMatrix' (3x3 K in pixels) or 'fx', 'fy' (m) with 'ppx', 'ppy' (m per pixel)"
        )
    fx, fy = _number(cam, "fx") / _number(cam, "ppx"), _number(cam, "fy") / _number(cam, "ppy")
    cx = _number(cam, "ccx") if "ccx" in cam else w / 2
    return _checked(Intrinsics(w, h, fx, fy, cx, _number(cam, "ccy") if "ccy" in cam else h / 2))


def dist_from_json(cam: dict[str, Any]) -> np.ndarray:
    """OpenCV distortion coefficients (k1, k2, p1, p2[, k3, ...]) of a camera.json dict; zeros when it has
    no `distCoeffs` (a pinhole camera). ValueError when they are not 4, 5, 8, 12 or 14 finite numbers."""
    raw = cam.get("distCoeffs", [0.0] * 5)
    try:
        dist = np.asarray(raw, dtype=np.float64).ravel()
    except (TypeError, ValueError):
        dist = np.zeros(0)
    if len(dist) not in DIST_LENGTHS or not np.isfinite(dist).all():
        raise ValueError(
            f"distCoeffs must be {', '.join(map(str, DIST_LENGTHS))} finite numbers (OpenCV's "
            f"k1, k2, p1, p2[, k3, ...]), got {raw!r}"
        )
    return dist


def camera_to_json(K: Intrinsics) -> dict[str, Any]:
    """A SPEED+ camera.json dict of a pinhole camera (no lens distortion): K in pixels, and the physical
    fx, fy (m) and ppx, ppy (m per pixel) at the nominal `PIXEL_PITCH`."""
    return {
        "Nu": int(K.width),
        "Nv": int(K.height),
        "ppx": PIXEL_PITCH,
        "ppy": PIXEL_PITCH,
        "fx": float(K.fx) * PIXEL_PITCH,
        "fy": float(K.fy) * PIXEL_PITCH,
        "ccx": float(K.cx),
        "ccy": float(K.cy),
        "cameraMatrix": K.K.tolist(),
        "distCoeffs": [0.0] * 5,
    }
