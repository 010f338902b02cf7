"""`rpod label`: the label table of the rendered (or imported) dataset and the dataset card.
(`rpod export speed OUT` writes the labelled set as a SPEED+ folder.)"""

from __future__ import annotations

import numpy as np

from pipeline.formats.renders import render_identity
from pipeline.formats.speed_folder import source_problem
from pipeline.geometry.labels import POSITION, QUAT, SIXD, table_problem
from pipeline.io.atomic import atomic_write_text
from pipeline.io.tables import write_parquet
from pipeline.seeds import seed_for
from pipeline.visibility import out_of_view, split_problem
from stages.artifacts.data import RENDER_KEY
from stages.artifacts.paths import DATASET_CARD as CARD
from stages.artifacts.paths import IMAGES, LABELS, PREVIEWS, RENDER
from stages.artifacts.readers import read_render_store
from stages.config import params as params_mod
from stages.config.schema import Params
from stages.errors import StageError
from stages.pages.label import dataset_card

# poses columns a label table keeps when the render wrote them: `background` (black, space or earth: what lies
# behind the target, pipeline/render/backgrounds.py; absent = every frame black)
OPTIONAL = ["background"]


def build_labels(poses, test_fraction: float, seed: int):
    """Poses table -> label table (contract columns, seeded train/test split of whole frames; the optional
    `background` column carried over). An imported SPEED set (columns `split` and `filename` in the poses) keeps
    its own split and names its files."""
    from pipeline.geometry.rotations import quat_to_6d

    if not 0 < test_fraction < 1:
        raise StageError(f"params.yaml label.test_fraction must be in (0, 1), got {test_fraction}")
    df = poses.sort_values("index").reset_index(drop=True).copy()
    q = df[QUAT].to_numpy()
    r6 = quat_to_6d(q)
    for k, c in enumerate(SIXD):
        df[c] = r6[:, k]
    rendered = [f"{IMAGES}:{i}" for i in df["index"]]
    df.insert(1, "image", df.pop("filename") if "filename" in df else rendered)
    if "split" not in df:
        n_test = int(round(test_fraction * len(df)))
        split = np.full(len(df), "train", dtype=object)
        split[np.random.default_rng(seed).permutation(len(df))[:n_test]] = "test"
        df["split"] = split
    cols = ["index", "image", "sequence", "frame", *POSITION, *QUAT, *SIXD, "range", "split"]
    return df[cols + [c for c in OPTIONAL if c in df]]


def main(params: Params) -> None:
    """Label the rendered frames: datasets/labels.parquet (t, q, 6-D, sequence, frame, train/test split)
    and the dataset card reports/dataset.md. Parameters: `seed` and `label.test_fraction` in params.yaml
    (an imported SPEED/SPEED+ set keeps its own split). `rpod export speed OUT` writes a SPEED+ folder."""
    images, poses, meta = read_render_store(RENDER)
    params_mod.check_render_fingerprint(meta, params, RENDER / "meta.json")
    labels = build_labels(poses, float(params.label.test_fraction), seed_for(params.seed, "label"))
    problem = (
        source_problem(meta, list(poses.sort_values("index").get("filename", [])))
        or table_problem(labels)
        or split_problem(out_of_view(images), labels["index"].to_numpy(), labels["split"].to_numpy())
    )
    if problem:  # the SPEED folder changed since the import, a bad pose, or a split mostly out of view
        raise StageError(f"{RENDER}: {problem}")
    labels.attrs[RENDER_KEY] = render_identity(meta)  # what every reader checks the render against (load_labels)
    write_parquet(labels, LABELS)
    atomic_write_text(CARD, dataset_card(labels, meta, sorted(PREVIEWS.glob("*.png")), CARD.parent))
    print(
        f"{LABELS}: {len(labels)} labels ({(labels.split == 'train').sum()} train, "
        f"{(labels.split == 'test').sum()} test); {CARD}"
    )
