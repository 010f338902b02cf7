"""SPEED / SPEED+ folders on disk (the label and camera fields and the frame conventions are
pipeline/formats/speed.py's): label files, camera.json and images read, and a labelled image set
written as a SPEED+ folder (`write_speed`). Every problem is a DataError naming the file.

Layouts: SPEED+: FOLDER/camera.json, FOLDER/synthetic/{train,validation}.json (test.json: our older
exports), images <folder of the JSON>/images/<filename>. SPEED: FOLDER/train.json and FOLDER/test.json, images
FOLDER/images/<train|test>/<filename>; FOLDER/camera.json if present, else SPEED's published camera.
"""

from __future__ import annotations

import hashlib
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.geometry.labels import POSITION, QUAT
from pipeline.io.atomic import atomic_dir, file_hash, read_json, write_json
from pipeline.io.errors import DataError
from pipeline.io.files import check_regular

TRAIN = ("synthetic/train.json", "train.json")  # training label files, the first found is read
TEST = ("synthetic/validation.json", "synthetic/test.json", "test.json")  # SPEED+'s, older exports', SPEED's
EXPORT_DIR = "synthetic"  # SPEED+'s domain folder of synthetic images


def read_labels(path: Path) -> tuple[list[str], np.ndarray, np.ndarray]:
    """(filenames, t (N, 3) m, q (N, 4)) of a SPEED/SPEED+ label file; one DataError naming file and field."""
    from pipeline.formats.speed import from_speed

    try:
        return from_speed(read_json(path))
    except ValueError as e:
        raise DataError(f"{path}: {e}") from None


def read_camera(folder: Path, speed_layout: bool) -> tuple[Any, np.ndarray]:
    """(pipeline.geometry.camera.Intrinsics, OpenCV distCoeffs) of FOLDER/camera.json (SPEED's published
    camera, no distortion, when a SPEED folder has none)."""
    from pipeline.formats.speed import SPEED_CAMERA, camera_from_json, dist_from_json

    path = folder / "camera.json"
    if not path.exists() and speed_layout:  # a FIFO exists: read_json refuses it
        print(f"{path} not found: using SPEED's published camera {SPEED_CAMERA}")
        return camera_from_json(SPEED_CAMERA), dist_from_json(SPEED_CAMERA)
    try:
        cam = read_json(path)
        return camera_from_json(cam), dist_from_json(cam)
    except ValueError as e:
        raise DataError(f"{path}: {e}") from None


def image_path(label_file: Path, name: str) -> Path:
    """SPEED+: <json folder>/images/<name>; SPEED: <json folder>/images/<json stem>/<name>."""
    plus = label_file.parent / "images" / name
    return plus if plus.is_file() else label_file.parent / "images" / label_file.stem / name


def read_image(path: Path, size: tuple[int, int], cam: Any, dist: np.ndarray) -> tuple[np.ndarray, bool]:
    """(uint8 RGB (H, W, 3) at `size` (W, H), whether the file is grayscale) of an image file taken by the
    camera `cam` (Intrinsics at Nu x Nv pixels, which the file must have) with OpenCV distortion `dist`:
    undistorted to the pinhole camera `cam` (cv2.undistort) before resizing, so its K is cam.scaled(W, H);
    a grayscale file is copied into the three channels. JPEGs are decoded at 1/2, 1/4 or 1/8 size when that
    still exceeds `size` (faster, same pixels; K scaled to match)."""
    import cv2

    source_size = (cam.width, cam.height)
    header, mode = image_header(path)
    if header != tuple(source_size):
        raise DataError(
            f"{path}: image is {header[0]}x{header[1]} pixels but camera.json gives Nu x Nv = "
            f"{source_size[0]}x{source_size[1]}"
        )
    reduce = max([r for r in (2, 4, 8) if source_size[0] / r >= size[0] and source_size[1] / r >= size[1]], default=1)
    flag = {
        1: cv2.IMREAD_COLOR,
        2: cv2.IMREAD_REDUCED_COLOR_2,
        4: cv2.IMREAD_REDUCED_COLOR_4,
        8: cv2.IMREAD_REDUCED_COLOR_8,
    }[reduce]
    img = cv2.imread(str(path), flag)  # image_header checked it is a regular file
    if img is None:
        raise DataError(f"{path}: not a readable image (named by its label file)")
    expect = (math.ceil(source_size[1] / reduce), math.ceil(source_size[0] / reduce))
    if img.shape[:2] != expect:
        raise DataError(
            f"{path}: image is {img.shape[1] * reduce}x{img.shape[0] * reduce} pixels but camera.json "
            f"gives Nu x Nv = {source_size[0]}x{source_size[1]}"
        )
    if np.any(dist):
        s = 1 / reduce  # pixel centres: u_reduced = (u + 0.5) * s - 0.5
        K = np.array([[cam.fx * s, 0, (cam.cx + 0.5) * s - 0.5], [0, cam.fy * s, (cam.cy + 0.5) * s - 0.5], [0, 0, 1]])
        img = cv2.undistort(img, K, dist)
    return cv2.resize(img, size, interpolation=cv2.INTER_AREA)[..., ::-1], mode in GRAY_MODES


