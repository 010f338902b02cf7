"""`rpod evaluate`: the safety chains on fresh trajectories, frame by frame.

On the trajectories `rpod eval_render` rendered into datasets/eval_render/ it runs, per eps and
trajectory, every frame through
  image -> (FGSM against that frame's true label when the schedule says so) -> pose -> exact SHAP
  -> detector flag,
once for each chain (stages.artifacts.paths.CHAINS): the **standard** model with its own detector (the
paper's reproduction: the detection accuracy tables and the timeline) and the **robust** model with its
own detector (the chain that ships), each attack crafted on that chain's pose model. Then the recorded
frames go through the defense calibrated for each chain (`rpod calibrate`, pipeline/defense/fusion.py):
the paper's LSTM alone (standard model), the defended standard chain, and the defended robust chain
that ships (metrics `fused`). Writes reports/integrated.md, reports/figures/timeline.png and
reports/metrics/evaluate.json.
"""

from __future__ import annotations

import dataclasses
import time
from typing import TYPE_CHECKING, Any

import numpy as np
import typer

from pipeline.geometry.labels import TARGET
from pipeline.io.atomic import atomic_write_text, save_figure
from pipeline.seeds import seed_for
from stages.artifacts.dvc import write_metrics
from stages.artifacts.models import load_chain
from stages.artifacts.paths import EVALUATE_FIGURE as FIGURE
from stages.artifacts.paths import EVALUATE_METRICS as METRICS
from stages.artifacts.paths import EVALUATE_REPORT as REPORT
from stages.artifacts.paths import PAPER, SHIPPED, Model
from stages.artifacts.readers import chaser_motion, read_eval_render
from stages.config.device import torch_setup
from stages.config.evaluation import Evaluate
from stages.config.params import evaluation_seed
from stages.config.schema import Params
from stages.pages.calibrate import unmet_banner
from stages.pages.evaluate import chain_names, clamp_section, defense_section, rates_section
from stages.pages.paper import ATTACK_LENGTH, INTEGRATED, INTEGRATED_EPS, P_START, by_eps, frames_note

if TYPE_CHECKING:
    from pipeline.evaluation.sequences import Sequence


@dataclasses.dataclass(frozen=True)
class ChainRun:
    """One chain's pass over the evaluation trajectories: the chain (pipeline.defense.chain.SafetyChain, with its
    calibrated defense) and what `pipeline.evaluation.sequences.evaluate_sequences` measured."""

    model: Model
    chain: Any
    result: Any


def main(params: Params) -> None:
    """Detect FGSM attacks frame by frame on fresh trajectories with the paper's and the shipped chain.

    Params: `seed` (the trajectories' base seed follows it), `evaluate` (trajectories, frames, lateral_range,
    p_start, attack_length, eps, batch_size), `defense`, plus `render`/`camera` for the images and `attack.loss` for the FGSM loss.
    """
    from pipeline.evaluation.sequences import nan_to_none, per_eps_summary

    e = params.evaluate
    torch_setup(params)
    images, poses, meta = read_eval_render(params)
    base = evaluation_seed(params)
    sequences = _sequences(images, poses, e, base)
    t0 = time.perf_counter()
    paper, shipped = (_run_chain(params, model, sequences) for model in (PAPER, SHIPPED))
    fused = _defended(params, paper, shipped, sequences)
    seconds = time.perf_counter() - t0
    res, chain = paper.result, paper.chain
    shipped_cal = shipped.chain.calibration
    summary = per_eps_summary(res.rows)
    eps_fig = _timeline(e, sequences, res, chain.threshold)
    clamp = _clamp_heldout(params, images, poses)
    metrics = _metrics(params, paper, shipped, fused, sequences, summary, meta, seconds, clamp)
    write_metrics(METRICS, nan_to_none(metrics), params.profile_name)
    atomic_write_text(
        REPORT,
        unmet_banner(shipped_cal.unmet)
        + unmet_banner(paper.chain.calibration.unmet, PAPER)
        + report(res.rows, summary, res.clean, sequences, e, meta, chain.threshold, eps_fig, params.profile_name, base)
        + defense_section(fused, shipped_cal.to_json(), params.defense.harm_m, e.attack_length, _shipped_clean(shipped))
        + clamp_section(clamp, base),
    )
    typer.echo(
        f"evaluate: {len(sequences)} trajectories x {len(e.eps)} eps, standard and robust chain in "
        f"{seconds:.0f} s; mean accuracy (standard, paper's view) {100 * metrics['accuracy_mean']:.2f}% "
        f"-> {REPORT}, {FIGURE}"
    )


