"""`rpod export speed OUT`: the labelled renders (or an imported set) as a SPEED+ folder, for other tools.

Reads datasets/render/ (`rpod render`) and datasets/labels.parquet (`rpod label`); writes OUT/camera.json
(K at the stored image size, no distortion), OUT/synthetic/train.json and test.json (`filename`,
`q_vbs2tango_true`, `r_Vo2To_vbs_true`: our q and t, the same numbers; pipeline/formats/speed.py) and the
images as OUT/synthetic/images/imgNNNNNN.png (lossless, so the pixels are the ones the pose model saw).
Not a DVC stage: run it after `dvc repro label`. The export is atomic: a temporary folder renamed to OUT.
OUT/.rpodguard-export.json lists the files written; an existing OUT is replaced only when it holds nothing
else (any other non-empty folder is refused, never deleted). Files are 0644.
"""
from __future__ import annotations

from pathlib import Path

import typer

app = typer.Typer(help="Write the pipeline's data in another dataset layout (SPEED+).", no_args_is_help=True)


@app.command("speed")
def speed(out: Path = typer.Argument(..., help="Folder to write: new, empty, or an earlier export holding "
                                                "only its own files (replaced).")) -> None:
    """Write datasets/render + datasets/labels.parquet as a SPEED+ folder: camera.json,
    synthetic/{train,test}.json, synthetic/images/*.png. `render.source: OUT` imports it back."""
    import numpy as np

    from pipeline.formats.speed_folder import write_speed
    from pipeline.geometry.camera import Intrinsics
    from stages.artifacts.paths import LABELS, RENDER
    from stages.artifacts.readers import read_render_store
    from stages.artifacts.data import load_labels

    images, _, meta = read_render_store(RENDER)
    labels = load_labels(LABELS)
    K = np.asarray(meta["K"], dtype=np.float64)
    write_speed(out, images, labels, Intrinsics(int(meta["width"]), int(meta["height"]), K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    counts = labels["split"].value_counts()
    typer.echo(f"{out}: camera.json, synthetic/train.json ({counts.get('train', 0)} images), "
               f"synthetic/test.json ({counts.get('test', 0)} images), synthetic/images/*.png")