GRAY_MODES = ("1", "L", "LA", "I", "I;16", "F")  # Pillow modes of single-channel images


def image_header(path: Path) -> tuple[tuple[int, int], str]:
    """((width, height) in pixels, Pillow mode) from the image file's header (nothing decoded); a DataError
    naming the file."""
    from PIL import Image, UnidentifiedImageError

    try:
        check_regular(path, "image")  # missing, or a FIFO that would block: one line naming it
    except DataError as e:
        raise DataError(f"{e} (named by its label file)") from None
    try:
        with Image.open(path) as im:
            return im.size, im.mode
    except (UnidentifiedImageError, Image.DecompressionBombError, OSError) as e:
        raise DataError(f"{path}: not a readable image (named by its label file): {e}") from None


def check_source(folder: Path, label_files: list[Path], images: list[Path], n_train: int) -> str:
    """The sha256 of a SPEED folder's content (`source_digest`: its label files, camera.json and images, by name
    and bytes), once every label file and image resolves (symbolic links followed) inside `folder` and no test
    image (`images[n_train:]`) is a training image, by path (a link to it) or by content (a byte-identical
    copy); a DataError naming the file otherwise."""
    root = folder.resolve()
    for path in [*label_files, *images]:
        real = path.resolve()
        if not real.is_relative_to(root):
            raise DataError(
                f"{path} resolves to {real}, outside the dataset folder {folder} (render.source); copy the file into it"
            )
    hashes = [file_hash(p, 64) for p in images]
    by_hash, by_file = dict(zip(hashes[:n_train], images[:n_train])), {p.resolve(): p for p in images[:n_train]}
    leaks = [
        (p, by_file.get(p.resolve()) or by_hash[h])
        for p, h in zip(images[n_train:], hashes[n_train:])
        if p.resolve() in by_file or h in by_hash
    ]
    if leaks:
        raise DataError(
            f"test image {leaks[0][0]} is the training image {leaks[0][1]} (a link to it or a "
            f"byte-identical copy; {len(leaks)} such images): a test image must never be trained on"
        )
    return source_digest(folder, label_files, images, hashes)


def source_digest(folder: Path, label_files: list[Path], images: list[Path], hashes: list[str] | None = None) -> str:
    """sha256 (hex) of what a SPEED import reads: the label files, FOLDER/camera.json when there is one and the
    images (their sha256 in `hashes` when known), each by its name relative to `folder` and its bytes, in order;
    the same wherever the folder lies."""
    camera = [folder / "camera.json"] if (folder / "camera.json").exists() else []
    files = [*label_files, *camera, *images]
    shas = [file_hash(p, 64) for p in [*label_files, *camera]] + (hashes or [file_hash(p, 64) for p in images])
    h = hashlib.sha256()
    for path, sha in zip(files, shas):
        h.update(f"{path.relative_to(folder).as_posix()}\0{sha}\n".encode())
    return h.hexdigest()