def _timeline(e: Evaluate, sequences: list[Sequence], res: Any, threshold: float) -> float:
    """Save the detection timeline of the first trajectory at the smallest eps (reports/figures/timeline.png);
    returns that eps."""
    from pipeline.report.figures import detection_timeline

    eps_fig = min(e.eps)
    s0 = sequences[0]
    title = (
        f"{s0.name}: FGSM eps={eps_fig:g} on {int(s0.attacked.sum())} of {len(s0.attacked)} "
        f"frames ({e.attack_length}-frame attacks, p_start={e.p_start:g}); standard model"
    )
    save_figure(
        detection_timeline(s0.poses["tz"].to_numpy(), s0.attacked, res.traces[(eps_fig, s0.name)], threshold, title),
        FIGURE,
    )
    return eps_fig


def _metrics(
    params: Params,
    paper: ChainRun,
    shipped: ChainRun,
    fused: dict[str, Any],
    sequences: list[Sequence],
    summary: list[dict[str, Any]],
    meta: dict[str, Any],
    seconds: float,
    clamp: dict[str, float],
) -> dict[str, Any]:
    """reports/metrics/evaluate.json: the standard chain's detection (per eps, rates), the shipped chain's, the
    defended chains' rows (`fused`), the clamp's held-out statistics and the run's time (`seconds`, s)."""
    from pipeline.attacks.schedule import attacked_fraction
    from pipeline.evaluation.rates import sequence_rates
    from pipeline.evaluation.sequences import rates_json

    e = params.evaluate
    res, chain = paper.result, paper.chain
    names = list(fused)
    return {
        "model": PAPER.value,
        "model_hash": paper.chain.pose_hash,
        "frames_per_trajectory": e.frames,
        "trajectories": len(sequences),
        "p_start": e.p_start,
        "attack_length": e.attack_length,
        "threshold": chain.threshold,
        "seconds": seconds,
        "accuracy_mean": float(np.mean([r["accuracy"] for r in summary])),
        "per_eps": {f"{r['eps']:g}": r for r in summary},
        "rows": res.rows,
        "clean": res.clean,
        "attacked_fraction": {s.name: float(s.attacked.mean()) for s in sequences},
        "start_xy": meta["start_xy"],
        "shipped": _shipped_metrics(shipped),
        "black_level_heldout": clamp,
        "rates": {
            f"{e:g}": r.as_json(attacked_fraction(P_START, ATTACK_LENGTH)) for e, r in sequence_rates(res.rows).items()
        },
        "fused": {
            "fusion": shipped.chain.defended.settings.fusion,
            "harm_m": params.defense.harm_m,
            "chains": chain_names(params.defense.fusion),
            **{
                key: {f"{r['eps']:g}": r for r in rates_json(fused[name])}
                for key, name in zip(("paper_per_eps", "standard_per_eps", "per_eps"), names)
            },
        },
    }


