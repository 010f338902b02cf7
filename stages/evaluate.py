"""`rpod evaluate`: the whole safety chain on fresh trajectories, frame by frame.

On the trajectories `rpod eval_render` rendered into datasets/eval_render/ it runs, per eps and
trajectory, every frame through
  image -> (FGSM against that frame's true label when the schedule says so) -> pose -> exact SHAP
  -> detector flag, then the recorded frames through the defense calibrated by `rpod calibrate`
  (motion check fused with the detector, pipeline/defense/fusion.py), and writes reports/integrated.md,
  reports/figures/timeline.png and reports/metrics/evaluate.json (the defended chain under `fused`).
"""
from __future__ import annotations

import dataclasses
import time
from typing import TYPE_CHECKING, Any

import numpy as np
import typer

from pipeline.io.atomic import atomic_write_text, save_figure
from pipeline.pose.labels import TARGET
from stages.artifacts.dvc import write_metrics
from stages.artifacts.paths import EVALUATE_FIGURE as FIGURE, EVALUATE_METRICS as METRICS, \
    EVALUATE_REPORT as REPORT, SEED_OFFSET
from stages.artifacts.readers import chaser_motion, read_eval_render
from stages.artifacts.models import load_chain, load_defense
from stages.config.device import torch_setup
from stages.config.evaluation import Evaluate
from stages.config.schema import Params
from stages.pages.evaluate import defense_section
from stages.pages.paper import INTEGRATED, INTEGRATED_EPS, by_eps
from stages.pages.calibrate import unmet_banner

if TYPE_CHECKING:
    from pipeline.evaluation.sequences import Sequence


def main(params: Params) -> None:
    """Detect FGSM attacks frame by frame on fresh trajectories with the whole safety chain.

    Params: `evaluate` (trajectories, frames, lateral_range, p_start, attack_length, eps, seed,
    batch_size), `defense`, plus `render`/`camera` for the images and `attack.loss` for the FGSM loss.
    """
    e = params.evaluate
    from pipeline.evaluation.sequences import (Sequence, defended_summary, evaluate_sequences, nan_to_none,
                                               per_eps_summary, rates_json)
    from pipeline.report.figures import detection_timeline
    from pipeline.evaluation.schedule import attack_schedule

    torch_setup(params)
    images, poses, meta = read_eval_render(params)
    chain, loss_fn, model_hash = load_chain(params)
    defense = load_defense(params, model_hash, chain.threshold)
    eps_list, length = e.eps, e.attack_length
    sequences = []
    for tr, g in poses.groupby("trajectory", sort=True):
        idx = g["index"].to_numpy()
        R_cam, u = chaser_motion(g)
        sequences.append(Sequence(name=f"T{int(tr) + 1}", images=images[idx], poses=g.reset_index(drop=True),
                                  targets=g[TARGET].to_numpy(np.float32), R_cam=R_cam, u=u,
                                  rel=g[["rel_x", "rel_y", "rel_z"]].to_numpy(np.float64),
                                  attacked=attack_schedule(len(idx), e.p_start, length,
                                                           e.seed + SEED_OFFSET["evaluate_schedule"] + int(tr))))
    t0 = time.perf_counter()
    res = evaluate_sequences(chain, loss_fn, sequences, eps_list, length, e.batch_size, "evaluate")
    harm = params.defense.harm_m
    # the paper's row: the LSTM alone at its own threshold (detector.pt); the defended chain: the calibrated one
    paper = dataclasses.replace(defense.settings, fusion="paper", threshold=chain.threshold,
                                update_below=min(params.defense.update_below or 1.0, chain.threshold))
    fused = {name: defended_summary(res.traces, sequences, eps_list, s, defense.motion, defense.noise, length, harm)
             for name, s in (("paper (LSTM alone)", paper), (f"defended ({defense.settings.fusion})", defense.settings))}
    seconds = time.perf_counter() - t0
    summary = per_eps_summary(res.rows)
    eps_fig = min(eps_list)
    s0 = sequences[0]
    title = (f"{s0.name}: FGSM eps={eps_fig:g} on {int(s0.attacked.sum())} of {len(s0.attacked)} "
             f"frames ({length}-frame attacks, p_start={e.p_start:g})")
    save_figure(detection_timeline(s0.poses["tz"].to_numpy(), s0.attacked, res.traces[(eps_fig, s0.name)],
                                   chain.threshold, title), FIGURE)
    metrics = {"model_hash": model_hash, "frames_per_trajectory": e.frames, "trajectories": len(sequences),
               "p_start": e.p_start, "attack_length": length, "threshold": chain.threshold,
               "seconds": seconds, "accuracy_mean": float(np.mean([r["accuracy"] for r in summary])),
               "per_eps": {f"{r['eps']:g}": r for r in summary},
               "rows": res.rows, "clean": res.clean,
               "attacked_fraction": {s.name: float(s.attacked.mean()) for s in sequences},
               "start_xy": meta["start_xy"],
               "fused": {"fusion": defense.settings.fusion, "harm_m": harm,
                         "per_eps": {f"{r['eps']:g}": r for r in rates_json(list(fused.values())[-1])},
                         "paper_per_eps": {f"{r['eps']:g}": r for r in rates_json(fused["paper (LSTM alone)"])}}}
    write_metrics(METRICS, nan_to_none(metrics), params.profile_name)
    atomic_write_text(REPORT, unmet_banner(defense.calibration)
                      + report(res.rows, summary, res.clean, sequences, e, meta, chain.threshold, eps_fig,
                               params.profile_name)
                      + defense_section(fused, defense.calibration, harm, e.attack_length))
    typer.echo(f"evaluate: {len(sequences)} trajectories x {len(eps_list)} eps in {seconds:.0f} s; mean accuracy "
               f"{100 * metrics['accuracy_mean']:.2f}% -> {REPORT}, {FIGURE}")


