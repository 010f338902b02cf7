"""Lab recordings on disk: the layout a real lab session is stored in, written for the
synthetic lab sequences and read back (or read from a real recording) by `rpod lab`.

One folder per sequence (a folder of such folders also works):

    images/000000.png ...     one image per camera frame, any size with the ZED's 16:9 aspect
    masks/000000.png ...      optional: nonzero = target; else a grey-level threshold segments it
    camera.csv                frame,timestamp            (s; optional column `image` = file name,
                              default {frame:06d}.png)
    mocap.csv                 timestamp,body,x,y,z,qw,qx,qy,qz   (s, m, body -> world quaternion)

The CSV parsing and frame matching are pipeline/evaluation/lab.py's; this module does the file I/O and turns
every problem into a DataError naming the file (and line).
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.io.errors import DataError


def write_recording(folder: Path, camera: Any, mocap: Any, images: np.ndarray, masks: np.ndarray | None) -> None:
    """Write one recording in the lab layout (PNG images, optional masks, camera.csv, mocap.csv)."""
    import cv2

    (folder / "images").mkdir(parents=True, exist_ok=True)
    if masks is not None:
        (folder / "masks").mkdir(exist_ok=True)
    for k, frame in enumerate(camera["frame"].to_numpy()):
        name = f"{int(frame):06d}.png"
        if not cv2.imwrite(str(folder / "images" / name), images[k][..., ::-1]):
            raise DataError(f"could not write {folder / 'images' / name}")
        if masks is not None and not cv2.imwrite(str(folder / "masks" / name), masks[k]):
            raise DataError(f"could not write {folder / 'masks' / name}")
    camera.to_csv(folder / "camera.csv", index=False, float_format="%.6f")
    mocap.to_csv(folder / "mocap.csv", index=False, float_format="%.6f")


def recording_folders(root: Path) -> list[Path]:
    """`root` itself when it holds camera.csv, else its subfolders that do (sorted)."""
    if not root.is_dir():
        raise DataError(f"lab recording folder {root} not found")
    if (root / "camera.csv").exists():
        return [root]
    subs = sorted(d for d in root.iterdir() if d.is_dir() and (d / "camera.csv").exists())
    if not subs:
        raise DataError(f"{root} holds no lab recording (no camera.csv in it or its subfolders)")
    return subs


def read_recording(
    folder: Path,
    width: int,
    height: int,
    bodies: dict[str, str],
    match: str,
    max_gap: float,
    threshold: float,
    max_pixels: int = 1 << 25,
    empty_tolerance: float = 0.0,
) -> dict[str, Any]:
    """Load one recording: segmented images resized to width x height (uint8), frames, lab labels t, q.

    Every problem is a DataError naming the file (and line for the CSVs): files outside the folder or
    not regular, images over `max_pixels` (checked on the header, before decoding), non-finite or
    duplicated rows, a target behind the camera, more than `empty_tolerance` of frames without target.
    """
    try:
        return _read_recording(folder, width, height, bodies, match, max_gap, threshold, max_pixels, empty_tolerance)
    except ValueError as e:  # pipeline.evaluation.lab.LabDataError and friends
        raise DataError(str(e)) from None


def _read_recording(
    folder: Path,
    width: int,
    height: int,
    bodies: dict[str, str],
    match: str,
    max_gap: float,
    threshold: float,
    max_pixels: int,
    empty_tolerance: float,
) -> dict[str, Any]:
    from tqdm import tqdm

    from pipeline.evaluation.lab import check_target_pixels, image_names, match_frames

    tables = _read_tables(folder)
    frames, t, q = match_frames(
        tables["camera.csv"],
        tables["mocap.csv"],
        bodies["camera"],
        bodies["target"],
        match,
        max_gap,
        str(folder / "camera.csv"),
        str(folder / "mocap.csv"),
    )
    names = image_names(tables["camera.csv"], frames, str(folder / "camera.csv"))
    images = np.zeros((len(frames), height, width, 3), np.uint8)
    for k, name in enumerate(tqdm(names, desc=f"read {folder.name}", unit="img", leave=False)):
        images[k] = _read_image(folder, name, k, (width, height), threshold, max_pixels)
    check_target_pixels(images, empty_tolerance, str(folder))
    return {"name": folder.name, "frames": frames, "images": images, "t_lab": t, "q": q}


def _read_tables(folder: Path) -> dict[str, Any]:
    """camera.csv and mocap.csv of the recording (file name -> DataFrame), regular files inside the folder."""
    import pandas as pd

    from pipeline.evaluation.lab import resolve_inside

    tables = {}
    for name in ("camera.csv", "mocap.csv"):
        path = folder / name
        if not path.exists():
            raise DataError(f"{path} not found (a lab recording needs images/, camera.csv and mocap.csv)")
        path = resolve_inside(folder, name, str(folder))
        try:
            tables[name] = pd.read_csv(path)
        except Exception as e:
            raise DataError(f"{folder / name} is not a readable CSV ({type(e).__name__}: {e})") from None
    return tables


def _read_image(
    folder: Path, name: str, k: int, size: tuple[int, int], threshold: float, max_pixels: int
) -> np.ndarray:
    """Image `name` of camera.csv's k-th frame: its size checked on the header against `max_pixels`, its aspect
    against size (width, height) pixels, segmented (its mask, else the grey-level `threshold`) and resized to
    size (uint8 RGB)."""
    import cv2
    from PIL import Image

    from pipeline.evaluation.lab import resolve_inside
    from pipeline.images import resize, segment

    (width, height), where = size, f"(camera.csv line {k + 2})"
    path = resolve_inside(folder / "images", name, f"{folder / 'camera.csv'} line {k + 2}")
    try:
        with warnings.catch_warnings():  # the size is checked against lab.max_image_pixels just below
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(path) as header:  # reads the header only
                w, h = header.size
    except Image.DecompressionBombError as e:
        raise DataError(f"{folder / 'images' / name} is above lab.max_image_pixels ({e}) {where}") from None
    except Exception:
        raise DataError(f"{folder / 'images' / name} cannot be read as an image {where}") from None
    if w * h > max_pixels:
        raise DataError(
            f"{folder / 'images' / name} is {w}x{h} = {w * h} pixels, above lab.max_image_pixels = {max_pixels} {where}"
        )
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise DataError(f"{folder / 'images' / name} cannot be read as an image {where}")
    h, w = bgr.shape[:2]
    if abs(w / h - width / height) > 0.01 * width / height:
        raise DataError(
            f"{folder / 'images' / name} is {w}x{h}; the lab images must have the model input's "
            f"aspect {width}:{height} {where}"
        )
    return resize(segment(bgr[..., ::-1], _read_mask(folder, name, k, (w, h)), threshold), width, height)


def _read_mask(folder: Path, name: str, k: int, size: tuple[int, int]) -> np.ndarray | None:
    """masks/`name` of camera.csv's k-th frame (grey levels, nonzero = target) when the recording has masks/, its
    size (w, h) pixels that of its image; None without masks/."""
    import cv2

    from pipeline.evaluation.lab import resolve_inside

    (w, h), where = size, f"(camera.csv line {k + 2})"
    mask = None
    mpath = folder / "masks" / name
    if (folder / "masks").is_dir():
        if mpath.exists():
            mpath = resolve_inside(folder / "masks", name, f"{folder / 'camera.csv'} line {k + 2}")
        mask = cv2.imread(str(mpath), cv2.IMREAD_GRAYSCALE)
        if mask is None:
            raise DataError(f"{mpath} cannot be read as a mask {where}")
        if mask.shape != (h, w):
            raise DataError(f"{mpath} is {mask.shape[1]}x{mask.shape[0]}, its image {w}x{h} {where}")
    return mask
