"""SPEED / SPEED+ folders on disk: `import_source` reads one into the render store (what `rpod render` does
when `render.source` names a folder) and `export` writes the labelled renders as one (`rpod export speed`).

Layouts read (pipeline/formats/speed.py has the label and camera fields and the frame conventions):
- SPEED+: FOLDER/camera.json, FOLDER/synthetic/train.json; test labels FOLDER/synthetic/test.json (what
  `rpod export speed` writes), else FOLDER/synthetic/validation.json; `render.source_test` names another
  (e.g. lightbox/test.json). Images: <folder of the JSON>/images/<filename>.
- SPEED: FOLDER/train.json and FOLDER/test.json, images FOLDER/images/<train|test>/<filename>;
  FOLDER/camera.json if present, else SPEED's published camera.
Every image is resized (area filter) to render.width x render.height, the pose model's input size, and K
is scaled with it; each image is one sequence, so the grouped splits downstream stay valid.
"""
from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from stages.config import params as params_mod
from stages.config.schema import Params
from stages.io import StageError, atomic_dir, create_array, read_json, remove_stale_temps, write_json, write_parquet

TRAIN = ("synthetic/train.json", "train.json")
TEST = ("synthetic/test.json", "synthetic/validation.json", "test.json")
EXPORT_DIR = "synthetic"                 # SPEED+'s domain folder of synthetic images


def labels_file(folder: Path, names: tuple[str, ...], given: str | None, what: str) -> Path:
    """The label JSON of a split: `given` (relative to folder) or the first of `names` that exists."""
    found = [folder / given] if given else [folder / n for n in names if (folder / n).is_file()]
    if not found or not found[0].is_file():
        tried = given or ", ".join(names)
        raise StageError(f"params.yaml render.source={folder}: no {what} labels ({tried} not found); "
                         f"set render.source_test for the test labels (e.g. lightbox/test.json)")
    return found[0]


def read_labels(path: Path) -> tuple[list[str], np.ndarray, np.ndarray]:
    """(filenames, t (N, 3) m, q (N, 4)) of a SPEED/SPEED+ label file; one StageError naming file and field."""
    from pipeline.formats.speed import from_speed

    try:
        return from_speed(read_json(path))
    except ValueError as e:
        raise StageError(f"{path}: {e}") from None


def read_camera(folder: Path, speed_layout: bool):
    """pipeline.geometry.camera.Intrinsics of FOLDER/camera.json (SPEED's published camera when a SPEED folder has none)."""
    from pipeline.formats.speed import SPEED_CAMERA, camera_from_json

    path = folder / "camera.json"
    if not path.is_file() and speed_layout:
        print(f"{path} not found: using SPEED's published camera {SPEED_CAMERA}")
        return camera_from_json(SPEED_CAMERA)
    try:
        return camera_from_json(read_json(path))
    except ValueError as e:
        raise StageError(f"{path}: {e}") from None


def image_path(label_file: Path, name: str) -> Path:
    """SPEED+: <json folder>/images/<name>; SPEED: <json folder>/images/<json stem>/<name>."""
    plus = label_file.parent / "images" / name
    return plus if plus.is_file() else label_file.parent / "images" / label_file.stem / name


def read_image(path: Path, size: tuple[int, int], source_size: tuple[int, int]) -> np.ndarray:
    """uint8 RGB (H, W, 3) at `size` (W, H) of an image file that must be `source_size` (Nu, Nv) pixels;
    JPEGs are decoded at 1/2, 1/4 or 1/8 size when that still exceeds `size` (faster, same pixels)."""
    import cv2

    reduce = max([r for r in (2, 4, 8) if source_size[0] / r >= size[0] and source_size[1] / r >= size[1]], default=1)
    flag = {1: cv2.IMREAD_COLOR, 2: cv2.IMREAD_REDUCED_COLOR_2, 4: cv2.IMREAD_REDUCED_COLOR_4,
            8: cv2.IMREAD_REDUCED_COLOR_8}[reduce]
    img = cv2.imread(str(path), flag) if path.is_file() else None
    if img is None:
        raise StageError(f"{path}: {'not found' if not path.is_file() else 'not a readable image'} "
                         f"(named by its label file)")
    expect = (math.ceil(source_size[1] / reduce), math.ceil(source_size[0] / reduce))
    if img.shape[:2] != expect:
        raise StageError(f"{path}: image is {img.shape[1] * reduce}x{img.shape[0] * reduce} pixels but camera.json "
                         f"gives Nu x Nv = {source_size[0]}x{source_size[1]}")
    return cv2.resize(img, size, interpolation=cv2.INTER_AREA)[..., ::-1]


