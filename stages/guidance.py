"""`rpod guidance`: the closed-loop rendezvous under attack, Blender rendering every step.

Runs a no-attack baseline and every (eps, start range S, length K) of params with one Renderer at
the pose model's input size; writes reports/guidance.md (one S x K table per eps),
reports/figures/guidance_trajectories.png and reports/metrics/guidance.json. With the safety chain
inside the loop it flies every cell again for each of `guidance.dynamics` and each of
undefended / `guidance.defenses` (detect-and-hold, detect-and-recover; a fresh calibrated defense
from models/defense.json per run) -> the defended section of the report, metrics `defended`, and
reports/figures/guidance_defended.png (one run per variant).
"""
from __future__ import annotations

import itertools
import time
from pathlib import Path
from typing import Any

import numpy as np
import typer

from stages import params as params_mod
from stages.artifacts import load_chain, load_defense
from stages.io import StageError, atomic_write_text, save_figure, write_metrics
from stages.pages.guidance import defended_section, guidance_page

REPORT = Path("reports/guidance.md")
FIGURE = Path("reports/figures/guidance_trajectories.png")
DEFENDED_FIGURE = Path("reports/figures/guidance_defended.png")
METRICS = Path("reports/metrics/guidance.json")
SEED_OFFSET = 500


def _plan(g: dict[str, Any]):
    """Validated settings and the (eps, S, K, window) grid, before anything is loaded or rendered."""
    from pipeline.guidance import GuidanceSettings

    params_mod.check_attack_params(g, "guidance")
    try:
        settings = GuidanceSettings(start=tuple(map(float, g["start"])), goal=tuple(map(float, g["target"])),
                                    tolerance=float(g["tolerance"]), max_step=float(g["max_step"]),
                                    max_steps=int(g["max_steps"]), variant=str(g["variant"]))
    except ValueError as e:
        raise StageError(f"params.yaml guidance: {e}") from None
    if int(g["slack_steps"]) < 0:
        raise StageError(f"params.yaml guidance.slack_steps must be >= 0, got {g['slack_steps']}")
    grid = []
    for eps, s, k in itertools.product(g["eps"], g["start_ranges"], g["lengths"]):
        try:
            grid.append((float(eps), float(s), int(k), settings.window(float(s), int(k))))
        except ValueError as e:
            raise StageError(f"params.yaml guidance.start_ranges / guidance.lengths: {e}") from None
    return settings, grid


