"""Shared access to the labelled renders for the stages that train on or attack them.

`load_split(params, "train" | "test")` reads `datasets/labels.parquet` (the `label` stage) and
`datasets/render/images.zarr` (the `render` stage), checks both (NaNs, the 6-D columns, image size
against params, labels made from this very render, an empty split) with one clear StageError each, and
returns the split's rows with
their uint8 (N, H, W, 3) RGB images. `pose_dataset(split, ...)` wraps it as a torch Dataset.
Label column `index` is the image's row in the zarr array `images`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from pipeline.formats.renders import META, POSES, read_renders, render_identity
from pipeline.geometry.labels import POSITION, QUAT, SIXD, against_poses, table_problem
from pipeline.io.atomic import read_json
from pipeline.io.tables import read_parquet
from stages.artifacts.paths import IMAGES, LABELS, RENDER
from stages.config.build import augment_config
from stages.config.params import check_render_fingerprint
from stages.config.schema import Params
from stages.config.sections import Augment
from stages.errors import StageError

REQUIRED = ["index", *POSITION, *QUAT, *SIXD, "range", "split"]
RENDER_KEY = "render_fingerprint"  # label table metadata (DataFrame.attrs): the fingerprint of the render it labels
# Above this many bytes a split is read from the store item by item instead of into memory.
PRELOAD_LIMIT_BYTES = 8 << 30


@dataclass
class Split:
    """One split: label rows (sorted by image index) and their images, uint8 (N, H, W, 3) RGB."""

    name: str
    labels: pd.DataFrame
    images: Any  # numpy array, or `_Rows` over the zarr array when not preloaded

    def __len__(self) -> int:
        return len(self.labels)

    @property
    def targets(self) -> np.ndarray:
        """(N, 9) float32: position (m, camera frame) then the 6-D rotation."""
        return self.labels[POSITION + SIXD].to_numpy(np.float32)


class _Rows:
    """Lazy view of chosen rows of a zarr array (one read per item)."""

    def __init__(self, array: Any, rows: np.ndarray):
        self.array, self.rows = array, rows

    def __len__(self) -> int:
        return len(self.rows)

    def __getitem__(self, i: int) -> np.ndarray:
        return self.array[int(self.rows[i])]


def load_labels(path: Path | str = LABELS, render: Path | str = RENDER) -> pd.DataFrame:
    """Read and validate the label table: made from the render in the folder `render` (the fingerprint in
    its meta.json, which `rpod label` copies into the table), required columns, no NaN or inf, valid values
    (`pipeline.geometry.labels.table_problem`: index, poses, 6-D = q, split) and the render's poses
    (`against_poses`: position, quaternion, range per index)."""
    path = Path(path)
    df = read_parquet(path, "label table")
    made, have = df.attrs.get(RENDER_KEY), render_identity(read_json(Path(render) / META))
    if made != have:
        raise StageError(
            f"{path} labels another render than {render} (render fingerprint "
            f"{made or 'not recorded'}, {render} has {have}): re-run `rpod label`"
        )
    extra6 = sorted(c for c in df.columns if c.startswith("r") and c[1:].isdigit() and c not in SIXD)
    missing6 = [c for c in SIXD if c not in df.columns]
    if missing6 or extra6:
        raise StageError(
            f"{path}: the 6-D rotation must be exactly the 6 columns r0..r5; "
            f"missing {missing6 or 'none'}, unexpected {extra6 or 'none'} (re-run `rpod label`)"
        )
    missing = [c for c in REQUIRED if c not in df.columns]
    if missing:
        raise StageError(f"{path}: missing columns {missing} (re-run `rpod label`)")
    numeric = ["index", *POSITION, *QUAT, *SIXD, "range"]
    nans = {c: int(n) for c, n in (~np.isfinite(df[numeric].astype(np.float64))).sum().items() if n}
    if nans:
        raise StageError(f"{path}: NaN or infinite labels in columns {nans} (re-run `rpod label`)")
    problem = table_problem(df) or against_poses(df, read_parquet(Path(render) / POSES, "render poses"))
    if problem:  # a bad value, or labels of other poses than the render's (poses.parquet)
        raise StageError(f"{path}: {problem} (re-run `rpod label`)")
    return df


def open_images(params: Params, path: Path | str = IMAGES) -> Any:
    """The zarr array `images` (N, H, W, 3) uint8 of the render folder holding `path` (FOLDER/images.zarr,
    or the store its meta.json names; pipeline.formats.renders), checked against render.width x
    render.height and the render params' fingerprint."""
    path = Path(path)
    renders = read_renders(path.parent, "image store", "re-run `rpod render`")
    arr, meta = renders.images, renders.meta
    if arr.ndim != 4 or arr.shape[3] != 3 or arr.dtype != np.uint8:
        raise StageError(f"{path}/images must be uint8 (N, H, W, 3), got {arr.dtype} {tuple(arr.shape)}")
    h, w = params.render.height, params.render.width
    if arr.shape[1:3] != (h, w):
        raise StageError(
            f"{path}/images are {arr.shape[2]}x{arr.shape[1]} pixels but params.yaml has "
            f"render.width x render.height = {w}x{h} (re-run `rpod render`, or fix params)"
        )
    check_render_fingerprint(meta, params, path.parent / "meta.json")
    return arr


