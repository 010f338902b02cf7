"""`rpod suite`: the full strongest-attack suite (issue 37) on every test frame of both pose models ->
reports/suite.md and reports/metrics/suite.json. A stage of optional/dvc.yaml (`dvc repro optional/dvc.yaml`), not of
the default `dvc repro`: on 2 CPU cores it would take days (the full suite costs 10-20 CPU-seconds per frame and eps);
on CUDA (`device: auto` finds it) it takes minutes.

Per model (models/pose.pt, models/pose_robust.pt) at every eps of `suite.eps`: the full suite (pipeline/attacks/
strongest.py FULL's members and starts at the sizes of `suite.full`) and the lean suite of `rpod train --robust` (the
`suite` params' members, steps, restarts, starts) on the same frames; the rows, sanity checks and background split of
each, and the lean suite over the full one per eps (within 5%: the lean figures of reports/pose_robust.md stand;
otherwise they are lower bounds).
"""

from __future__ import annotations

import time

import numpy as np
import typer

from pipeline.io.atomic import atomic_write_text
from stages.artifacts import data
from stages.artifacts.dvc import write_metrics
from stages.artifacts.models import load_pose
from stages.artifacts.paths import POSE, POSE_ROBUST, SUITE_METRICS, SUITE_REPORT
from stages.config.build import suite_config
from stages.config.device import torch_setup
from stages.config.schema import Params
from stages.engine.suite import suite_seed
from stages.pages.suite import suite_page


def main(params: Params) -> None:
    """Run the full and the lean strongest-attack suite on every test frame of both pose models; write the page and
    metrics."""
    from pipeline.attacks.strongest import run_suite
    from pipeline.evaluation.strongest import compare, table

    device = torch_setup(params)
    s, seed = params.suite, suite_seed(params)
    test = data.load_split(params, "test")
    images, targets = np.stack([test.images[i] for i in range(len(test))]), test.targets.astype(np.float64)
    kinds = data.backgrounds(test.labels)
    configs = {"full": suite_config(s, seed, full=True), "lean": suite_config(s, seed)}
    out, seconds = {}, {}
    for name, path in (("standard", POSE), ("robust", POSE_ROBUST)):
        model = load_pose(params, path).model
        t0 = time.perf_counter()
        runs = {k: run_suite(model, images, targets, s.eps, c, device=device) for k, c in configs.items()}
        seconds[name] = time.perf_counter() - t0
        out[name] = {k: {**table(r, kinds), "stability": None, "full_check": None} for k, r in runs.items()}
        out[name]["lean"]["full_check"] = compare(runs["lean"], runs["full"])
        typer.echo(f"suite: {name} model, {len(test)} test frames, {len(s.eps)} eps in {seconds[name]:.0f} s")
    metrics = {
        "models": out,
        "frames": len(test),
        "eps": [float(e) for e in s.eps],
        "device": str(device),
        "seconds": seconds,
    }
    write_metrics(SUITE_METRICS, metrics, params.profile_name)
    atomic_write_text(SUITE_REPORT, suite_page(metrics, params))
    typer.echo(f"suite: -> {SUITE_REPORT}, {SUITE_METRICS}")