def main() -> None:
    """Fly the closed loop without attack and under every (eps, S, K) attack window; report outcomes."""
    from tqdm import tqdm

    from pipeline.attacks import stored_attack
    from pipeline.figures import guidance_trajectories, guidance_variants
    from pipeline.guidance import CachedCamera, fly_grid
    from pipeline.scene import Renderer

    p = params_mod.load()
    g = p["guidance"]
    settings, grid = _plan(g)
    a = p["attack"]
    params_mod.torch_setup(p)
    attack = params_mod.make_attack(a, g["method"], int(p["seed"]) + SEED_OFFSET)
    chain, loss_fn, model_hash = load_chain(p)  # refuses a pose model whose input size is not render.width x height
    defense = load_defense(p, model_hash, chain.threshold)
    model = chain.model
    K = params_mod.intrinsics(p)  # the model's input size

    def attack_at(eps: float) -> Any:
        return stored_attack(model, loss_fn, eps, attack)

    with Renderer(K, params_mod.scene_settings(p["render"])) as renderer:
        camera = CachedCamera(renderer.render, model, chain=chain)
        t0 = time.perf_counter()
        # Attacked runs get the steps the unattacked chaser needed plus slack_steps: an attack succeeds
        # when it delays or diverts the chaser beyond that (the paper: 50 nominal steps + ~10).
        baseline, arrival, horizon, runs = fly_grid(camera, K, settings, grid, int(g["slack_steps"]), attack_at,
                                                    lambda it: tqdm(it, desc="guidance runs", unit="run"))
        seconds = time.perf_counter() - t0
        counts = dict(camera.counts)      # the paper's grid alone
        defended = _defended(camera, K, settings, grid, g, defense, (baseline, runs), attack_at)
        defended["seconds"] = time.perf_counter() - t0 - seconds
        defended.update({k: v - counts[k] for k, v in camera.counts.items()})

    metrics = _metrics(settings, g, a, model_hash, seconds, counts, (baseline, arrival, horizon, runs), defended)
    write_metrics(METRICS, metrics, p)
    atomic_write_text(REPORT, guidance_page(metrics, g, p["render"]) + defended_section(metrics["defended"], g))
    save_figure(guidance_trajectories(baseline, [(s, k, r) for e, s, k, r in runs if e == runs[0][0]] if runs else [],
                                      runs[0][0] if runs else None, settings.goal), FIGURE)
    save_figure(guidance_variants(defended["example"]["runs"], settings.goal, defended["example"]["title"],
                                  settings.tolerance), DEFENDED_FIGURE)
    typer.echo(f"guidance: baseline {baseline.outcome} ({baseline.miss:.2f} m); {len(runs)} attacked runs, "
          f"{counts['renders']} renders for {counts['steps']} steps in {seconds:.0f} s; defended grid "
          f"{defended['renders']} renders for {defended['steps']} steps in {defended['seconds']:.0f} s -> {REPORT}")
    if baseline.outcome != "rendezvous held":
        typer.secho(f"warning: the no-attack baseline did not reach the target ({baseline.outcome}, miss "
                    f"{baseline.miss:.2f} m): the pose model is not good enough for closed-loop guidance, so the "
                    f"attack tables say little; see {REPORT}", fg=typer.colors.YELLOW, err=True)


def _defended(camera: Any, K: Any, settings: Any, grid: list[Any], g: dict[str, Any], defense: Any,
              paper: tuple[Any, list[Any]], attack_at: Any) -> dict[str, Any]:
    """Every (eps, S, K) cell for each of guidance.dynamics, undefended and each of guidance.defenses
    (pipeline.guidance.fly_defended), with a progress bar."""
    from tqdm import tqdm

    from pipeline.guidance import fly_defended

    bar = tqdm(total=len(g["dynamics"]) * (1 + len(g["defenses"])) * (len(grid) + 1), desc="guidance defended",
               unit="run")
    try:
        return fly_defended(camera, K, settings, grid, list(g["dynamics"]), list(g["defenses"]),
                            int(g["slack_steps"]), defense, paper, attack_at, bar)
    finally:
        bar.close()


def _metrics(settings: Any, g: dict[str, Any], a: dict[str, Any], model_hash: str, seconds: float,
             counts: dict[str, int], flown: tuple[Any, int | None, int, list[Any]],
             defended: dict[str, Any]) -> dict[str, Any]:
    """reports/metrics/guidance.json: the paper grid's runs and success rates, and the defended grid."""
    baseline, arrival, horizon, runs = flown
    metrics = {
        "variant": settings.variant, "method": g["method"], "loss": a["loss"], "max_steps": settings.max_steps,
        "tolerance": settings.tolerance, "model_hash": model_hash, "seconds": seconds, **counts,
        "baseline": {"outcome": baseline.outcome, "miss_m": baseline.miss, "arrival_step": arrival},
        "horizon": horizon, "slack_steps": int(g["slack_steps"]),
        "runs": [{"eps": e, "start_range": s, "length": k, "outcome": r.outcome, "miss_m": r.miss,
                  "attack_start": r.attack_start, "attacked_frames": r.attacked_frames, "steps": len(r.estimates)}
                 for e, s, k, r in runs],
    }
    metrics["attack_success_rate"] = {f"{e:g}": float(np.mean([r.outcome != "rendezvous held" for e2, _, _, r in runs
                                                               if e2 == e])) for e in dict.fromkeys(e for e, *_ in runs)}
    metrics["defended"] = {k: v for k, v in defended.items() if k != "example"}
    return metrics
