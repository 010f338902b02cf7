"""`rpod guidance`: the closed-loop rendezvous under attack, Blender rendering every step.

Runs a no-attack baseline and every (eps, start range S, length K) of params, rendered at the pose
model's input size; the runs fan out over the engine's workers (stages/engine/guidance_worker.py on
stages/engine/pool.py: in-process with one worker, else Ray actors each holding one Blender scene and
the safety chain), each attacked run's attack seeded by its place in the grid, so the results do not
depend on the worker count; writes reports/guidance.md (one S x K table per eps),
reports/figures/guidance_trajectories.png and reports/metrics/guidance.json. That paper grid flies the
standard model (models/pose.pt, the paper's reproduction; FGSM on it). With the safety chain that ships
(the robust model models/pose_robust.pt, its detector models/detector_robust.pt) inside the loop it flies
every cell again for each of `guidance.dynamics` and each of undefended / `guidance.defenses`
(detect-and-hold, detect-and-recover; a fresh calibrated defense from models/defense.json per run; FGSM on
the robust model) -> the defended section of the report, metrics `defended`, and
reports/figures/guidance_defended.png (one run per variant). Last, the in-loop attacker
(pipeline/attackers/in_loop.py; goal capture: pipeline/attackers/capture.py) on the shipped chain at each
`integrity.in_loop_eps`, goal and start range under the true_state dynamics (the paper dynamics place the chaser at
its estimate: prediction = truth by construction, no integrity evidence) and every variant, then on the standard
chain (the standard model with its detector and models/defense_standard.json) with each of
`guidance.standard_defenses`, its no-attack run first -> the in-loop section, metrics `in_loop`. Every true_state
run executes its commands with the thrusters' error and Clohessy-Wiltshire motion (`guidance.execution`,
pipeline/guidance/dynamics.py; the defense is told the commands). Every run of the shipped chain and of the standard
chain is judged by where it docks (pipeline/evaluation/closed_loop.py: range and lateral miss, collision, lost
target, hold; the breaking point per dynamics and variant) -> metrics `closed_loop`, the section the page
leads with. Rates count only the runs that met the attack.
"""

from __future__ import annotations

import dataclasses
import itertools
import time
from pathlib import Path
from typing import Any

import numpy as np
import typer

from pipeline.guidance.law import DOCKED
from pipeline.io.atomic import atomic_write_text, save_figure
from pipeline.seeds import seed_for
from stages.artifacts.dvc import write_metrics
from stages.artifacts.models import load_chain
from stages.artifacts.paths import GUIDANCE_DEFENDED_FIGURE as DEFENDED_FIGURE
from stages.artifacts.paths import GUIDANCE_FIGURE as FIGURE
from stages.artifacts.paths import GUIDANCE_METRICS as METRICS
from stages.artifacts.paths import GUIDANCE_REPORT as REPORT
from stages.artifacts.paths import PAPER, SHIPPED
from stages.config.build import check_attack_params, execution_settings, intrinsics, make_attack, scene_settings
from stages.config.device import torch_setup
from stages.config.evaluation import Integrity
from stages.config.schema import Params
from stages.config.sections import Attack, Guidance
from stages.engine import chunks
from stages.engine import pool as engine
from stages.engine.guidance_worker import GuidanceSetup, GuidanceWorker, flights
from stages.errors import StageError
from stages.pages.calibrate import unmet_banner
from stages.pages.guidance import closed_loop_section, defended_section, guidance_page, in_loop_section


def _in_loop(i: Integrity, settings: Any) -> tuple[tuple[float, str, float], ...]:
    """The in-loop attacker's (eps, goal, S) cells of params.integrity, S checked against the approach; the capture
    attacks from the first frame (S = the start range: acquisition)."""
    for s in i.in_loop_start_ranges:
        try:
            settings.window(float(s), 1)
        except ValueError as e:
            raise StageError(f"params.yaml integrity.in_loop_start_ranges: {e}") from None
    start = float(np.linalg.norm(settings.start))
    return tuple(
        (float(e), goal, float(s))
        for e, goal in itertools.product(sorted(i.in_loop_eps), i.in_loop_goals)
        for s in ((start,) if goal == "capture" else i.in_loop_start_ranges)
    )