def _clamp_heldout(params: Params, images: Any, poses: Any) -> dict[str, float]:
    """The black-level clamp's statistics (pipeline.pose.robustness.black_level_stats: the robust model's threshold
    train.adversarial.black_level against the background under the simulated lab shift lab.domain_shift, and the
    target values it erases) on the evaluation frames over a black background, which the threshold's choice did
    not read."""
    from pipeline.pose.robustness import black_level_stats
    from stages.artifacts.data import backgrounds

    shift = params.lab.domain_shift
    return black_level_stats(
        images,
        float(params.train.adversarial.black_level),
        float(shift.noise_std),
        float(shift.blur_sigma),
        seed_for(evaluation_seed(params), "evaluate.black_level"),
        backgrounds=backgrounds(poses),
    )


def _sequences(images: np.ndarray, poses: Any, e: Evaluate, base: int) -> list[Sequence]:
    """The evaluation trajectories as chain sequences with their motion and attack schedules seeded from `base`."""
    from pipeline.attacks.schedule import attack_schedule
    from pipeline.evaluation.sequences import Sequence

    out = []
    for tr, g in poses.groupby("trajectory", sort=True):
        idx = g["index"].to_numpy()
        R_cam, u = chaser_motion(g)
        out.append(
            Sequence(
                name=f"T{int(tr) + 1}",
                images=images[idx],
                poses=g.reset_index(drop=True),
                targets=g[TARGET].to_numpy(np.float32),
                R_cam=R_cam,
                u=u,
                rel=g[["rel_x", "rel_y", "rel_z"]].to_numpy(np.float64),
                attacked=attack_schedule(
                    len(idx), e.p_start, e.attack_length, seed_for(base, "evaluate.schedule", int(tr))
                ),
            )
        )
    return out


def _run_chain(params: Params, model: Model, sequences: list[Sequence]) -> ChainRun:
    """One chain (its pose model, its detector, its calibrated defense) over every sequence, clean and at every
    eps of `evaluate.eps` (FGSM crafted on that chain's pose model)."""
    from pipeline.attacks.gradient import attack_loss
    from pipeline.evaluation.sequences import evaluate_sequences

    e = params.evaluate
    chain = load_chain(params, model)
    res = evaluate_sequences(
        chain.onboard,
        attack_loss(params.attack.loss, chain.loss),
        sequences,
        e.eps,
        e.attack_length,
        e.batch_size,
        f"evaluate ({model.value} model)",
    )
    return ChainRun(model, chain, res)


def _defended(params: Params, paper: ChainRun, shipped: ChainRun, sequences: list[Sequence]) -> dict[str, Any]:
    """The recorded frames through the defenses: the paper's LSTM alone at its own threshold and the defended
    standard chain (both on the standard model's frames, its defense file), then the defended shipped chain."""
    from pipeline.evaluation.sequences import defended_summary

    e, harm, names = params.evaluate, params.defense.harm_m, chain_names(params.defense.fusion)
    d = paper.chain.defended
    lstm_alone = dataclasses.replace(
        d.settings,
        fusion="paper",
        threshold=paper.chain.threshold,
        update_below=min(d.settings.update_below or 1.0, paper.chain.threshold),
    )
    cases = (
        (names["paper"], paper, lstm_alone),
        (names["standard"], paper, d.settings),
        (names["shipped"], shipped, shipped.chain.defended.settings),
    )
    return {
        name: defended_summary(
            run.result.traces,
            sequences,
            e.eps,
            settings,
            run.chain.defended.motion,
            run.chain.defended.noise,
            e.attack_length,
            harm,
        )
        for name, run, settings in cases
    }


def _shipped_metrics(run: ChainRun) -> dict[str, Any]:
    """metrics `shipped`: the robust chain's model hash, its detector's own threshold, and per eps its per-frame
    detection at that threshold (its defended rows are under `fused`)."""
    from pipeline.evaluation.sequences import per_eps_summary

    return {
        "model": run.model.value,
        "model_hash": run.chain.pose_hash,
        "threshold": run.chain.threshold,
        "defense_threshold": run.chain.defended.settings.threshold,
        "clean": run.result.clean,
        "per_eps": {f"{r['eps']:g}": r for r in per_eps_summary(run.result.rows)},
    }


