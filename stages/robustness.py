"""`rpod robustness`: the shipped safety chain against attacks its detector never saw.

Reads models/pose.pt, models/detector.pt, models/surrogate.pt (`rpod train --surrogate`) and a
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

from pipeline.io.atomic import atomic_write_text, save_figure
from pipeline.io.errors import not_found
from pipeline.pose.labels import TARGET
from stages.artifacts.dvc import write_metrics
from stages.artifacts.paths import DETECTOR, POSE, ROBUSTNESS_FIGURE as FIGURE, ROBUSTNESS_METRICS as METRICS, \
    ROBUSTNESS_REPORT as REPORT, SEED_OFFSET, SURROGATE
from stages.artifacts.readers import read_eval_render
from stages.artifacts.models import Pose, load_defense, load_pose
from stages.config.device import torch_setup
from stages.config.evaluation import Robustness, attack_name
from stages.config.schema import Params
from stages.errors import StageError
from stages.pages.robustness import robustness_page
from stages.pages.calibrate import unmet_banner


def main(params: Params) -> None:
    """Run every attack and corruption row on held-out test frames; write the report, metrics and figure."""
    from tqdm import tqdm

    from pipeline.attacks.adaptive import PerFrameChain
    from pipeline.defense.chain import load_onboard_chain
    from pipeline.report.figures import robustness_vs_eps
    from pipeline.evaluation.robustness import run_attack_rows, worst_by_eps
    from stages.artifacts.data import load_split

    # the lambdas as floats, as the metrics echo them
    r = dataclasses.replace(params.robustness, lambdas=[float(v) for v in params.robustness.lambdas])
    if not SURROGATE.exists():
        raise not_found(SURROGATE)
    torch_setup(params)
    seed = params.seed + SEED_OFFSET["robustness"]
    pose, surrogate = load_pose(params), load_pose(params, SURROGATE)
    chain = load_onboard_chain(pose.model, pose.hash, POSE, DETECTOR)
    split = load_split(params, "test")
    n = min(r.frames, len(split))
    pick = np.sort(np.random.default_rng(seed).choice(len(split), n, replace=False))
    images = np.stack([np.asarray(split.images[int(i)]) for i in pick])
    targets = split.targets[pick]

    target = PerFrameChain(pose.model, chain.shap, chain.detector)
    specs = _specs(params, r, target, pose, surrogate, seed)
    n_corr = sum(len(v) for v in dataclasses.asdict(r.corruptions).values())
    bar = tqdm(total=-(-n // r.batch_size) * (len(specs) + n_corr + 1), desc="robustness", unit="batch",
               dynamic_ncols=True)

    def progress(it: Any) -> Any:
        for item in it:
            yield item
            bar.update(1)

    t0 = time.perf_counter()
    rows = run_attack_rows(chain, images, targets, specs, r.harm_m, r.batch_size, progress,
                           pgd_is_lambda0="pgd" in r.transfer and 0.0 in r.lambdas)
    clean_harm, corruptions = _corruption_rows(chain, images, targets, r, seed, progress)
    bar.close()
    fused = _fused_rows(params, r, chain, target, seed, pose.hash)
    seconds = time.perf_counter() - t0
    metrics = {"rows": rows, "corruptions": corruptions, "frames": n, "test_frames": len(split), "harm_m": r.harm_m,
               "steps": r.steps, "gradients_per_frame": sum(s.cost for s in specs), "lambdas": r.lambdas,
               "eps": r.eps, "threshold": chain.threshold,
               "clean_harmful_rate": clean_harm.value, "ci95_clean_harmful": clean_harm.ci(),
               "surrogate": {"best_epoch": int(surrogate.meta.get("epoch", 0)),
                             "validation_position_m": float(surrogate.meta.get("val_pos_m", float("nan")))},
               "model_hash": pose.hash, "surrogate_hash": surrogate.hash, "seconds": seconds,
               "worst_harmful_undetected": worst_by_eps(rows), **fused,
               "worst_harmful_undetected_fused": worst_by_eps(fused["fused_rows"])}
    write_metrics(METRICS, metrics, params.profile_name)
    atomic_write_text(REPORT, unmet_banner({"unmet": fused["fused"]["calibration_unmet"]}) + robustness_page(metrics, params))
    worst_fused = [row for row in fused["fused_rows"] if row["lambda"] is None]
    save_figure(robustness_vs_eps([row for row in rows if row["attack"] != "adaptive pgd"] + worst_fused), FIGURE)
    print(f"robustness: {len(rows)} attack rows and {len(corruptions)} corruption rows on {n} test frames in "
          f"{seconds:.0f} s -> {REPORT}, {METRICS}, {FIGURE}")


def _specs(p: Params, r: Robustness, target: Any, pose: Pose, surrogate: Pose, seed: int) -> list[Any]:
    """The attack rows to run, in report order (pipeline.evaluation.robustness.attack_specs)."""
    from pipeline.evaluation.robustness import attack_specs

    a = p.attack
    transfer = [(name, *attack_name(name, "transfer")) for name in r.transfer]
    on_surrogate = [(name, *attack_name(name, "surrogate_attacks")) for name in r.surrogate_attacks]
    return attack_specs(pose, surrogate, target, eps=r.eps, unseen_eps=r.unseen_eps, transfer=transfer,
                        lambdas=r.lambdas, surrogate_attacks=on_surrogate, steps=r.steps, mi_steps=a.steps,
                        momentum=float(a.momentum), loss=a.loss, seed=seed)


def _corruption_rows(chain: Any, images: np.ndarray, targets: np.ndarray, r: Robustness, seed: int,
                     progress: Any) -> tuple[Any, list[dict[str, Any]]]:
    """(rate of clean frames beyond harm_m, corruption rows: `none` first, then each corruption and strength)."""
    from pipeline.defense.chain import run_sequence
    from pipeline.attacks.corruptions import corrupt
    from pipeline.evaluation.robustness import corruption_row
    from pipeline.evaluation.stats import rate
    from pipeline.pose.metrics import pose_errors

    none = np.zeros(len(images), bool)
    clean = run_sequence(chain, images, targets, none, None, r.batch_size, progress)
    clean_pos = pose_errors(clean.pose, targets)[0]
    rows = [corruption_row("none", 0.0, clean_pos, clean.flag)]
    for name, strengths in dataclasses.asdict(r.corruptions).items():
        for s in strengths:
            res = run_sequence(chain, corrupt(name, s, seed)(images), targets, none, None, r.batch_size, progress)
            rows.append(corruption_row(name, s, pose_errors(res.pose, targets)[0], res.flag))
    return rate(clean_pos > r.harm_m), rows


def _fused_rows(p: Params, r: Robustness, chain: Any, target: Any, seed: int, model_hash: str) -> dict[str, Any]:
    """Adaptive attack on the fused chain (LSTM flag OR motion gate, pipeline.defense.fusion) over bursts of
    `evaluate.attack_length` frames every `robustness.burst_every` frames of each eval_render
    trajectory, per eps and lambda and the per-burst worst case over lambda; rates with bootstrap
    intervals over trajectories. Also the fused chain's false-alarm rate on the clean trajectories."""
    import torch
    from tqdm import tqdm

    from pipeline.attacks.adaptive import adaptive_pgd
    from pipeline.attacks.gradient import attack_loss
    from pipeline.evaluation.robustness import fused_bursts, fused_row, worst_burst_over_lambda

    images, labels, trajs, bursts, defended, info = _fused_setup(p, r, chain, model_hash)
    full = attack_loss(p.attack.loss, load_pose(p).loss)
    rows = []
    bar = tqdm(total=len(r.eps) * len(r.lambdas) * len(trajs), desc="robustness (fused)", unit="trajectory")
    for i, e in enumerate(r.eps):
        runs = []
        for lam in r.lambdas:
            def craft(fused: Any, x: Any, y: Any, e: float = e, lam: float = lam) -> Any:
                return adaptive_pgd(fused, x, y, e, full, lam, steps=r.steps,
                                    generator=torch.Generator().manual_seed(seed + 700 + i))
            runs.append(fused_bursts(chain, target, defended, images, labels, trajs, bursts, craft, r.batch_size,
                                     lambda: bar.update(1)))
            rows.append(fused_row("fused chain: adaptive pgd", e, lam, *runs[-1][:3], r.harm_m))
        wp, wf = worst_burst_over_lambda([v[0] for v in runs], [v[1] for v in runs], runs[0][3], r.harm_m)
        rows.append(fused_row("fused chain: adaptive pgd, worst over lambda", e, None, wp, wf, runs[0][2], r.harm_m))
    bar.close()
    return {"fused_rows": rows, "fused": info}