def _plan(g: Guidance) -> tuple[Any, list[tuple[float, float, int, Any]]]:
    """Validated settings and the (eps, S, K, window) grid, before anything is loaded or rendered."""
    from pipeline.guidance.law import GuidanceSettings

    check_attack_params(g, "guidance")
    try:
        settings = GuidanceSettings(
            start=tuple(map(float, g.start)),
            goal=tuple(map(float, g.target)),
            tolerance=float(g.tolerance),
            max_step=float(g.max_step),
            max_steps=g.max_steps,
            variant=g.variant,
        )
    except ValueError as e:
        raise StageError(f"params.yaml guidance: {e}") from None
    if g.slack_steps < 0:
        raise StageError(f"params.yaml guidance.slack_steps must be >= 0, got {g.slack_steps}")
    grid = []
    for eps, s, k in itertools.product(g.eps, g.start_ranges, g.lengths):
        try:
            grid.append((float(eps), float(s), int(k), settings.window(float(s), int(k))))
        except ValueError as e:
            raise StageError(f"params.yaml guidance.start_ranges / guidance.lengths: {e}") from None
    return settings, grid


HORIZON_H = 24.0  # hours: a grid projected to run longer on this machine is refused before the first run


def check_duration(plan: Any, chain: Any, K: Any) -> None:
    """Refuse a grid whose no-attack runs alone (`pipeline.guidance.grid.baseline_steps`, one chain forward a
    step, the fastest of three timed here) would outlast HORIZON_H, naming guidance.max_steps."""
    import torch

    from pipeline.guidance.grid import baseline_steps

    x = torch.zeros(1, 3, K.height, K.width, device=next(chain.model.parameters()).device)
    seconds = []
    for _ in range(3):
        t0 = time.perf_counter()
        chain(x).prob.cpu()
        seconds.append(time.perf_counter() - t0)
    steps = baseline_steps(plan)
    hours = steps * min(seconds) / 3600
    if hours > HORIZON_H:
        raise StageError(
            f"params.yaml guidance.max_steps={plan.settings.max_steps}: the no-attack runs alone fly "
            f"{steps:,} closed-loop steps, about {hours:,.0f} h at {1000 * min(seconds):.2f} ms per step "
            f"on this machine (more than {HORIZON_H:g} h); lower it (the nominal approach takes 50 steps)"
        )


def main(params: Params) -> None:
    """Fly the closed loop without attack and under every (eps, S, K) attack window, on the engine's
    workers (each run on one; results in grid order); report outcomes."""
    g = params.guidance
    settings, grid = _plan(g)
    in_loop = _in_loop(params.integrity, settings)
    make_attack(params.attack, g.method, 0)  # refuses bad attack params before anything runs
    torch_setup(params)
    # each refuses a pose model whose input size is not render.width x height, or a detector of another model
    with_defense = {SHIPPED: True, PAPER: bool(g.standard_defenses)}  # the standard chain flies defended in the loop
    chains = {m.value: load_chain(params, m, defended=with_defense[m]) for m in (PAPER, SHIPPED)}
    hashes = {m: chain.pose_hash for m, chain in chains.items()}
    shipped = chains[SHIPPED.value]
    K, es = intrinsics(params), engine.engine_settings(params)  # K: the model's input size
    plan = _grid_plan(params, settings, grid, in_loop)
    check_duration(plan, shipped.onboard, K)
    flown, t0, seconds = _fly(params, plan, chains, K, es)
    counts, paper_runs, defended, looped = _grids(plan, flown, t0, seconds)
    baseline, _, _, attacked = paper_runs
    metrics = _metrics(settings, g, params.attack, hashes, seconds, counts, paper_runs, defended)
    metrics |= _shipped_metrics(params, plan, flown, looped, t0)
    standard = chains[PAPER.value] if g.standard_defenses else None
    _write_outputs(params, metrics, (shipped, standard), settings, (baseline, attacked), defended)
    typer.echo(
        f"guidance: baseline {baseline.outcome} ({baseline.miss:.2f} m); {len(attacked)} attacked runs in "
        f"{seconds:.0f} s; defended grid and {looped} in-loop runs in {defended['seconds']:.0f} s -> {REPORT}"
    )
    if baseline.outcome != DOCKED:
        typer.secho(
            f"warning: the no-attack baseline did not reach the target ({baseline.outcome}, miss "
            f"{baseline.miss:.2f} m): the pose model is not good enough for closed-loop guidance, so the "
            f"attack tables say little; see {REPORT}",
            fg=typer.colors.YELLOW,
            err=True,
        )