def load_split(
    params: Params,
    split: str,
    *,
    images_path: Path | str = IMAGES,
    labels_path: Path | str = LABELS,
    preload: bool | None = None,
) -> Split:
    """Rows of `split` ("train" or "test") with their images; `preload` None = when it fits in memory."""
    from tqdm import tqdm

    images = open_images(params, images_path)
    labels = load_labels(labels_path, Path(images_path).parent)
    rows = labels[labels["split"] == split].sort_values("index").reset_index(drop=True)
    if rows.empty:
        found = sorted(map(str, labels["split"].unique()))
        raise StageError(
            f"{labels_path}: the {split!r} split is empty (splits present: {found}); "
            f"check label.test_fraction and the number of rendered frames"
        )
    index = rows["index"].to_numpy(np.int64)
    outside = index[(index < 0) | (index >= images.shape[0])]
    if len(outside):
        raise StageError(
            f"{labels_path}: image index {int(outside[0])} is outside {images_path}/images "
            f"({images.shape[0]} images); re-run `rpod label` after `rpod render`"
        )
    nbytes = len(index) * int(np.prod(images.shape[1:]))
    if preload is False or (preload is None and nbytes > PRELOAD_LIMIT_BYTES):
        return Split(split, rows, _Rows(images, index))
    out = np.empty((len(index), *images.shape[1:]), np.uint8)
    step = images.chunks[0]
    for start in tqdm(range(0, images.shape[0], step), desc=f"read {split} images", unit="chunk", leave=False):
        sel = (index >= start) & (index < start + step)
        if sel.any():
            out[sel] = images[start : start + step][index[sel] - start]
    return Split(split, rows, out)


def subset(split: Split, rows: np.ndarray, name: str) -> Split:
    """The rows `rows` (positions in `split`) of a split as a new split called `name`."""
    rows = np.asarray(rows, np.int64)
    images = (
        _Rows(split.images.array, split.images.rows[rows]) if isinstance(split.images, _Rows) else split.images[rows]
    )
    return Split(name, split.labels.iloc[rows].reset_index(drop=True), images)


def backgrounds(table: pd.DataFrame) -> np.ndarray | None:
    """(N,) each frame's background kind (black, space, earth: the `background` column of a split's labels or a
    rendered set's poses); None when the table has none (every frame black)."""
    return table["background"].to_numpy(str) if "background" in table else None


def pose_dataset(split: Split, augment: Augment | None = None, seed: int = 0) -> Any:
    """A `pipeline.pose.train.PoseDataset` over a split; `augment` = the train.augment params (or None)."""
    from pipeline.pose.train import PoseDataset

    return PoseDataset(split.images, split.targets, None if augment is None else augment_config(augment), seed)


def training_sets(params: Params, seed: int) -> tuple[tuple[Any, Any, Any], tuple[Any, Any]]:
    """((fit split, its augmented dataset, its plain dataset), (validation split, its dataset))."""
    train_split, val_split = fit_and_validation_splits(params, seed)
    return (
        (train_split, pose_dataset(train_split, params.train.augment, seed=seed), pose_dataset(train_split)),
        (val_split, pose_dataset(val_split)),
    )


def fit_and_validation_splits(params: Params, seed: int) -> tuple[Any, Any]:
    """The labelled training split cut into the frames `fit` trains on and the validation frames
    (`train.val_fraction` of whole frames, seeded) the checkpoint is selected on; the test split is not read."""
    from pipeline.evaluation.splits import holdout

    labelled, fraction = load_split(params, "train"), params.train.val_fraction
    try:
        fit_rows, val_rows = holdout(labelled.labels["index"].to_numpy(), float(fraction), seed)
    except ValueError as e:
        raise StageError(f"params.yaml train.val_fraction={fraction!r}: {e}") from None
    return subset(labelled, fit_rows, "train"), subset(labelled, val_rows, "val")