def _fused_setup(p: Params, r: Robustness, chain: Any, model_hash: str) -> tuple[Any, ...]:
    """(eval_render images, labels (N, 9), frame indices per trajectory, bursts per trajectory, the
    defended-chain settings, facts incl. the fused chain's false-alarm rate on the clean trajectories)."""
    from pipeline.evaluation.robustness import Defended, burst_schedule, fused_false_alarms

    images, poses, _ = read_eval_render(p)
    labels = poses[TARGET].to_numpy(np.float64)
    trajs = [np.flatnonzero(poses["trajectory"].to_numpy() == t) for t in np.unique(poses["trajectory"])]
    # the defense that ships: params.defense with the noise model `rpod calibrate` fitted on validation trajectories
    shipped = load_defense(p, model_hash, chain.threshold)
    defended = Defended(shipped.settings, shipped.motion, shipped.noise)
    length = p.evaluate.attack_length
    try:
        bursts = [burst_schedule(len(ix), length, r.burst_every) for ix in trajs]
    except ValueError as e:
        raise StageError(f"params.yaml robustness.burst_every / evaluate.attack_length: {e}") from None
    # the fused chain on the clean trajectories: its false alarms
    alarms = fused_false_alarms(chain, defended, images, labels, trajs, r.batch_size)
    info = {"trajectories": len(trajs), "bursts": sum(len(b) for b in bursts), "burst_length": length,
            "burst_every": r.burst_every, "false_alarm_rate": alarms.value, "ci95_false_alarm": alarms.ci(),
            "noise_model": defended.noise.as_dict(), "gate": defended.motion.gate,
            "gate_false_alarm": defended.motion.false_alarm, "noise_inflation": shipped.calibration.get("inflation", 1.0),
            "fusion": defended.settings.fusion, "calibration_unmet": shipped.calibration.get("unmet", []),
            "noise_fitted_on": "validation trajectories (models/defense.json, rpod calibrate)"}
    return images, labels, trajs, bursts, defended, info