def _grid_plan(
    params: Params,
    settings: Any,
    grid: list[tuple[float, float, int, Any]],
    in_loop: tuple[tuple[float, str, float], ...],
) -> Any:
    """The GridPlan of every run: the paper grid, the defended grid per `guidance.dynamics` and defense, and the
    in-loop cells (under true_state when guidance.dynamics has it) on the shipped chain and, with each of
    `guidance.standard_defenses`, the standard chain, with the seeded execution settings."""
    from pipeline.guidance.grid import GridPlan

    g = params.guidance
    return GridPlan(
        settings,
        tuple(grid),
        g.slack_steps,
        tuple(g.dynamics),
        tuple(g.defenses),
        in_loop,
        execution_settings(params, seed_for(params.seed, "execution")),
        ("true_state",) if "true_state" in g.dynamics else (),
        tuple(g.standard_defenses),
    )


def _fly(
    params: Params, plan: Any, chains: dict[str, Any], K: Any, es: engine.EngineSettings
) -> tuple[list[Any], float, float]:
    """Fly every run of `plan` on the engine's workers (`chains`: the loaded chains by name, whose calibrated
    defenses the workers take): ((result, rendered keys) per run in plan order, the time.perf_counter() reading at
    the start (s), the seconds until the paper grid's last run finished)."""
    from tqdm import tqdm

    scene, threads = chunks.prepare(K, scene_settings(params.render), es)
    runs = flights(plan)  # attacked runs last the no-attack arrival + slack_steps (the paper: 50 nominal steps + ~10)
    finished, t0, paper_done = [0], time.perf_counter(), [0.0]

    def progress(i: int, _: Any) -> None:
        finished[0] += i < plan.paper_size
        if finished[0] == plan.paper_size and not paper_done[0]:
            paper_done[0] = time.perf_counter() - t0
        bar.update(1)

    with tqdm(total=len(runs), desc="guidance runs", unit="run") as bar:
        on_cpu = params if es.in_process else dataclasses.replace(params, device="cpu")  # Ray workers hold no GPU
        setup = GuidanceSetup(
            params=on_cpu,
            K=K,
            scene=scene,
            root=str(Path.cwd()),
            defense=chains[SHIPPED.value].defended,
            plan=plan,
            seed=seed_for(params.seed, "guidance"),
            torch_threads=None if es.in_process else threads,
            standard_defense=chains[PAPER.value].defended if plan.standard_defenses else None,
        )
        flown = engine.run(GuidanceWorker, setup, runs, es, num_cpus=threads, progress=progress)
    return flown, t0, paper_done[0]


def _grids(
    plan: Any, flown: list[Any], t0: float, seconds: float
) -> tuple[dict[str, int], tuple[Any, int | None, int, list[Any]], dict[str, Any], int]:
    """(the paper grid's counts, its (baseline, arrival step, horizon, attacked runs), the defended grid with its
    seconds (the in-loop runs included) and counts, the number of in-loop runs)."""
    from pipeline.guidance.grid import defended_grid, grid_counts, paper_grid

    paper = flown[: plan.paper_size]
    counts = grid_counts(paper)  # the paper's grid alone
    paper_runs = paper_grid(plan, [r for r, _ in flown])
    defended = defended_grid(plan, [r for r, _ in flown])
    defended["seconds"] = time.perf_counter() - t0 - seconds  # with the in-loop runs: they share the workers
    looped = len(plan.in_loop_runs())
    defended.update(
        grid_counts(flown[plan.paper_size : len(flown) - looped], frozenset().union(*(k for _, k in paper)))
    )
    return counts, paper_runs, defended, looped