def source_problem(meta: dict[str, Any], filenames: list[str]) -> str | None:
    """What differs between an import's render folder (its meta.json `source`, `filenames` its poses' `filename`
    column) and the SPEED folder it came from, now: None when they agree or the folder is gone (the import
    holds the images itself)."""
    source = meta.get("source") or {}
    folder = Path(source.get("folder", ""))
    if "sha256" not in source or not folder.is_dir():
        return None
    changed = f"render.source {folder} changed since `rpod render` imported it"
    try:
        now = source_digest(
            folder, [folder / source["train"], folder / source["test"]], [folder / f for f in filenames]
        )
    except DataError as e:
        return f"{changed} ({e}); re-run `rpod render`"
    if now == source["sha256"]:
        return None
    return (
        f"{changed} (sha256 of its label files, camera.json and images {now[:16]}, imported "
        f"{source['sha256'][:16]}); re-run `rpod render`"
    )


MARKER = ".rpodguard-export.json"  # written inside every export: the files it wrote (so a rerun may replace them)
MARKER_FORMAT = "rpodguard-export/2"  # /2: each file with its sha256 (a rerun refuses edited files)


SPLIT_FILES = {"train": "train.json", "test": "validation.json"}  # our split -> SPEED+'s label file
IMAGE_FORMATS = {"png": "png", "jpeg-gray": "jpg"}  # format -> file extension: lossless RGB; grayscale JPEG as SPEED+
JPEG_QUALITY = 95


def write_speed(
    out: Path, images: Any, labels: Any, K: Any, image_format: str = "png", overwrite: bool = False
) -> None:
    """Write the labelled images as a SPEED+ folder `out` (camera.json, synthetic/train.json, the test split
    as synthetic/validation.json, synthetic/images/imgNNNNNN.png or .jpg, NNNNNN = label index + 1, and
    MARKER), atomically. `image_format`: "png" keeps every pixel; "jpeg-gray" writes grayscale JPEGs
    (quality JPEG_QUALITY) as SPEED+ does. An existing `out` is replaced only when it is empty or holds
    nothing but an earlier export's files, unchanged (its MARKER lists them with their sha256; `overwrite`
    replaces edited ones too); a symbolic link `out` is followed (its target is written); files 0644,
    folders 0755."""
    from pipeline.formats.speed import camera_to_json, to_speed
    from pipeline.io.atomic import followed, remove_stale_temps

    if image_format not in IMAGE_FORMATS:
        raise DataError(f"image format {image_format!r} is not one of {', '.join(IMAGE_FORMATS)}")
    gray = image_format == "jpeg-gray"
    if out.is_symlink() and not out.exists():
        raise DataError(f"{out} is a symbolic link to {os.readlink(out)}, which does not exist; name a folder")
    out = followed(out)
    check_replaceable(out, overwrite)
    remove_stale_temps(out)  # temporary folders of killed exports (those holding their token)
    labels = labels.sort_values("index").reset_index(drop=True)
    names = [f"img{int(i) + 1:06d}.{IMAGE_FORMATS[image_format]}" for i in labels["index"]]
    index, step = labels["index"].to_numpy(), int(images.chunks[0])
    outside = index[(index < 0) | (index >= images.shape[0])]
    if len(outside):
        raise DataError(
            f"the labels name image {int(outside[0])} but the render store holds {images.shape[0]} "
            f"(0..{images.shape[0] - 1}); re-run `rpod label`"
        )
    with atomic_dir(out) as tmp:
        _write_images(tmp, out, images, step, index, names, gray)
        for split, file in SPLIT_FILES.items():
            rows = (labels["split"] == split).to_numpy()
            try:
                records = to_speed(
                    [n for n, keep in zip(names, rows) if keep], labels.loc[rows, POSITION], labels.loc[rows, QUAT]
                )
            except ValueError as e:
                raise DataError(f"the labels of {e}; re-run `rpod label`") from None
            write_json(tmp / EXPORT_DIR / file, records)
        write_json(tmp / "camera.json", camera_to_json(K))
        write_json(
            tmp / MARKER,
            {
                "written_by": "rpod export speed",
                "format": MARKER_FORMAT,
                "files": {name: file_hash(tmp / name, 64) for name in sorted(_tree(tmp))},
            },
        )
        _world_readable(tmp)


