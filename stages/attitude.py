"""`rpod attitude VARIANT...`: issue 38's attitude decomposition -> reports/attitude.md, reports/metrics/attitude.json.

The committed standard model (models/pose.pt, `rpod train`) and the models `rpod pose_trial VARIANT` trained on
variants of the data set (datasets/pose_trials/VARIANT/: the same seed, frame count and recipe), each on its own
validation split (the frames its checkpoint was chosen on: the same frame indices in every variant) and, as a
measurement only (nothing is chosen on it), its test split. Per model and split: mean position, attitude, tilt and
roll errors, overall and per target-attitude group (sequences 0-4 fixed, 5-12 rotating), with 95% percentile
bootstrap intervals over the sequences (pipeline/pose/decomposition.py). Each variant's contribution to the attitude
gap is the standard model's mean attitude error minus the variant model's, paired by sequence. Where a variant's
images have the standard model's input size (per_sequence) the standard model also runs on them: the part of the
contribution that the frames themselves bring (the standard model on them) and the part that training on them brings.
Where one variant makes two others' changes at once (its settings are theirs merged, e.g. per_sequence_320x180), the
interaction: its contribution minus the sum of the two alone, paired by sequence over the four models (whether the
causes add).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import numpy as np
import typer

from pipeline.io.atomic import atomic_write_text, file_hash
from pipeline.seeds import seed_for
from stages.artifacts.dvc import write_metrics
from stages.artifacts.paths import ATTITUDE_METRICS, ATTITUDE_REPORT, IMAGES, LABELS, POSE, POSE_TRIALS
from stages.config.params import PARAMS_FILE, load
from stages.config.schema import Params
from stages.errors import StageError
from stages.pages.attitude import attitude_page

SPLITS = ("validation", "test")
STANDARD = "standard"


def main(
    params: Params,
    variants: Annotated[
        list[str],
        typer.Argument(
            help="Pose trials to compare (datasets/pose_trials/VARIANT, "
            "`rpod pose_trial VARIANT`), e.g. per_sequence 320x180."
        ),
    ],
) -> None:
    """Compare the standard model with the pose trials' models, per split and target-attitude group."""
    from stages.artifacts.models import load_pose, load_trial_pose
    from stages.config.device import torch_setup

    device = torch_setup(params)
    seed = seed_for(params.seed, "train")
    frames = {STANDARD: _frames(params, Path("."), seed)}
    models = {STANDARD: load_pose(params).model}
    trials = {}
    for v in variants:
        folder = POSE_TRIALS / v
        if not (folder / PARAMS_FILE).exists():
            raise StageError(f"{folder} not found: run `rpod pose_trial {v}` (dvc repro optional/dvc.yaml:trial_{v})")
        trials[v] = load(folder / PARAMS_FILE)
        frames[v] = _frames(trials[v], folder, seed)
        models[v] = load_trial_pose(trials[v], folder, device)
    errors = {name: {s: _errors(models[name], frames[name][s], device) for s in SPLITS} for name in models}
    cross = {
        v: {s: _errors(models[STANDARD], frames[v][s], device) for s in SPLITS}
        for v, p in trials.items()
        if (p.render.width, p.render.height) == (params.render.width, params.render.height)
    }
    metrics = {
        "model_hash": file_hash(POSE),
        "seed": seed,
        "variants": variants,
        "changes": {v: _changes(v) for v in variants},
        "models": {
            name: {"size": _size(trials.get(name, params)), **{s: _summary(e) for s, e in per.items()}}
            for name, per in errors.items()
        },
        "cross": {v: {s: _summary(e) for s, e in per.items()} for v, per in cross.items()},
        "contributions": {
            v: {s: _contribution(errors[STANDARD][s], errors[v][s], cross.get(v, {}).get(s)) for s in SPLITS}
            for v in variants
        },
        "interactions": {
            v: {"of": list(pair), **{s: _interaction(errors, v, pair, s) for s in SPLITS}}
            for v, pair in _combinations({v: _summary_of(v).get("settings", {}) for v in variants}).items()
        },
    }
    write_metrics(ATTITUDE_METRICS, metrics, params.profile_name)
    atomic_write_text(ATTITUDE_REPORT, attitude_page(metrics, metrics["changes"]))
    c = metrics["contributions"]
    typer.echo(
        "attitude: "
        + "; ".join(f"{v}: {c[v]['validation']['attitude_deg'][0]:+.2f} deg (validation)" for v in variants)
        + f" -> {ATTITUDE_REPORT}"
    )


def _summary_of(variant: str) -> dict[str, Any]:
    """A pose trial's summary.json (what it changes, in words and as settings)."""
    from pipeline.io.atomic import read_json
    from stages.artifacts.paths import trial_summary

    return dict(read_json(trial_summary(variant)))


def _changes(variant: str) -> str:
    """What a pose trial changes, in words (its summary.json)."""
    return str(_summary_of(variant).get("changes", variant))


