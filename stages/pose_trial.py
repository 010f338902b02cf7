"""`rpod pose_trial VARIANT`: the standard pose recipe retrained on one variant of the default data set (issue 38,
items 3 and 5), for a measured cause of the attitude gap or a held-out check of a choice.

The variant's data set is rendered, labelled and trained by the pipeline's own commands (`rpod render`, `label`,
`train`), each a subprocess in datasets/pose_trials/VARIANT/ with a params.yaml that differs from the main one in
the variant's settings only (`trial_params`): the same seed (so the same poses, split and training seed where the
variant leaves them), the same frame count, recipe and epochs. That folder then holds what the main pipeline
holds at the top level (datasets/render/, datasets/labels.parquet, models/pose.pt, reports/pose.md,
reports/metrics/train.json) plus summary.json (the variant, its settings, seconds per step). `rpod attitude`
compares the variants' models with the committed standard model; `rpod heldout` re-checks the camera default with the
`fy360` model.

Variants (`VARIANTS`):
- per_sequence: render.target_attitude per_sequence (paper-like labels: the paper's Table 1 gives each
  sequence one fixed target attitude, 0 or +-10 deg; ours draws the rotating sequences' attitude every frame);
- 320x180: the images (and the network's input) at 320x180, twice our 160x90 (a resolution point towards the
  paper's 480x270; K scales with the size);
- per_sequence_320x180: both of the above at once (whether their contributions add: `rpod attitude`'s additivity
  row);
- 480x270: the paper's image size (for a GPU box: about 9x the default training's work);
- fy360: the paper's printed camera, fy = 360 at 480x270 (the camera default's held-out check).
"""

from __future__ import annotations

import dataclasses
from typing import Annotated, Any

import typer

from pipeline.io.atomic import atomic_dir, read_json, write_json
from stages.artifacts.paths import POSE_TRIALS, TRAIN_METRICS, trial_summary
from stages.config.params import given
from stages.config.schema import Params
from stages.engine.subrun import run_steps
from stages.errors import StageError

# variant -> (what it changes, in words; the params it sets: section -> {field: value})
VARIANTS: dict[str, tuple[str, dict[str, dict[str, Any]]]] = {
    "per_sequence": (
        "target attitude fixed per sequence (the paper's Table 1)",
        {"render": {"target_attitude": "per_sequence"}},
    ),
    "320x180": ("images at 320x180 (twice our 160x90)", {"render": {"width": 320, "height": 180}}),
    "per_sequence_320x180": (
        "both: target attitude fixed per sequence, images at 320x180",
        {"render": {"target_attitude": "per_sequence", "width": 320, "height": 180}},
    ),
    "480x270": ("images at 480x270 (the paper's size)", {"render": {"width": 480, "height": 270}}),
    "fy360": ("the paper's printed camera, fy = 360 at 480x270", {"camera": {"fy": 360.0}}),
}
STEPS = {"render": ["render"], "label": ["label"], "train": ["train"]}  # dvc.yaml stage name -> its `rpod` command


def trial_params(p: Params, variant: str) -> Params:
    """params.yaml of a variant: the main params with the variant's settings, its renders kept in its folder."""
    if variant not in VARIANTS:
        raise StageError(f"unknown pose trial {variant!r}; choose one of {', '.join(VARIANTS)}")
    if given(p.render.source):
        raise StageError(
            f"params.yaml render.source={p.render.source!r}: a pose trial re-renders the procedural data "
            "set, so it compares nothing with an imported one; unset render.source"
        )
    changes = {
        section: dataclasses.replace(getattr(p, section), **fields) for section, fields in VARIANTS[variant][1].items()
    }
    changes["engine"] = dataclasses.replace(changes.get("engine", p.engine), store=None)
    return dataclasses.replace(p, **changes)


def main(params: Params, variant: Annotated[str, typer.Argument(help=f"The variant: {', '.join(VARIANTS)}.")]) -> None:
    """Render, label and train the standard recipe on one variant of the data set -> datasets/pose_trials/VARIANT/."""
    sub = trial_params(params, variant)
    final = POSE_TRIALS / variant
    with atomic_dir(final) as tmp:
        seconds = run_steps(sub, STEPS, tmp, final, f"pose_trial {variant}", "in")
        train = read_json(tmp / TRAIN_METRICS)
        write_json(
            tmp / trial_summary(variant).name,
            {
                "variant": variant,
                "changes": VARIANTS[variant][0],
                "settings": VARIANTS[variant][1],
                "size": [sub.render.width, sub.render.height],
                "seconds": seconds,
                "best_epoch": train.get("best_epoch"),
                "validation": train.get("val"),
                "test": train.get("test"),
            },
        )
    print(f"pose_trial {variant}: {sum(seconds.values()):.0f} s -> {final}/")
