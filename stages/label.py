"""`rpod label`: the label table of the rendered dataset, its SPEED-style JSON, and the dataset card."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from stages import params as params_mod
from stages.artifacts import LABELS, RENDER, read_render_store
from stages.io import StageError, atomic_write_text, write_json, write_parquet
from stages.pages.label import dataset_card

SPEED = Path("datasets/speed_labels.json")
CARD = Path("reports/dataset.md")
PREVIEWS = Path("reports/figures/previews")
SEED_OFFSET = 200


def build_labels(poses, test_fraction: float, seed: int):
    """Poses table -> label table (contract columns, seeded train/test split of whole frames)."""
    from pipeline.rotations import quat_to_6d

    if not 0 < test_fraction < 1:
        raise StageError(f"params.yaml label.test_fraction must be in (0, 1), got {test_fraction}")
    df = poses.sort_values("index").reset_index(drop=True).copy()
    q = df[["qw", "qx", "qy", "qz"]].to_numpy()
    r6 = quat_to_6d(q)
    for k in range(6):
        df[f"r{k}"] = r6[:, k]
    df.insert(1, "image", [f"{RENDER}/images.zarr:{i}" for i in df["index"]])
    n_test = int(round(test_fraction * len(df)))
    split = np.full(len(df), "train", dtype=object)
    split[np.random.default_rng(seed).permutation(len(df))[:n_test]] = "test"
    df["split"] = split
    cols = ["index", "image", "sequence", "frame", "tx", "ty", "tz", "qw", "qx", "qy", "qz",
            *[f"r{k}" for k in range(6)], "range", "split"]
    return df[cols]


def main() -> None:
    """Label the rendered frames: datasets/labels.parquet (t, q, 6-D, sequence, frame, train/test split),
    datasets/speed_labels.json (SPEED/SPEED+ format) and the dataset card reports/dataset.md.
    Parameters: `seed` and `label.test_fraction` in params.yaml."""
    from pipeline.rotations import to_speed

    p = params_mod.load()
    _, poses, meta = read_render_store(RENDER)
    params_mod.check_render_fingerprint(meta, p, RENDER / "meta.json")
    labels = build_labels(poses, float(p["label"]["test_fraction"]), int(p["seed"]) + SEED_OFFSET)
    write_parquet(labels, LABELS)
    write_json(SPEED, to_speed(list(labels["image"]), labels[["tx", "ty", "tz"]].to_numpy(),
                               labels[["qw", "qx", "qy", "qz"]].to_numpy()))
    atomic_write_text(CARD, dataset_card(labels, meta, sorted(PREVIEWS.glob("*.png")), CARD.parent))
    print(f"{LABELS}: {len(labels)} labels ({(labels.split == 'train').sum()} train, "
          f"{(labels.split == 'test').sum()} test); {SPEED}; {CARD}")
