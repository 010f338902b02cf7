"""`rpod suite`: the full strongest-attack suite (issue 37) on every test frame of both pose models ->
reports/suite.md and reports/metrics/suite.json. A stage of optional/dvc.yaml (`dvc repro optional/dvc.yaml`), not of
the default `dvc repro`: on 2 CPU cores it would take about 40 hours (the full suite costs about 23 s per frame and eps
on the robust model, 12 s on the standard one); on one H200 (`device: auto` finds CUDA) about 16 minutes (README, "GPU
and the paper profile").

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


Partial = Annotated[
    bool,
    typer.Option(
        "--partial",
        help="Attack nothing: write the page and metrics from the parts kept in datasets/suite/, each model over the "
        "eps (from the smallest up) both its suites reached; the page names the parts that did not run.",
    ),
]


class _OutOfTime(Exception):
    """The time budget of `--minutes` is spent."""


def main(params: Params, minutes: Minutes = None, partial: Partial = False) -> None:
    """Run the full and the lean strongest-attack suite on every test frame of both pose models; write the page and
    metrics (parts kept in datasets/suite/ as they finish)."""
    from pipeline.evaluation.strongest import compare, table

    device = torch_setup(params)
    test = data.load_split(params, "test")
    images, targets = np.stack([test.images[i] for i in range(len(test))]), test.targets.astype(np.float64)
    jobs, kinds = suite_jobs(params, images, targets), data.backgrounds(test.labels)
    if partial:
        runs, devices, missing = _kept(jobs, params.suite.eps)
    else:
        (runs, devices), missing = _run(params, jobs, images, targets, device, minutes), []
    out, seconds = {}, {}
    for name in ("standard", "robust"):
        full, lean = runs[name, "full"], runs[name, "lean"]
        out[name] = {
            k: {**table(r, kinds), "stability": None, "full_check": None} for k, r in (("full", full), ("lean", lean))
        }
        out[name]["lean"]["full_check"] = compare(lean, full)
        seconds[name] = float(sum(r.seconds.sum() * r.frames for r in (full, lean)))
        typer.echo(
            f"suite: {name} model, {len(test)} test frames, eps {list(full.eps)}: {seconds[name]:.0f} s attacking"
        )
    metrics = {
        "models": out,
        "frames": len(test),
        "eps": [float(e) for e in params.suite.eps],
        "missing": missing,
        "device": ", ".join(sorted(devices)),
        "seconds": seconds,
    }
    write_metrics(SUITE_METRICS, metrics, params.profile_name)
    atomic_write_text(SUITE_REPORT, suite_page(metrics, params))
    typer.echo(f"suite: -> {SUITE_REPORT}, {SUITE_METRICS}" + (f" ({len(missing)} parts not run)" if missing else ""))


def _run(
    params: Params, jobs: list[SuiteJob], images: np.ndarray, targets: np.ndarray, device: Any, minutes: float | None
) -> tuple[dict[tuple[str, str], Any], set[str]]:
    """(runs, devices): every job's run over every eps (parts kept read, the others computed and kept) and the
    devices the parts ran on; a StageError when the `minutes` budget stops it."""
    from pipeline.attacks.strongest import run_suite

    clock = _Clock(time.perf_counter(), None if minutes is None else 60.0 * minutes)
    here, runs, devices = _device_name(device), {}, set()
    try:
        for job in jobs:
            model = load_pose(params, job.path).model
            part = _parts(job, here, clock, devices)
            run = run_suite(
                model,
                images,
                targets,
                params.suite.eps,
                job.config,
                device=device,
                part=part,
                progress=f"{job.name} {job.kind}",
            )
            runs[job.name, job.kind] = run
    except _OutOfTime:
        raise StageError(
            f"suite: stopped at the {minutes:g}-minute budget; the parts done are kept in {SUITE_PARTS}/: run "
            "`rpod suite` again to go on (or `rpod suite --partial` for a page of what is there)"
        ) from None
    return runs, devices


def _kept(jobs: list[SuiteJob], eps: list[float]) -> tuple[dict[tuple[str, str], Any], set[str], list[str]]:
    """(runs, devices, missing part files) of `--partial`: per model its two suites over the longest run of eps
    from the smallest up that both have kept; a StageError when a model has none."""
    from pipeline.attacks.strongest import join_eps
    from pipeline.formats.suite import read_suite_part

    kept = {(j.name, j.kind): [read_suite_part(j.part_path(e), j.key) for e in eps] for j in jobs}
    missing = [j.part_path(e).name for j in jobs for e, got in zip(eps, kept[j.name, j.kind]) if got is None]
    runs, devices = {}, set()
    for name in dict.fromkeys(j.name for j in jobs):
        n = min(next((i for i, got in enumerate(kept[name, k]) if got is None), len(eps)) for k in ("full", "lean"))
        if n == 0:
            raise StageError(f"suite --partial: no part of the {name} model at eps {eps[0]:g} in {SUITE_PARTS}/")
        for k in ("full", "lean"):
            runs[name, k] = join_eps([got[0] for got in kept[name, k][:n]])
            devices |= {got[1] for got in kept[name, k][:n]}
    return runs, devices, missing


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
