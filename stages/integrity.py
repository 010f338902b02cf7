"""`rpod integrity`: issue 39's full integrity grid -> reports/integrity_full.md and
reports/metrics/integrity_full.json. A stage of optional/dvc.yaml (`dvc repro optional/dvc.yaml`), not of the
default `dvc repro`: it does not fit the default profile's 40-minute budget (its cost per attacked frame and
attacker: conf/config.yaml, integrity.attackers).

The campaign of `rpod robustness` (stages/engine/campaigns.py, pipeline/evaluation/campaign.py) with nothing left out:
every attacker of the schema (the captures per direction and `integrity.capture_initial`, the drifts, the nested
burst on its error / AL objective) on the shipped chain, the standard one and the undefended robust control, every
eval_render trajectory (or the first `--trajectories N`) and every eps of `integrity.eps` (no stop at a chain's
breaking point). The page has the same sections as the head of reports/robustness.md.

Each chain flies one trajectory at a time, each trajectory's attacks on their own seeds, and keeps the trajectory's
share of the campaign in datasets/integrity_shards/<chain>/ (a persistent DVC output): a killed run, re-run with the
same params, models and data, reads the shares it finished and flies the rest (stages/artifacts/shards.py). The
trajectories still to fly fan out on the engine (stages/engine/pool.py: `engine.workers` Ray workers, each holding
the chain once, one trajectory per job, each share written as its job finishes): on the CPU over Ray workers that
share the cores out, on a CUDA GPU (`device`) in this process, where the GPU does the work (as `rpod attack`).
"""

from __future__ import annotations

import os
import time
from typing import Annotated, Any, Callable, Optional

import typer

from pipeline.io.atomic import atomic_write_text, check_writable
from pipeline.seeds import seed_for
from stages.artifacts.dvc import write_metrics
from stages.artifacts.models import load_chain
from stages.artifacts.paths import INTEGRITY_METRICS, INTEGRITY_REPORT, INTEGRITY_SHARDS, PAPER, SHIPPED
from stages.config.device import torch_setup
from stages.config.schema import Params
from stages.engine import pool as engine
from stages.engine.campaigns import integrity_campaign
from stages.pages.calibrate import unmet_banner
from stages.pages.integrity import integrity_page


def main(
    params: Params,
    trajectories: Annotated[
        Optional[int],
        typer.Option(
            "--trajectories", min=1, help="Fly only the first N eval_render trajectories (default: all of them)."
        ),
    ] = None,
) -> None:
    """Fly the full integrity grid (every attacker, chain, trajectory and eps) and write its page and metrics.

    Resumable: each chain and trajectory's share is kept in datasets/integrity_shards/ once flown, and a re-run with
    the same params, models and data reads it instead of flying it again.

    Params: `integrity` (eps, capture_initial and capture_rate, the burst's and the drift's settings, frame_steps,
    alert_limit_kind), `robustness.burst_every`, `batch_size`, `harm_m`, `defense`, `guidance` (the AL's constants
    and the execution error the page states), and the eval_render params its trajectories were rendered with;
    `engine` (workers, address): where the trajectories still to fly fan out.
    """
    check_writable(INTEGRITY_SHARDS, INTEGRITY_REPORT.parent, INTEGRITY_METRICS.parent)  # found now, not after flying
    es, fan_out = shard_engine(params, torch_setup(params))
    t0 = time.perf_counter()
    shipped = load_chain(params, SHIPPED)
    seed = seed_for(params.seed, "robustness")
    with engine.session(es):  # one Ray for the three chains
        out = integrity_campaign(
            params, shipped, seed, full=True, trajectories=trajectories, shards=INTEGRITY_SHARDS, fan_out=fan_out
        )
    integrity = out["integrity"]
    seconds = time.perf_counter() - t0
    write_metrics(
        INTEGRITY_METRICS,
        {"integrity": integrity, "fused_rows": out["fused_rows"], "fused": out["fused"], "seconds": seconds},
        params.profile_name,
    )
    atomic_write_text(
        INTEGRITY_REPORT,
        unmet_banner(out["fused"]["calibration_unmet"])
        + unmet_banner(integrity["chains"][PAPER.value]["calibration_unmet"], PAPER)
        + integrity_page(integrity, params),
    )
    flown = integrity["chains"][SHIPPED.value]["trajectories"]
    typer.echo(
        f"integrity: breaking eps {integrity['breaking_eps']} on {flown} "
        f"trajectories in {seconds:.0f} s -> {INTEGRITY_REPORT}, {INTEGRITY_METRICS}"
    )


def shard_engine(params: Params, device: Any) -> tuple[engine.EngineSettings, Callable[..., list[Any]]]:
    """(the engine settings, the campaign's `fan_out`: stages/engine/pool.py `run` on them): the missing shares fan
    out over CPU workers (the params' torch threads shared out, each worker's chain on the CPU); on a GPU they are
    flown in this process, where the GPU does the work. engine.timeout_s counts per (attacker, eps) run of a
    trajectory, the job's unit of progress."""
    import dataclasses

    from stages.engine.campaigns import campaign_for, full_grid

    es = engine.engine_settings(params)
    if device.type != "cpu":
        es = dataclasses.replace(es, workers=1, address=None)
    # a job is a whole trajectory of the full grid (about an hour on 2 cores): the no-progress guard waits
    # engine.timeout_s for each of its (attacker, eps) runs
    grid = campaign_for(full_grid(params), 0, None, [])
    runs = (len(grid.plans) + (grid.burst is not None)) * len(grid.eps)
    es = dataclasses.replace(es, timeout_s=es.timeout_s * runs)
    threads = es.threads(params.threads or os.cpu_count() or 1)

    def fan_out(worker_cls: Any, setup: Any, jobs: list[Any], progress: Callable[[int, Any], None]) -> list[Any]:
        on_ray = setup if es.in_process else setup.on_ray(threads)
        return engine.run(worker_cls, on_ray, jobs, es, num_cpus=threads, progress=progress)

    return es, fan_out