def _combinations(settings: dict[str, dict[str, dict[str, Any]]]) -> dict[str, tuple[str, str]]:
    """variant -> (a, b): the given variants whose settings (section -> {field: value}) are exactly two others' merged,
    those two changing disjoint fields."""

    def fields(v: str) -> set[tuple[str, str, str]]:
        return {(sec, k, repr(x)) for sec, kv in settings[v].items() for k, x in kv.items()}

    out = {}
    for v in settings:
        for a in settings:
            for b in settings:
                if a < b and v not in (a, b) and fields(a) and fields(b) and not fields(a) & fields(b):
                    if fields(a) | fields(b) == fields(v):
                        out[v] = (a, b)
    return out


def _interaction(errors: dict[str, Any], both: str, pair: tuple[str, str], split: str) -> dict[str, Any]:
    """The combined variant's contribution to the attitude gap minus the two alone (deg; > 0: together they remove
    more than the sum), paired by sequence over the four models, and the sum alone."""
    from pipeline.pose.decomposition import bootstrap_contrast

    a, b = pair
    sides = [errors[n][split] for n in (a, b, both, STANDARD)]
    att = [(e["attitude_deg"], e["sequence"]) for e in sides]
    return {
        "interaction_deg": bootstrap_contrast(att, [1.0, 1.0, -1.0, -1.0]),
        "alone_sum_deg": bootstrap_contrast(att[:2] + att[3:] + att[3:], [-1.0, -1.0, 1.0, 1.0]),
    }


def _size(p: Params) -> list[int]:
    return [p.render.width, p.render.height]


def _frames(p: Params, root: Path, seed: int) -> dict[str, Any]:
    """The validation split (train.val_fraction of the training split, `seed`: the frames `rpod train` chose its
    checkpoint on) and the test split of the data set in `root`."""
    from pipeline.evaluation.splits import holdout
    from stages.artifacts.data import load_split, subset

    paths = {"images_path": root / IMAGES, "labels_path": root / LABELS}
    labelled = load_split(p, "train", **paths)
    _, val_rows = holdout(labelled.labels["index"].to_numpy(), float(p.train.val_fraction), seed)
    return {"validation": subset(labelled, val_rows, "val"), "test": load_split(p, "test", **paths)}


def _errors(model: Any, split: Any, device: Any) -> dict[str, np.ndarray]:
    """Per frame of a split: position (m), attitude, tilt and roll (deg) errors, sequence id and attitude group."""
    from pipeline.geometry.trajectories import attitude_groups
    from pipeline.pose.metrics import pose_errors, tilt_roll_deg
    from pipeline.pose.train import predict
    from stages.artifacts.data import pose_dataset

    pred = predict(model, pose_dataset(split), device=device)
    pos, att = pose_errors(pred, split.targets)
    tilt, roll = tilt_roll_deg(pred, split.targets)
    seq = split.labels["sequence"].to_numpy()
    return {
        "position_m": pos,
        "attitude_deg": att,
        "tilt_deg": tilt,
        "roll_deg": roll,
        "sequence": seq,
        "group": attitude_groups(seq),
    }


def _summary(e: dict[str, np.ndarray]) -> dict[str, Any]:
    """Means with their bootstrap intervals over sequences, overall and per target-attitude group."""
    from pipeline.pose.decomposition import bootstrap_mean

    keys = ("position_m", "attitude_deg", "tilt_deg", "roll_deg")
    out: dict[str, Any] = {
        "frames": int(len(e["sequence"])),
        **{k: bootstrap_mean(e[k], e["sequence"]) for k in keys},
        "groups": {},
    }
    for g in np.unique(e["group"]):
        m = e["group"] == g
        out["groups"][str(g)] = {
            "frames": int(m.sum()),
            "sequences": int(len(np.unique(e["sequence"][m]))),
            **{k: bootstrap_mean(e[k][m], e["sequence"][m]) for k in keys},
        }
    return out


def _contribution(
    standard: dict[str, np.ndarray], variant: dict[str, np.ndarray], cross: dict[str, np.ndarray] | None
) -> dict[str, Any]:
    """The standard model's mean error minus the variant model's (deg, m; paired by sequence), and with `cross` (the
    standard model on the variant's frames) its two parts: the frames (standard on its frames - standard on the
    variant's) and the training (standard on the variant's frames - the variant model on them)."""
    from pipeline.pose.decomposition import bootstrap_model_difference

    def diff(a: dict[str, np.ndarray], b: dict[str, np.ndarray], key: str) -> tuple[float, float, float]:
        return bootstrap_model_difference(a[key], a["sequence"], b[key], b["sequence"])

    out: dict[str, Any] = {
        "attitude_deg": diff(standard, variant, "attitude_deg"),
        "position_m": diff(standard, variant, "position_m"),
    }
    if cross is not None:
        out["frames_part_deg"] = diff(standard, cross, "attitude_deg")
        out["training_part_deg"] = diff(cross, variant, "attitude_deg")
    return out
