"""`rpod guidance`: the closed-loop rendezvous of SPEC 5 under attack, Blender rendering every step.

Runs a no-attack baseline and every (eps, start range S, length K) of params with one Renderer at
the pose model's input size; writes reports/guidance.md (one S x K table per eps),
reports/figures/guidance_trajectories.png and reports/metrics/guidance.json.
"""
from __future__ import annotations

import dataclasses
import itertools
import time
from pathlib import Path
from typing import Any

import numpy as np
import typer

from stages import params as params_mod
from stages.artifacts import load_pose
from stages.io import StageError, atomic_write_text, save_figure, write_metrics

REPORT = Path("reports/guidance.md")
FIGURE = Path("reports/figures/guidance_trajectories.png")
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

    from pipeline.attacks import attack_loss, stored_attack
    from pipeline.figures import guidance_trajectories
    from pipeline.guidance import CachedCamera, arrival_step, run_rendezvous
    from pipeline.scene import Renderer

    p = params_mod.load()
    g = p["guidance"]
    settings, grid = _plan(g)
    a = p["attack"]
    params_mod.set_threads(p)
    attack = params_mod.make_attack(a, g["method"], int(p["seed"]) + SEED_OFFSET)
    pose = load_pose(p)  # refuses a checkpoint whose input size is not render.width x height
    model, loss_fn = pose.model, attack_loss(a["loss"], pose.loss)
    K = params_mod.intrinsics(p)  # the model's input size

    with Renderer(K, params_mod.scene_settings(p["render"])) as renderer:
        camera = CachedCamera(renderer.render, model)
        t0 = time.perf_counter()
        baseline = run_rendezvous(camera.render, camera.estimate, K, settings)
        # Attacked runs get the steps the unattacked chaser needed plus slack_steps: an attack succeeds
        # when it delays or diverts the chaser beyond that (the paper: 50 nominal steps + ~10).
        arrival = arrival_step(baseline, settings.goal, settings.tolerance)
        horizon = settings.max_steps if arrival is None else min(settings.max_steps, arrival + int(g["slack_steps"]))
        attacked_settings = dataclasses.replace(settings, max_steps=horizon)
        runs = []
        for eps, s, k, window in tqdm(grid, desc="guidance runs", unit="run"):
            camera.attack = stored_attack(model, loss_fn, eps, attack)
            runs.append((eps, s, k, run_rendezvous(camera.render, camera.estimate, K, attacked_settings, window)))
        seconds = time.perf_counter() - t0
    counts = camera.counts

    metrics = {
        "variant": settings.variant, "method": g["method"], "loss": a["loss"], "max_steps": settings.max_steps,
        "tolerance": settings.tolerance, "model_hash": pose.hash, "seconds": seconds, **counts,
        "baseline": {"outcome": baseline.outcome, "miss_m": baseline.miss, "arrival_step": arrival},
        "horizon": horizon, "slack_steps": int(g["slack_steps"]),
        "runs": [{"eps": e, "start_range": s, "length": k, "outcome": r.outcome, "miss_m": r.miss,
                  "attack_start": r.attack_start, "attacked_frames": r.attacked_frames, "steps": len(r.estimates)}
                 for e, s, k, r in runs],
    }
    metrics["attack_success_rate"] = {f"{e:g}": float(np.mean([r.outcome != "rendezvous held" for e2, _, _, r in runs
                                                               if e2 == e])) for e in dict.fromkeys(e for e, *_ in runs)}
    write_metrics(METRICS, metrics, p)
    atomic_write_text(REPORT, _report(metrics, g, a, p["render"]))
    save_figure(guidance_trajectories(baseline, [(s, k, r) for e, s, k, r in runs if e == runs[0][0]] if runs else [],
                                      runs[0][0] if runs else None, settings.goal), FIGURE)
    typer.echo(f"guidance: baseline {baseline.outcome} ({baseline.miss:.2f} m); {len(runs)} attacked runs, "
          f"{counts['renders']} renders for {counts['steps']} steps in {seconds:.0f} s -> {REPORT}")
    if baseline.outcome != "rendezvous held":
        typer.secho(f"warning: the no-attack baseline did not reach the target ({baseline.outcome}, miss "
                    f"{baseline.miss:.2f} m): the pose model is not good enough for closed-loop guidance, so the "
                    f"attack tables say little; see {REPORT}", fg=typer.colors.YELLOW, err=True)


