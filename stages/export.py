"""`rpod export speed OUT`: the labelled renders (or an imported set) as a SPEED+ folder, for other tools.

Reads datasets/render/ (`rpod render`) and datasets/labels.parquet (`rpod label`); writes OUT/camera.json
(K at the stored image size, no distortion, and SPEED+'s physical fx, fy, ppx, ppy),
OUT/synthetic/train.json and the test split as validation.json, SPEED+'s name (`filename`,
`q_vbs2tango_true`, `r_Vo2To_vbs_true`: our q and t, the same numbers; pipeline/formats/speed.py) and the
images as OUT/synthetic/images/imgNNNNNN.png (lossless, so the pixels are the ones the pose model saw) or,
with `--format jpeg-gray`, as grayscale imgNNNNNN.jpg like SPEED+'s.
Not a DVC stage: run it after `dvc repro label`. The export is atomic: a temporary folder renamed to OUT.
OUT/.rpodguard-export.json lists the files written with their sha256; an existing OUT is replaced only when it
holds nothing else and none of them was edited since (`--overwrite` replaces edited ones; any other non-empty
folder is refused, never deleted). A symbolic link OUT is followed. Files are 0644.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from stages.errors import StageError

app = typer.Typer(help="Write the pipeline's data in another dataset layout (SPEED+).", no_args_is_help=True)


@app.command("speed")
def speed(
    out: Path = typer.Argument(
        ..., help="Folder to write: new, empty, or an earlier export holding only its own files (replaced)."
    ),
    image_format: Annotated[
        str, typer.Option("--format", help="png (lossless RGB) or jpeg-gray (grayscale JPEG, as SPEED+ ships)")
    ] = "png",
    overwrite: Annotated[
        bool,
        typer.Option(
            "--overwrite", help="replace files of an earlier export in OUT that were edited since (refused without it)"
        ),
    ] = False,
) -> None:
    """Write datasets/render + datasets/labels.parquet as a SPEED+ folder: camera.json,
    synthetic/{train,validation}.json, synthetic/images/*.png (or *.jpg). `render.source: OUT` imports it back."""

    from pipeline.formats.speed_folder import IMAGE_FORMATS, write_speed
    from pipeline.geometry.camera import Intrinsics
    from stages.artifacts.data import load_labels
    from stages.artifacts.paths import LABELS, RENDER
    from stages.artifacts.readers import read_render_store

    if image_format not in IMAGE_FORMATS:
        raise StageError(f"--format {image_format}: not one of {', '.join(IMAGE_FORMATS)}")
    images, _, meta = read_render_store(RENDER)
    labels = load_labels(LABELS)
    K = Intrinsics.from_K(meta["K"], int(meta["width"]), int(meta["height"]))
    write_speed(out, images, labels, K, image_format, overwrite)
    counts = labels["split"].value_counts()
    typer.echo(
        f"{out}: camera.json, synthetic/train.json ({counts.get('train', 0)} images), synthetic/validation"
        f".json ({counts.get('test', 0)} images), synthetic/images/*.{IMAGE_FORMATS[image_format]}"
    )