def import_source(p: Params, out: Path) -> None:
    """Import the SPEED/SPEED+ folder of render.source into `out` (images.zarr, poses.parquet with a
    `split` and `filename` column, meta.json with K scaled to render.width x height), atomically."""
    import pandas as pd
    import zarr
    from tqdm import tqdm

    r = p.render
    folder = Path(str(params_mod.given(r.source)))
    if not folder.is_dir():
        raise StageError(f"params.yaml render.source: {folder} is not a folder")
    train = labels_file(folder, TRAIN, None, "training")
    test = labels_file(folder, TEST, r.source_test, "test")
    cam = read_camera(folder, speed_layout=train.parent == folder)
    W, H = r.width, r.height
    K = cam.scaled(W, H)
    if abs(W / H - cam.width / cam.height) > 0.01 * W / H:
        print(f"render.source: {cam.width}x{cam.height} images resized to {W}x{H} change the aspect; "
              f"K is scaled per axis (fy/fx = {K.fy / K.fx:.3f})")
    parts = [(split, f, *read_labels(f)) for split, f in (("train", train), ("test", test))]
    names = [image_path(f, n) for _, f, ns, _, _ in parts for n in ns]
    t = np.concatenate([x[3] for x in parts])
    q = np.concatenate([x[4] for x in parts])
    n, chunk = len(names), r.chunk
    for d in remove_stale_temps(out):
        print(f"removed {d}, left over from an interrupted run")
    t0 = time.perf_counter()
    with atomic_dir(out) as tmp:
        images = create_array(zarr.open_group(str(tmp / "images.zarr"), mode="w"), "images", shape=(n, H, W, 3),
                              chunks=(chunk, H, W, 3), dtype="uint8")
        for lo in tqdm(range(0, n, chunk), desc="import", unit="chunk"):
            images[lo:lo + chunk] = np.stack([read_image(f, (W, H), (cam.width, cam.height))
                                              for f in names[lo:lo + chunk]])
        write_parquet(pd.DataFrame({
            "index": np.arange(n), "sequence": np.arange(n), "frame": 0, "tx": t[:, 0], "ty": t[:, 1],
            "tz": t[:, 2], "qw": q[:, 0], "qx": q[:, 1], "qy": q[:, 2], "qz": q[:, 3],
            "range": np.linalg.norm(t, axis=1), "split": [s for s, _, ns, _, _ in parts for _ in ns],
            "filename": [str(f.relative_to(folder)) for f in names]}), tmp / "poses.parquet")
        seconds = time.perf_counter() - t0
        write_json(tmp / "meta.json", {
            "complete": True, "fingerprint": params_mod.render_fingerprint(p), "frames": n, "width": W,
            "height": H, "K": K.K, "render": dataclasses.asdict(r), "seed": p.seed, "seconds": seconds,
            "seconds_per_image": seconds / n, "chunk": chunk,
            "camera": {"ref_width": cam.width, "ref_height": cam.height, "fx": cam.fx, "fy": cam.fy, "cx": cam.cx,
                       "cy": cam.cy},
            "source": {"folder": str(folder), "train": str(train.relative_to(folder)),
                       "test": str(test.relative_to(folder)), "train_images": len(parts[0][2]),
                       "test_images": len(parts[1][2])}})


def export(out: Path, images: Any, labels: Any, K: Any) -> None:
    """Write the labelled images as a SPEED+ folder `out` (camera.json, synthetic/{train,test}.json,
    synthetic/images/imgNNNNNN.png, NNNNNN = label index + 1), atomically; PNG keeps every pixel."""
    import cv2

    from pipeline.formats.speed import camera_to_json, to_speed

    if out.exists() and any(out.iterdir()) and not (out / "camera.json").is_file():
        raise StageError(f"{out} exists and is not a SPEED folder written before; name a new or empty folder")
    labels = labels.sort_values("index").reset_index(drop=True)
    names = [f"img{int(i) + 1:06d}.png" for i in labels["index"]]
    index, step = labels["index"].to_numpy(), int(images.chunks[0])
    if index.min() < 0 or index.max() >= images.shape[0]:
        raise StageError(f"the labels name image {int(index.max())} but the render store holds {images.shape[0]}; "
                         f"re-run `rpod label`")
    with atomic_dir(out) as tmp:
        (tmp / EXPORT_DIR / "images").mkdir(parents=True)
        for lo in range(0, int(images.shape[0]), step):   # one stored chunk at a time
            rows = np.flatnonzero((index >= lo) & (index < lo + step))
            block = np.asarray(images[lo:lo + step]) if len(rows) else None
            for k in rows:
                path = tmp / EXPORT_DIR / "images" / names[k]
                if not cv2.imwrite(str(path), block[index[k] - lo][..., ::-1]):
                    raise StageError(f"could not write {out / EXPORT_DIR / 'images' / names[k]}")
        for split in ("train", "test"):
            rows = (labels["split"] == split).to_numpy()
            write_json(tmp / EXPORT_DIR / f"{split}.json",
                       to_speed([n for n, keep in zip(names, rows) if keep], labels.loc[rows, ["tx", "ty", "tz"]],
                                labels.loc[rows, ["qw", "qx", "qy", "qz"]]))
        write_json(tmp / "camera.json", camera_to_json(K))
