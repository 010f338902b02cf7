"""The strongest-attack suite (issue 37) on the two pose models, for `rpod train --robust` (the attacked-error
table of reports/pose_robust.md on a seeded sample of test frames, and the attacker capacity on the validation
frames, datasets/capacity/) and `rpod suite` (the full suite on every test frame; optional/dvc.yaml).

Seeds (pipeline/seeds.py): the test sample and the suite's draws on stream `suite` of params `seed`; the
stability and lean-vs-full subsamples and the capacity's frames and draws on streams of that seed. The capacity's
frames are the train split's validation fraction (`data.fit_and_validation_splits` with the standard model's
seed: never fitted by either model); the test split is never read for it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.io.atomic import file_hash
from pipeline.seeds import seed_for
from stages.artifacts import data
from stages.artifacts.paths import POSE, POSE_ROBUST, SUITE_PARTS
from stages.config.build import suite_config
from stages.config.schema import Params


def suite_seed(params: Params) -> int:
    """The seed of the suite's test sample and attack draws."""
    return seed_for(params.seed, "suite")


def attacked_tables(
    params: Params, models: dict[str, Any], test: data.Split, device: Any, checks: bool = True
) -> dict[str, Any]:
    """Per model (name -> pose network) `pipeline.evaluation.strongest.attacked_table` of the suite params on a
    seeded sample of `suite.frames` frames of the test split, its stability check on `suite.check_frames` of them
    and its lean-vs-full check on `suite.full_frames` (0: not run; without `checks` neither runs), the frames'
    backgrounds split."""
    from pipeline.evaluation.strongest import attacked_table
    from pipeline.pose.robustness import sample_rows

    s, seed = params.suite, suite_seed(params)
    sample = data.subset(test, sample_rows(len(test), s.frames, seed), "test")
    images, targets = np.stack([sample.images[i] for i in range(len(sample))]), sample.targets.astype(np.float64)
    check = sample_rows(len(sample), s.check_frames if checks else 0, seed_for(seed, "suite.check"))
    full_check = sample_rows(len(sample), s.full_frames if checks else 0, seed_for(seed, "suite.full"))
    lean, full = suite_config(s, seed), suite_config(s, seed, full=True)
    return {
        name: attacked_table(
            model,
            images,
            targets,
            s.eps,
            lean,
            backgrounds=data.backgrounds(sample.labels),
            check=check,
            full_check=full_check,
            full=full,
            device=device,
        )
        for name, model in models.items()
    }


def capacities(params: Params, models: dict[str, Any], val: data.Split, device: Any) -> dict[str, Any]:
    """Per model (name -> pose network) the per-frame capacity table of the suite params on a seeded sample of
    `suite.capacity.frames` frames of the validation split `val` (topped up to `suite.capacity.min_count` frames
    in each range bin: pipeline.evaluation.strongest.top_up_bins) at `suite.capacity.eps`, and its fitted overbound
    ((table, overbounds); pipeline/evaluation/strongest.py); a bin with too few frames in `val` stops the stage."""
    from pipeline.evaluation.strongest import capacity_frames, fit_overbound, top_up_bins
    from pipeline.pose.robustness import sample_rows
    from stages.errors import StageError

    c, seed = params.suite.capacity, seed_for(suite_seed(params), "suite.capacity")
    range_m = np.linalg.norm(val.targets[:, :3].astype(np.float64), axis=1)
    rows = top_up_bins(sample_rows(len(val), c.frames, seed), range_m, c.edges, c.min_count, seed)
    sample = data.subset(val, rows, "val")
    images, targets = np.stack([sample.images[i] for i in range(len(sample))]), sample.targets.astype(np.float64)
    config, index = suite_config(params.suite, seed), sample.labels["index"].to_numpy()
    out = {}
    for name, model in models.items():
        table = capacity_frames(model, images, targets, c.eps, config, index, device=device)
        try:
            out[name] = (table, fit_overbound(table, c.edges, c.quantile, c.margin, c.min_count))
        except ValueError as e:
            raise StageError(
                f"params.yaml suite.capacity ({len(sample)} validation frames): {e}; widen "
                f"suite.capacity.edges, lower min_count or attack more frames"
            ) from None
    return out


def write_capacities(folder: Any, capacity: dict[str, Any], params: Params, hashes: dict[str, str]) -> dict[str, Any]:
    """Each model's capacity files (pipeline/formats/capacity.py) into `folder`, from `capacities`' output; `hashes`:
    model -> its pose file's hash. Returns model -> the fitted overbound's JSON content (for the metrics)."""
    from pipeline.formats.capacity import write_capacity

    s = params.suite
    out = {}
    for name, (table, overbounds) in capacity.items():
        meta = {
            "model_hash": hashes[name],
            "split": "val",
            "frames": int(table["index"].nunique()),
            "eps": [float(e) for e in s.capacity.eps],
            "min_count": s.capacity.min_count,
            "suite": {"members": list(s.members), "steps": s.steps, "restarts": s.restarts, "starts": list(s.starts)},
        }
        out[name] = write_capacity(folder, name, table, overbounds, meta)
    return out


@dataclass(frozen=True)
class SuiteJob:
    """One suite run of `rpod suite`: pose model `name` (standard | robust) from `path`, suite `kind` (full | lean)
    with its SuiteConfig, and `key`: the identity of its parts (the model file, the frames, the settings); its part
    at eps e is SUITE_PARTS/<name>-<kind>-<e>.npz."""

    name: str
    path: Path
    kind: str
    config: Any
    key: str

    def part_path(self, e: float) -> Path:
        return SUITE_PARTS / f"{self.name}-{self.kind}-{e:g}.npz"


def suite_jobs(params: Params, images: np.ndarray, targets: np.ndarray) -> list[SuiteJob]:
    """`rpod suite`'s runs on the test `images` (N, H, W, 3 uint8) and `targets` (N, 9), in the order it runs them:
    the robust model first (the chain that ships), the full suite then the lean one, both in batches of
    `suite.full.batch_size`."""
    from pipeline.formats.suite import part_key

    s, seed = params.suite, suite_seed(params)
    jobs = []
    for name, path in (("robust", POSE_ROBUST), ("standard", POSE)):
        for kind in ("full", "lean"):
            config = dataclasses.replace(suite_config(s, seed, full=kind == "full"), batch_size=s.full.batch_size)
            jobs.append(
                SuiteJob(name, Path(path), kind, config, part_key(file_hash(path, 64), images, targets, config))
            )
    return jobs