def report(rows: list[dict[str, Any]], summary: list[dict[str, Any]], clean: dict[str, dict[str, float]],
           sequences: list[Sequence], e: Evaluate, meta: dict[str, Any], threshold: float,
           eps_fig: float, profile: str) -> str:
    from pipeline.evaluation.sequences import accuracy_table, detail_table, pct
    from pipeline.report.markdown import markdown_table

    names = [s.name for s in sequences]
    att_frac = np.mean([s.attacked.mean() for s in sequences])
    mean_acc = 100 * np.mean([s["accuracy"] for s in summary])
    starts = ", ".join(f"{n} ({x:+.1f}, {y:+.1f}) m" for n, (x, y) in zip(names, meta["start_xy"]))
    clean_rows = [{"trajectory": n, "FPR % (no attack)": pct(c["fpr"]), "position error (m)": c["position_mean_m"],
                   "attitude error (deg)": c["attitude_mean_deg"]} for n, c in clean.items()]
    clean_rows.append({"trajectory": "all (equal frames each)",
                       "FPR % (no attack)": pct(float(np.mean([c["fpr"] for c in clean.values()]))),
                       "position error (m)": float(np.mean([c["position_mean_m"] for c in clean.values()])),
                       "attitude error (deg)": float(np.mean([c["attitude_mean_deg"] for c in clean.values()]))})
    return f"""# Integrated evaluation: the safety chain frame by frame

{len(names)} fresh trajectories (never seen in training; seed {e.seed}), {e.frames} frames each, from 60 m
with lateral start offsets {starts} along a projectile-shaped path to (0, 0, 10) m. Every frame goes
through the chain as onboard: image -> (FGSM against that frame's true label, stored as an 8-bit
image, when the schedule attacks it) -> pose -> exact SHAP of the GAP features -> LSTM detector
(threshold {threshold:.3f}). A frame outside an attack starts one with probability {e.p_start:g};
each attack lasts {e.attack_length} frames, so {100 * att_frac:.1f}% of the frames are attacked
(the same schedule for every eps). Accuracy counts frames, as the paper does: correctly classified
frames / all frames (time: reports/metrics/evaluate.json).

## Detection accuracy (%)

{markdown_table(accuracy_table(rows, summary, names, by_eps(INTEGRATED_EPS)), decimals=2)}
Mean over eps: **{mean_acc:.2f}%** (paper: {INTEGRATED}% overall, from 2,500-frame trajectories at
480x270 with the full-width network; ours: the {profile} profile's {e.frames} frames at
{meta['width']}x{meta['height']}).

## What the paper did not report

Rates averaged over the trajectories; the delay is the number of frames from an attack's first
frame to its first flag (0 = flagged at once), over the attacks flagged at all; a missed attack
has no flag in any of its frames. The pose errors are position errors on the attacked frames the
detector let through (the ones guidance would act on), and on all attacked frames.

{markdown_table(detail_table(summary), decimals=2)}
Without any attack (the same frames, clean). The trajectories are whole sequences never rendered
for training, so these pose errors are the **held-out-trajectory** errors, beside the per-frame test
split's (reports/pose.md, whose test frames lie between training frames of the same sequences):

{markdown_table(clean_rows, decimals=2)}
![timeline](figures/timeline.png)

Timeline of {names[0]} at eps = {eps_fig:g}: true and estimated range, the detector's probability and
flags, and the position error (red crosses: attacked frames that were not flagged).
"""