def _horizon_text(m: dict[str, Any]) -> str:
    arrival = m["baseline"]["arrival_step"]
    if arrival is None:
        return f"Every run lasts {m['horizon']} steps (guidance.max_steps; the no-attack baseline did not arrive)."
    return (f"The no-attack baseline arrived after {arrival} steps (the nominal approach takes 50; in the paper "
            f"variant a bias of the estimate along the range changes how far the chaser moves per step), so every attacked run lasts {m['horizon']} steps: "
            f"that arrival plus guidance.slack_steps = {m['slack_steps']}, at most guidance.max_steps = {m['max_steps']}. "
            "An attack succeeds when the chaser is not at the target point by then.")


def _cell(r: dict[str, Any]) -> str:
    text = {"rendezvous held": "held", "attack succeeded": "**attack succeeded**",
            "target lost": f"**target lost** (step {r['steps']})", "missed without attack": "missed"}[r["outcome"]]
    frames = "" if r["attacked_frames"] == r["length"] else f", {r['attacked_frames']} attacked frames"
    return f"{text}, {r['miss_m']:.2f} m{frames}"


def _report(m: dict[str, Any], g: dict[str, Any], a: dict[str, Any], render: dict[str, Any]) -> str:
    from pipeline.report import markdown_table

    tables = []
    for eps in dict.fromkeys(r["eps"] for r in m["runs"]):
        rows = []
        for s in g["start_ranges"]:
            row = {"S (m)": f"{float(s):g}"}
            for r in m["runs"]:
                if r["eps"] == eps and r["start_range"] == float(s):
                    row[f"K = {r['length']}"] = _cell(r)
            rows.append(row)
        rate = m["attack_success_rate"][f"{eps:g}"]
        tables.append(f"### eps = {eps:g}: the chaser missed or lost the target in {rate:.0%} of the runs\n\n"
                      f"{markdown_table(rows)}")
    law = ("the next true position is computed from the estimate, `p_new = p_est - clip(p_est - p_tar, -1, 1)` "
           "(the paper's variant: the chaser ends up where it believes it goes, so one wrong estimate moves the true "
           "chaser by as much as the estimate is wrong, and any estimate within 1 m per axis of the target point puts "
           "it exactly there; `guidance.variant: true_state` applies the command to the true state instead)"
           if m["variant"] == "paper" else
           "the command `clip(p_est - p_tar, -1, 1)` is computed from the estimate and applied to the true state")
    start, goal = (", ".join(f"{float(v):g}" for v in g[k]) for k in ("start", "target"))
    baseline = f"**No-attack baseline: {m['baseline']['outcome']}, final miss {m['baseline']['miss_m']:.2f} m.**"
    if m["baseline"]["outcome"] != "rendezvous held":
        baseline += (" The pose model cannot guide the chaser even without an attack, so a miss in the tables "
                     "below cannot be blamed on the attack.")
    return f"""# Closed-loop rendezvous under attack

The chaser starts at ({start}) m (the target's position relative to the chaser, target-centred frame,
approach along +z) and steers to ({goal}) m with at most {g['max_step']:g} m per axis per step: {law}.
Every step renders a new {render['width']}x{render['height']} Blender image (the pose model's input size)
at the true pose, the pose CNN estimates the target position, and the chaser re-points its camera
at where it believes the target is. {_horizon_text(m)} A run succeeds for
the chaser when it ends within {m['tolerance']:g} m of the target point; "target lost" means the
target's centre left the image, which ends the run. The attack ({m['method']} on the {m['loss']}
loss, images quantised to 8 bits as in `rpod attack`) starts at the first step at range <= S and
lasts K frames (fewer when the run ends first; the cell then says how many).

{baseline}

Cells: outcome, final distance to the target point.

{chr(10).join(tables)}
{m['renders']} rendered frames for {m['steps']} guidance steps (runs share the baseline's frames until
their attack starts), {m['attacked']} attacked frames, {m['seconds']:.0f} s.

![true trajectories](figures/guidance_trajectories.png)

The full paper grid (eps 0.5, 0.3, 0.1, 0.05, 0.01; S = 60..10 m; K = 5..20) runs with
`dvc exp run -S profile=paper` (everything at paper scale) or, on the current model,
`dvc exp run -S 'guidance.eps=[0.5,0.3,0.1,0.05,0.01]' -S 'guidance.start_ranges=[60,50,40,30,20,10]' -S 'guidance.lengths=[5,10,15,20]'`.
"""