def _write_images(
    tmp: Path, out: Path, images: Any, step: int, index: np.ndarray, names: list[str], gray: bool
) -> None:
    """tmp/EXPORT_DIR/images/: image index[k] of the render store `images` as names[k] (BGR PNG, or a grayscale
    JPEG when `gray`), read one stored chunk of `step` images at a time; errors name the file in `out`."""
    import cv2

    (tmp / EXPORT_DIR / "images").mkdir(parents=True)
    for lo in range(0, int(images.shape[0]), step):  # one stored chunk at a time
        rows = np.flatnonzero((index >= lo) & (index < lo + step))
        block = np.asarray(images[lo : lo + step]) if len(rows) else None
        for k in rows:
            rgb = block[index[k] - lo]
            pixels = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY) if gray else rgb[..., ::-1]
            flags = [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY] if gray else []
            if not cv2.imwrite(str(tmp / EXPORT_DIR / "images" / names[k]), pixels, flags):
                raise DataError(f"could not write {out / EXPORT_DIR / 'images' / names[k]}")


def check_replaceable(out: Path, overwrite: bool = False) -> None:
    """A DataError unless `out` is missing, an empty folder, or an earlier export holding only the files
    its MARKER lists, each as it was written (its sha256; an edited one is replaced only with `overwrite`):
    a rerun replaces the whole folder, so it must hold nothing else."""
    if not out.exists():
        return
    if not out.is_dir():
        raise DataError(f"{out} exists and is not a folder; name a new or empty folder")
    if not any(out.iterdir()):
        return
    marker = out / MARKER
    try:
        recorded = read_json(marker) if marker.is_file() else None
        written = recorded["files"] if recorded is not None else None
    except (DataError, KeyError, TypeError):
        written = None
    if not isinstance(written, (dict, list)):
        raise DataError(
            f"{out} exists and is not a SPEED folder written before by `rpod export speed` "
            f"(no {MARKER}); name a new or empty folder"
        )
    extra = sorted(_tree(out) - set(written) - {MARKER})
    if extra:
        raise DataError(
            f"{out} holds {out / extra[0]}, which `rpod export speed` did not write "
            f"({len(extra)} such files); move them away or name a new folder"
        )
    if overwrite:
        return
    if isinstance(written, list) or recorded.get("format") != MARKER_FORMAT:
        raise DataError(
            f"{marker} lists no sha256 of the files (an older export), so edits to them cannot be "
            f"found; pass --overwrite to replace them, or name a new folder"
        )
    edited = sorted(
        name for name, sha in written.items() if os.path.lexists(out / name) and not _unchanged(out / name, sha)
    )
    if edited:
        raise DataError(
            f"{out / edited[0]} was changed since `rpod export speed` wrote it ({len(edited)} such "
            f"files; its sha256 is in {MARKER}); move it away, or pass --overwrite to replace it"
        )


def _unchanged(path: Path, sha256: Any) -> bool:
    """Whether `path` is a regular file whose sha256 is `sha256`."""
    return path.is_file() and not path.is_symlink() and file_hash(path, 64) == sha256


def _tree(folder: Path) -> set[str]:
    """Paths (relative, '/'-separated) of the files and symbolic links below `folder`."""
    return {p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_symlink() or not p.is_dir()}


def _world_readable(folder: Path) -> None:
    """Files 0644 and folders 0755 below and including `folder` (temporary files are created 0600/0700)."""
    folder.chmod(0o755)
    for p in folder.rglob("*"):
        p.chmod(0o755 if p.is_dir() else 0o644)