def _shipped_clean(run: ChainRun) -> dict[str, float]:
    """The shipped chain's clean pose errors over the evaluation trajectories (m, deg; equal frames each)."""
    clean = run.result.clean.values()
    return {
        "position_m": float(np.mean([c["position_mean_m"] for c in clean])),
        "attitude_deg": float(np.mean([c["attitude_mean_deg"] for c in clean])),
    }


def report(
    rows: list[dict[str, Any]],
    summary: list[dict[str, Any]],
    clean: dict[str, dict[str, float]],
    sequences: list[Sequence],
    e: Evaluate,
    meta: dict[str, Any],
    threshold: float,
    eps_fig: float,
    profile: str,
    evaluation_base: int,
) -> str:
    from pipeline.evaluation.sequences import accuracy_table
    from pipeline.report.markdown import markdown_table

    names = [s.name for s in sequences]
    att_frac = np.mean([s.attacked.mean() for s in sequences])
    mean_acc = 100 * np.mean([s["accuracy"] for s in summary])
    starts = ", ".join(f"{n} ({x:+.1f}, {y:+.1f}) m" for n, (x, y) in zip(names, meta["start_xy"]))
    return f"""# Integrated evaluation: the safety chains frame by frame

Which model: every table above "The defended chains" is the paper's reproduction, the **standard
model** (models/pose.pt) with its own detector (models/detector.pt); the defended section adds the chain
that ships, the **robust model** (models/pose_robust.pt) with its own detector (models/detector_robust.pt).

{len(names)} fresh trajectories (never seen in training; base seed {evaluation_base}, following `seed`), {e.frames} frames each, from 60 m
with lateral start offsets {starts} along a projectile-shaped path to (0, 0, 10) m, each planned step flown
with the thrusters' execution error (`guidance.execution`; the defense is told the commands). Every frame goes
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
{meta["width"]}x{meta["height"]}). {frames_note()}

## Rates and the attacked fraction

{rates_section(rows, ATTACK_LENGTH, by_eps(INTEGRATED_EPS), "trajectories")}
""" + _detail_section(summary, clean, names[0], eps_fig)


def _detail_section(
    summary: list[dict[str, Any]], clean: dict[str, dict[str, float]], first: str, eps_fig: float
) -> str:
    """The report's tail: the rates and pose errors the paper did not report, the clean held-out-trajectory errors
    and the timeline of trajectory `first` at `eps_fig`."""
    from pipeline.evaluation.sequences import detail_table
    from pipeline.report.markdown import markdown_table

    clean_rows = _clean_rows(clean)
    return f"""## What the paper did not report

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

Timeline of {first} at eps = {eps_fig:g}: true and estimated range, the detector's probability and
flags, and the position error (red crosses: attacked frames that were not flagged).
"""


def _clean_rows(clean: dict[str, dict[str, float]]) -> list[dict[str, Any]]:
    """The clean pose-error table rows: per trajectory its false-positive rate (%) and mean position (m) and attitude
    (deg) errors, then their means over the trajectories."""
    from pipeline.evaluation.sequences import pct

    clean_rows = [
        {
            "trajectory": n,
            "FPR % (no attack)": pct(c["fpr"]),
            "position error (m)": c["position_mean_m"],
            "attitude error (deg)": c["attitude_mean_deg"],
        }
        for n, c in clean.items()
    ]
    clean_rows.append(
        {
            "trajectory": "all (equal frames each)",
            "FPR % (no attack)": pct(float(np.mean([c["fpr"] for c in clean.values()]))),
            "position error (m)": float(np.mean([c["position_mean_m"] for c in clean.values()])),
            "attitude error (deg)": float(np.mean([c["attitude_mean_deg"] for c in clean.values()])),
        }
    )
    return clean_rows
