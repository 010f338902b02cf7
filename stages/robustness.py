"""`rpod robustness`: the safety evidence that can fail, and the shipped chain against attacks its detector never saw.

The chain that ships is the robust model (models/pose_robust.pt) with its own detector (models/detector_robust.pt)
and defense (models/defense.json). The integrity campaign (issue 39, pipeline/evaluation/campaign.py) flies it over
the first `integrity.trajectories` eval_render trajectories (flown with execution error, the chain told the
commands), and beside it the standard model's chain (models/pose.pt, models/detector.pt,
models/defense_standard.json: the paper's reproduction) and the undefended robust control (the shipped pose network,
no detector, no defense) over the first `integrity.comparison_trajectories`: every attacker of `integrity.attackers`
(capture from acquisition, drift, burst) at each eps of `integrity.eps` in increasing order (stopping after a
chain's breaking point with `integrity.stop_at_break`), judged by the measures that can fail: per trajectory the
largest error / AL (`integrity.alert_limit_kind`, the persistent-bias AL by default) on an available frame beside
the single-frame AL, error / PL, the final error; the worst over attackers; the breaking point per chain; Stanford
counts; HMI trajectories with Clopper-Pearson intervals. The page leads with them. The per-frame rows below run on
the shipped chain, and the page shows the two pose models side by side (clean and under the strongest-attack suite:
reports/metrics/robust.json).

Reads the shipped chain, models/surrogate.pt (`rpod train --surrogate`) and a
seeded sample of `robustness.frames` held-out test frames; every attacked image is stored as 8-bit
(`pipeline.attacks.gradient.quantize`) before it goes through the chain, as in the other stages. Rows:
- seen: FGSM on the training loss at robustness.eps (the attack the detector was trained on);
- transfer: FGSM at robustness.unseen_eps, and robustness.transfer (pgd, mifgsm, fgsm/position,
  fgsm/rotation: method[/loss]) at robustness.eps;
- adaptive: L-inf PGD on pose_loss - lambda * detector logit (pipeline.attacks.adaptive) per lambda and eps,
  plus the per-frame worst case over lambda;
- surrogate: robustness.surrogate_attacks crafted on the surrogate pose model, evaluated on ours;
- corruptions (not attacks): robustness.corruptions at camera-realistic strengths;
- fused (the chain that ships, issue 16: LSTM flag OR motion gate): the adaptive attack on the
  fused chain over whole bursts of the eval_render trajectories, evaluated by the real defense
  (pipeline.defense.fusion.run_defense) over each whole trajectory, clean frames included.
Params are checked on load (stages.config.evaluation.Robustness). Writes reports/robustness.md,
reports/metrics/robustness.json, reports/figures/robustness.png (text: stages/pages/robustness.py).
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import numpy as np

from pipeline.io.atomic import atomic_write_text, read_json, save_figure
from pipeline.io.errors import not_found
from pipeline.seeds import seed_for
from stages.artifacts.dvc import write_metrics
from stages.artifacts.models import load_chain, load_pose
from stages.artifacts.paths import INTEGRITY_FIGURE, PAPER, ROBUST_METRICS, SHIPPED, SURROGATE
from stages.artifacts.paths import ROBUSTNESS_FIGURE as FIGURE
from stages.artifacts.paths import ROBUSTNESS_METRICS as METRICS
from stages.artifacts.paths import ROBUSTNESS_REPORT as REPORT
from stages.config.device import torch_setup
from stages.config.evaluation import Robustness, attack_name
from stages.config.schema import Params
from stages.engine.campaigns import integrity_campaign
from stages.pages.calibrate import unmet_banner
from stages.pages.robustness import pose_models, robustness_page


def main(params: Params) -> None:
    """Run every attack and corruption row on held-out test frames; write the report, metrics and figure."""
    from pipeline.attacks.adaptive import PerFrameChain
    from pipeline.evaluation.robustness import run_attack_rows

    # the lambdas as floats, as the metrics echo them
    r = dataclasses.replace(params.robustness, lambdas=[float(v) for v in params.robustness.lambdas])
    for path in (SURROGATE, ROBUST_METRICS):
        if not path.exists():
            raise not_found(path)
    torch_setup(params)
    seed = seed_for(params.seed, "robustness")
    shipped, surrogate = load_chain(params, SHIPPED), load_pose(params, SURROGATE)
    chain = shipped.onboard
    images, targets, n_test = _test_frames(params, r.frames, seed)
    n = len(images)
    target = PerFrameChain(shipped.model, chain.shap, chain.detector)
    specs = _specs(params, r, target, shipped, surrogate, seed)
    n_corr = sum(len(v) for v in dataclasses.asdict(r.corruptions).values())
    bar, progress = _progress_bar(-(-n // r.batch_size) * (len(specs) + n_corr + 1))
    t0 = time.perf_counter()
    rows = run_attack_rows(
        chain,
        images,
        targets,
        specs,
        r.harm_m,
        r.batch_size,
        progress,
        pgd_is_lambda0="pgd" in r.transfer and 0.0 in r.lambdas,
    )
    shipped_threshold = shipped.defended.settings.threshold
    clean_harm, corruptions = _corruption_rows(chain, images, targets, r, seed, shipped_threshold, progress)
    bar.close()
    fused = integrity_campaign(params, shipped, seed)
    seconds, figure = time.perf_counter() - t0, fused.pop("figure")
    metrics = _metrics(r, shipped, surrogate, specs, rows, corruptions, clean_harm, fused, n, n_test, seconds)
    _write_outputs(params, metrics, rows, fused, figure)
    print(
        f"robustness: {len(rows)} attack rows, {len(corruptions)} corruption rows on {n} test frames and "
        f"{len(fused['integrity']['rows'])} integrity rows in {seconds:.0f} s -> {REPORT}, {METRICS}, {INTEGRITY_FIGURE}"
    )


def _progress_bar(total: int) -> tuple[Any, Any]:
    """(the stage's progress bar over `total` batches, a wrapper of an iterable that advances it per item)."""
    from tqdm import tqdm

    bar = tqdm(total=total, desc="robustness", unit="batch", dynamic_ncols=True)

    def progress(it: Any) -> Any:
        for item in it:
            yield item
            bar.update(1)

    return bar, progress


def _metrics(
    r: Robustness,
    shipped: Any,
    surrogate: Any,
    specs: list[Any],
    rows: list[dict[str, Any]],
    corruptions: list[dict[str, Any]],
    clean_harm: Any,
    fused: dict[str, Any],
    n: int,
    n_test: int,
    seconds: float,
) -> dict[str, Any]:
    """reports/metrics/robustness.json: the attack and corruption rows on `n` of `n_test` test frames, the integrity
    campaign's blocks (`fused`), the run's time (`seconds`, s) and the models' hashes."""
    from pipeline.evaluation.robustness import worst_by_eps

    return {
        "rows": rows,
        "corruptions": corruptions,
        "frames": n,
        "test_frames": n_test,
        "harm_m": r.harm_m,
        "steps": r.steps,
        "gradients_per_frame": sum(s.cost for s in specs),
        "lambdas": r.lambdas,
        "eps": r.eps,
        "threshold": shipped.onboard.threshold,
        "shipped_threshold": shipped.defended.settings.threshold,
        "clean_harmful_rate": clean_harm.value,
        "ci95_clean_harmful": clean_harm.ci(),
        "surrogate": {
            "best_epoch": int(surrogate.meta.get("epoch", 0)),
            "validation_position_m": float(surrogate.meta.get("val_pos_m", float("nan"))),
        },
        "model": SHIPPED.value,
        "model_hash": shipped.pose_hash,
        "surrogate_hash": surrogate.hash,
        "seconds": seconds,
        "minutes": seconds / 60,
        "worst_harmful_undetected": worst_by_eps(rows),
        **fused,
        "worst_harmful_undetected_fused": worst_by_eps(fused["fused_rows"]),
        "pose_models": pose_models(read_json(ROBUST_METRICS)),
    }


def _write_outputs(
    params: Params, metrics: dict[str, Any], rows: list[dict[str, Any]], fused: dict[str, Any], figure: Any
) -> None:
    """Write the metrics, the report (behind the unmet-calibration banners) and both figures."""
    from pipeline.report.figures import robustness_vs_eps

    write_metrics(METRICS, metrics, params.profile_name)
    atomic_write_text(
        REPORT,
        unmet_banner(fused["fused"]["calibration_unmet"])
        + unmet_banner(fused["integrity"]["chains"][PAPER.value]["calibration_unmet"], PAPER)
        + robustness_page(metrics, params),
    )
    worst_fused = [row for row in fused["fused_rows"] if row["lambda"] is None]
    save_figure(robustness_vs_eps([row for row in rows if row["attack"] != "adaptive pgd"] + worst_fused), FIGURE)
    save_figure(_integrity_figure(*figure), INTEGRITY_FIGURE)


def _test_frames(p: Params, frames: int, seed: int) -> tuple[np.ndarray, np.ndarray, int]:
    """(images (n, H, W, 3) uint8, labels (n, 9), test-split size) of a seeded sample of `frames` test frames."""
    from stages.artifacts.data import load_split

    split = load_split(p, "test")
    n = min(frames, len(split))
    pick = np.sort(np.random.default_rng(seed).choice(len(split), n, replace=False))
    return np.stack([np.asarray(split.images[int(i)]) for i in pick]), split.targets[pick], len(split)


def _specs(p: Params, r: Robustness, target: Any, pose: Any, surrogate: Any, seed: int) -> list[Any]:
    """The attack rows to run, in report order (pipeline.evaluation.robustness.attack_specs)."""
    from pipeline.evaluation.robustness import attack_specs

    a = p.attack
    transfer = [(name, *attack_name(name, "transfer")) for name in r.transfer]
    on_surrogate = [(name, *attack_name(name, "surrogate_attacks")) for name in r.surrogate_attacks]
    return attack_specs(
        pose,
        surrogate,
        target,
        eps=r.eps,
        unseen_eps=r.unseen_eps,
        transfer=transfer,
        lambdas=r.lambdas,
        surrogate_attacks=on_surrogate,
        steps=r.steps,
        mi_steps=a.steps,
        momentum=float(a.momentum),
        loss=a.loss,
        seed=seed,
    )


def _corruption_rows(
    chain: Any,
    images: np.ndarray,
    targets: np.ndarray,
    r: Robustness,
    seed: int,
    shipped_threshold: float,
    progress: Any,
) -> tuple[Any, list[dict[str, Any]]]:
    """(rate of clean frames beyond harm_m, corruption rows: `none` first, then each corruption and strength;
    false alarms at the detector's own threshold and at the shipped one, models/defense.json's)."""
    from pipeline.attacks.corruptions import corrupt
    from pipeline.defense.chain import run_sequence
    from pipeline.evaluation.robustness import corruption_row
    from pipeline.pose.metrics import pose_errors
    from pipeline.stats import rate

    none = np.zeros(len(images), bool)
    clean = run_sequence(chain, images, targets, none, None, r.batch_size, progress)
    clean_pos = pose_errors(clean.pose, targets)[0]
    rows = [corruption_row("none", 0.0, clean_pos, clean.flag, clean.prob >= shipped_threshold)]
    for name, strengths in dataclasses.asdict(r.corruptions).items():
        for s in strengths:
            res = run_sequence(chain, corrupt(name, s, seed)(images), targets, none, None, r.batch_size, progress)
            rows.append(
                corruption_row(name, s, pose_errors(res.pose, targets)[0], res.flag, res.prob >= shipped_threshold)
            )
    return rate(clean_pos > r.harm_m), rows


def _integrity_figure(clean: list[Any], top: list[tuple[str, list[Any], list[np.ndarray]]], eps: float) -> Any:
    """The Stanford diagram of every attacker at `eps` (integrity_runs.diagram_eps: the largest with a plotted attacked
    frame) and the clean runs, and trajectory 0 over frames."""
    from pipeline.evaluation.integrity_runs import diagram_points
    from pipeline.report.figures import integrity_diagram
    from stages.pages.integrity import attacker_names

    every = [np.ones(len(c.pose), bool) for c in clean]
    points = {
        "no attack": diagram_points(clean, every),
        **{f"{attacker_names(name)}, eps {eps:g}": diagram_points(flown, masks) for name, flown, masks in top},
    }
    series = {
        "no attack": clean[0].frames.error,
        **{f"{attacker_names(name)}, eps {eps:g}": flown[0].frames.error for name, flown, _ in top},
    }
    return integrity_diagram(
        points,
        series,
        clean[0].frames.alert,
        f"Trusted estimate against its bound, eps {eps:g} (counted frames: from the first attacked one)",
    )