def _shipped_metrics(params: Params, plan: Any, flown: list[Any], looped: int, t0: float) -> dict[str, Any]:
    """The metrics of the shipped chain's in-loop and closed-loop judgement, the execution params and the
    stage's minutes so far."""
    from functools import partial

    from pipeline.defense.integrity import alert_limit
    from pipeline.evaluation.closed_loop import closed_loop_outcomes
    from pipeline.guidance.grid import grid_counts, in_loop_grid
    from stages.config.build import alert_limit_settings

    collision = params.integrity.collision_range_m
    limit = partial(alert_limit, settings=alert_limit_settings(params))
    return {
        "in_loop": in_loop_grid(plan, [r for r, _ in flown], collision) | grid_counts(flown[len(flown) - looped :]),
        "closed_loop": closed_loop_outcomes(plan, [r for r, _ in flown], collision, limit),
        "execution": dataclasses.asdict(params.guidance.execution),
        "minutes": (time.perf_counter() - t0) / 60,
    }


def _write_outputs(
    params: Params,
    metrics: dict[str, Any],
    chains: tuple[Any, Any],
    settings: Any,
    paper: tuple[Any, list[Any]],
    defended: dict[str, Any],
) -> None:
    """reports/metrics/guidance.json, reports/guidance.md (behind the unmet-calibration banners of the shipped chain
    and, where it flies defended, the standard one) and the two figures; `chains`: (shipped, standard or None);
    `paper`: the paper grid's (baseline, attacked runs)."""
    from pipeline.report.figures import guidance_trajectories, guidance_variants

    g = params.guidance
    baseline, attacked = paper
    write_metrics(METRICS, metrics, params.profile_name)
    atomic_write_text(
        REPORT,
        unmet_banner(chains[0].calibration.unmet)
        + (unmet_banner(chains[1].calibration.unmet, PAPER) if chains[1] is not None else "")
        + closed_loop_section(metrics["closed_loop"], params)
        + guidance_page(metrics, g, params.render)
        + defended_section(metrics["defended"], g)
        + in_loop_section(metrics["in_loop"], params.integrity),
    )
    first = attacked[0][0] if attacked else None
    save_figure(
        guidance_trajectories(baseline, [(s, k, r) for e, s, k, r in attacked if e == first], first, settings.goal),
        FIGURE,
    )
    save_figure(
        guidance_variants(defended["example"]["runs"], settings.goal, defended["example"]["title"], settings.tolerance),
        DEFENDED_FIGURE,
    )


def _metrics(
    settings: Any,
    g: Guidance,
    a: Attack,
    hashes: dict[str, str],
    seconds: float,
    counts: dict[str, int],
    flown: tuple[Any, int | None, int, list[Any]],
    defended: dict[str, Any],
) -> dict[str, Any]:
    """reports/metrics/guidance.json: the paper grid's runs and success rates (standard model: `model_hash`),
    and the defended grid (the shipped chain: `models`); `hashes`: pose-model hash per model name."""
    baseline, arrival, horizon, runs = flown
    metrics = {
        "variant": settings.variant,
        "method": g.method,
        "loss": a.loss,
        "max_steps": settings.max_steps,
        "tolerance": settings.tolerance,
        "model_hash": hashes[PAPER.value],
        "seconds": seconds,
        **counts,
        "models": {
            "paper": {"model": PAPER.value, "model_hash": hashes[PAPER.value]},
            "shipped": {"model": SHIPPED.value, "model_hash": hashes[SHIPPED.value]},
        },
        "baseline": {"outcome": baseline.outcome, "miss_m": baseline.miss, "arrival_step": arrival},
        "horizon": horizon,
        "slack_steps": g.slack_steps,
        "runs": [
            {
                "eps": e,
                "start_range": s,
                "length": k,
                "outcome": r.outcome,
                "miss_m": r.miss,
                "attack_start": r.attack_start,
                "attacked_frames": r.attacked_frames,
                "steps": len(r.estimates),
            }
            for e, s, k, r in runs
        ],
    }
    # of the runs that met the attack (a run that never reached S was not attacked)
    met = {
        e: [r.outcome != DOCKED for e2, _, _, r in runs if e2 == e and r.attacked_frames > 0]
        for e in dict.fromkeys(e for e, *_ in runs)
    }
    metrics["attack_success_rate"] = {f"{e:g}": float(np.mean(v)) if v else None for e, v in met.items()}
    metrics["defended"] = {k: v for k, v in defended.items() if k != "example"}
    return metrics
