"""`rpod suite`: the full strongest-attack suite (issue 37) on every test frame of both pose models ->
reports/suite.md and reports/metrics/suite.json. A stage of optional/dvc.yaml (`dvc repro optional/dvc.yaml`), not of
the default `dvc repro`: on 2 CPU cores it would take days (the full suite costs 10-20 CPU-seconds per frame and eps);
on CUDA (`device: auto` finds it) it takes minutes.

Per model (models/pose_robust.pt first, then models/pose.pt) at every eps of `suite.eps`: the full suite
(pipeline/attacks/strongest.py FULL's members and starts at the sizes of `suite.full`) and the lean suite of `rpod
train --robust` (the `suite` params' members, steps, restarts, starts) on the same frames, both in batches of
`suite.full.batch_size`; the rows, sanity checks and background split of each, and the lean suite over the full one
per eps (within 5%: the lean figures of reports/pose_robust.md stand; otherwise they are lower bounds).

Each (model, suite, eps) part is kept in datasets/suite/ as it finishes (pipeline/formats/suite.py), keyed by the
model file, the frames, the settings and the eps: a run stopped by `--minutes`, Ctrl-C or a lost machine goes on
where it stopped, and parts computed on a GPU machine (copied into datasets/suite/) are read here.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Annotated, Any, Callable, Optional

import numpy as np
import typer

from pipeline.io.atomic import atomic_write_text
from stages.artifacts import data
from stages.artifacts.dvc import write_metrics
from stages.artifacts.models import load_pose
from stages.artifacts.paths import SUITE_METRICS, SUITE_PARTS, SUITE_REPORT
from stages.config.device import torch_setup
from stages.config.schema import Params
from stages.engine.suite import SuiteJob, suite_jobs
from stages.errors import StageError
from stages.pages.suite import suite_page

Minutes = Annotated[
    Optional[float],
    typer.Option(
        "--minutes",
        min=0.0,
        help="Start no part (a model, suite and eps) that would end after this many minutes, judged by the parts "
        "before it; what is done is kept in datasets/suite/ and the next run goes on from there (exit status 1).",
    ),
]


class _OutOfTime(Exception):
    """The time budget of `--minutes` is spent."""


def main(params: Params, minutes: Minutes = None) -> None:
    """Run the full and the lean strongest-attack suite on every test frame of both pose models; write the page and
    metrics (parts kept in datasets/suite/ as they finish)."""
    from pipeline.attacks.strongest import run_suite
    from pipeline.evaluation.strongest import compare, table

    device = torch_setup(params)
    test = data.load_split(params, "test")
    images, targets = np.stack([test.images[i] for i in range(len(test))]), test.targets.astype(np.float64)
    kinds, eps = data.backgrounds(test.labels), params.suite.eps
    clock = _Clock(time.perf_counter(), None if minutes is None else 60.0 * minutes)
    runs, devices, here = {}, set(), _device_name(device)
    try:
        for job in suite_jobs(params, images, targets):
            model = load_pose(params, job.path).model
            part = _parts(job, here, clock, devices)
            runs[job.name, job.kind] = run_suite(
                model, images, targets, eps, job.config, device=device, part=part, progress=f"{job.name} {job.kind}"
            )
    except _OutOfTime:
        raise StageError(
            f"suite: stopped at the {minutes:g}-minute budget; the parts done are kept in {SUITE_PARTS}/: run "
            "`rpod suite` again to go on"
        ) from None
    out, seconds = {}, {}
    for name in ("standard", "robust"):
        full, lean = runs[name, "full"], runs[name, "lean"]
        out[name] = {
            k: {**table(r, kinds), "stability": None, "full_check": None} for k, r in (("full", full), ("lean", lean))
        }
        out[name]["lean"]["full_check"] = compare(lean, full)
        seconds[name] = float(sum(r.seconds.sum() * r.frames for r in (full, lean)))
        typer.echo(f"suite: {name} model, {len(test)} test frames, {len(eps)} eps: {seconds[name]:.0f} s of attacks")
    metrics = {
        "models": out,
        "frames": len(test),
        "eps": [float(e) for e in eps],
        "device": ", ".join(sorted(devices)),
        "seconds": seconds,
    }
    write_metrics(SUITE_METRICS, metrics, params.profile_name)
    atomic_write_text(SUITE_REPORT, suite_page(metrics, params))
    typer.echo(f"suite: -> {SUITE_REPORT}, {SUITE_METRICS}")


@dataclasses.dataclass
class _Clock:
    """The `--minutes` budget: `start` (perf_counter s), `budget` (s; None = none)."""

    start: float
    budget: float | None

    def check(self, cost: float | None) -> None:
        """Raise _OutOfTime when a part of `cost` seconds (None: unknown) would end past the budget."""
        if self.budget is not None and time.perf_counter() - self.start + (cost or 0.0) > self.budget:
            raise _OutOfTime


def _parts(job: SuiteJob, device: str, clock: _Clock, devices: set[str]) -> Callable[..., Any]:
    """run_suite's `part` hook for `job`: a part stored with the job's key is read, else it is computed (when the
    budget allows: as long as this job's last part took) and stored."""
    from pipeline.formats.suite import read_suite_part, write_suite_part

    last: list[float] = []

    def part(e: float, compute: Callable[[], Any]) -> Any:
        stored = read_suite_part(job.part_path(e), job.key)
        if stored is not None:
            devices.add(stored[1])
            return stored[0]
        clock.check(last[-1] if last else None)
        t0 = time.perf_counter()
        result = compute()
        last.append(time.perf_counter() - t0)
        write_suite_part(job.part_path(e), result, job.key, device)
        devices.add(device)
        return result

    return part


def _device_name(device: Any) -> str:
    """`cpu`, or e.g. `cuda (NVIDIA H200)`."""
    import torch

    if getattr(device, "type", str(device)) != "cuda":
        return "cpu"
    return f"cuda ({torch.cuda.get_device_name(device)})"
