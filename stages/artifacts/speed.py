"""A SPEED / SPEED+ folder as the render output: `import_source` reads the folder `render.source` names
into the render store (what `rpod render` does then); the files are read by pipeline/formats/speed_folder.py
(which also writes them: `rpod export speed`), the fields and frame conventions are pipeline/formats/speed.py's.

Layouts read:
- SPEED+: FOLDER/camera.json, FOLDER/synthetic/train.json; test labels FOLDER/synthetic/validation.json
  (SPEED+'s and `rpod export speed`'s), else FOLDER/synthetic/test.json (older exports);
  `render.source_test` names another (e.g. lightbox/test.json). Images: <folder of the JSON>/images/<filename>.
- SPEED: FOLDER/train.json and FOLDER/test.json, images FOLDER/images/<train|test>/<filename>;
  FOLDER/camera.json if present, else SPEED's published camera.
Every image is resized (area filter) to render.width x render.height, the pose model's input size, and K
is scaled with it; images are first undistorted with camera.json's distCoeffs (cv2.undistort), so K is a
pinhole camera's; grayscale images are copied into the model's 3 channels (one warning per import). Each
image is one sequence, so the grouped splits downstream stay valid.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.formats.speed import relative_name
from pipeline.formats.speed_folder import TEST, TRAIN, check_source, image_path, read_camera, read_image, read_labels
from pipeline.geometry.labels import pose_columns
from pipeline.io.atomic import atomic_dir, remove_stale_temps, write_json
from pipeline.io.store import create_array
from pipeline.io.tables import write_parquet
from pipeline.visibility import empty_problem, out_of_view
from stages.config import params as params_mod
from stages.config.schema import Params
from stages.errors import StageError


def labels_file(folder: Path, names: tuple[str, ...], given: str | None, what: str) -> Path:
    """The label JSON of a split: `given` (relative to folder) or the first of `names` that exists."""
    if given is not None:
        try:
            given = relative_name(given, "params.yaml render.source_test")
        except ValueError as e:
            raise StageError(str(e)) from None
    found = [folder / given] if given else [folder / n for n in names if (folder / n).exists()]
    if not found or not found[0].exists():  # a FIFO exists: read_labels refuses it (not "not found")
        tried = given or ", ".join(names)
        raise StageError(
            f"params.yaml render.source={folder}: no {what} labels ({tried} not found); "
            f"set render.source_test for the test labels (e.g. lightbox/test.json)"
        )
    return found[0]


def check_images(names: list[Path], n_train: int, train: Path, test: Path) -> None:
    """A StageError when an image is labelled in both splits or any labelled image is missing (checked
    before the first image is read)."""
    both = set(names[:n_train]) & set(names[n_train:])
    if both:
        raise StageError(
            f"{sorted(both)[0]} is labelled in both {train} and {test} ({len(both)} such images): "
            f"a test image must never be trained on"
        )
    missing = [f for f in names if not f.exists()]  # a FIFO exists: image_header refuses it
    if missing:
        raise StageError(
            f"{missing[0]}: not found, named by its label file ({len(missing)} of {len(names)} labelled images missing)"
        )


def import_source(p: Params, out: Path) -> float:
    """Import the SPEED/SPEED+ folder of render.source into `out` (images.zarr, poses.parquet with a
    `split` and `filename` column, meta.json with K scaled to render.width x height), atomically;
    returns the seconds it took (for reports/metrics/render.json, never meta.json)."""
    r = p.render
    folder = Path(str(params_mod.given(r.source)))
    if not folder.is_dir():
        raise StageError(f"params.yaml render.source: {folder} is not a folder")
    train = labels_file(folder, TRAIN, None, "training")
    test = labels_file(folder, TEST, r.source_test, "test")
    cam, dist, K = _camera(folder, train, r.width, r.height)
    parts = [(split, f, *read_labels(f)) for split, f in (("train", train), ("test", test))]
    names = [image_path(f, n) for _, f, ns, _, _ in parts for n in ns]
    check_images(names, len(parts[0][2]), train, test)
    digest = check_source(folder, [train, test], names, len(parts[0][2]))  # confined, no leak; what it holds
    t = np.concatenate([x[3] for x in parts])
    q = np.concatenate([x[4] for x in parts])
    n = len(names)
    chunk = min(r.chunk, n)
    for d in remove_stale_temps(out):
        print(f"removed {d}, left over from an interrupted run")
    t0 = time.perf_counter()
    with atomic_dir(out) as tmp:
        _write_images(tmp, folder, names, cam, dist, (r.width, r.height), chunk)
        _write_poses(tmp, folder, parts, names, t, q)
        seconds = time.perf_counter() - t0
        source = {
            "folder": str(folder),
            "sha256": digest,
            "train": str(train.relative_to(folder)),
            "test": str(test.relative_to(folder)),
            "train_images": len(parts[0][2]),
            "test_images": len(parts[1][2]),
        }
        _write_meta(tmp, p, cam, dist, K, n, chunk, source)
    return seconds


def _camera(folder: Path, train: Path, W: int, H: int) -> tuple[Any, np.ndarray, Any]:
    """(the folder's camera (Intrinsics, pixels of its images), its OpenCV distCoeffs, K scaled to W x H pixels);
    says so when the resize changes the aspect."""
    cam, dist = read_camera(folder, speed_layout=train.parent == folder)
    K = cam.scaled(W, H)
    if abs(W / H - cam.width / cam.height) > 0.01 * W / H:
        print(
            f"render.source: {cam.width}x{cam.height} images resized to {W}x{H} change the aspect; "
            f"K is scaled per axis (fy/fx = {K.fy / K.fx:.3f})"
        )
    return cam, dist, K


def _write_images(
    tmp: Path, folder: Path, names: list[Path], cam: Any, dist: np.ndarray, size: tuple[int, int], chunk: int
) -> None:
    """tmp/images.zarr: the labelled images, undistorted and resized to size (W, H) pixels, in chunks of `chunk`
    images (a warning for grayscale ones; a StageError when the target is out of view in them)."""
    import zarr
    from tqdm import tqdm

    (W, H), n = size, len(names)
    images = create_array(
        zarr.open_group(str(tmp / "images.zarr"), mode="w"),
        "images",
        shape=(n, H, W, 3),
        chunks=(chunk, H, W, 3),
        dtype="uint8",
    )
    gray = 0
    for lo in tqdm(range(0, n, chunk), desc="import", unit="chunk"):
        read = [read_image(f, (W, H), cam, dist) for f in names[lo : lo + chunk]]
        images[lo : lo + chunk] = np.stack([img for img, _ in read])
        gray += sum(g for _, g in read)
    if gray:
        print(
            f"warning: render.source: {gray} of {n} images are grayscale; each is copied into the pose "
            f"model's 3 channels (R = G = B)"
        )
    problem = empty_problem(out_of_view(images), f"images imported from {folder}")
    if problem:
        raise StageError(f"params.yaml render.source: {problem}; check its images and camera.json's distCoeffs")


def _write_poses(
    tmp: Path, folder: Path, parts: list[tuple[Any, ...]], names: list[Path], t: np.ndarray, q: np.ndarray
) -> None:
    """tmp/poses.parquet: per image (one sequence each) its pose t (m), q and range (m), its split (from the
    labels of `parts`: split, label file, filenames, ...) and filename relative to the folder."""
    import pandas as pd

    n = len(names)
    write_parquet(
        pd.DataFrame(
            {
                "index": np.arange(n),
                "sequence": np.arange(n),
                "frame": 0,
                **pose_columns(t, q),
                "range": np.linalg.norm(t, axis=1),
                "split": [s for s, _, ns, _, _ in parts for _ in ns],
                "filename": [str(f.relative_to(folder)) for f in names],
            }
        ),
        tmp / "poses.parquet",
    )


def _write_meta(
    tmp: Path, p: Params, cam: Any, dist: np.ndarray, K: Any, n: int, chunk: int, source: dict[str, Any]
) -> None:
    """tmp/meta.json: the store's n frames, size, scaled K, render settings, the source camera (pixels of its
    images) with the distCoeffs removed, and the `source` record."""
    r = p.render
    write_json(
        tmp / "meta.json",
        {
            "complete": True,
            "fingerprint": params_mod.render_fingerprint(p),
            "frames": n,
            "width": r.width,
            "height": r.height,
            "K": K.K,
            "render": params_mod.render_record(r),
            "seed": p.seed,
            "chunk": chunk,
            "camera": {
                "ref_width": cam.width,
                "ref_height": cam.height,
                "fx": cam.fx,
                "fy": cam.fy,
                "cx": cam.cx,
                "cy": cam.cy,
                "dist_coeffs_removed": dist.tolist(),
            },
            "source": source,
        },
    )
