"""`rpod robustness`: the shipped safety chain against attacks its detector never saw.

The chain that ships is the robust model (models/pose_robust.pt) with its own detector
(models/detector_robust.pt) and defense (models/defense.json): every row below runs on it. Beside it, the
standard model's chain (models/pose.pt, models/detector.pt, models/defense_standard.json: the paper's
reproduction) gets the integrity rows of `integrity.standard_attackers` on the first
`integrity.standard_trajectories` trajectories (the full suite on both chains does not fit the budget), and
the page shows the two pose models side by side (clean and under the strongest-attack suite:
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

from pipeline.geometry.labels import TARGET
from pipeline.io.atomic import atomic_write_text, read_json, save_figure
from pipeline.io.errors import not_found
from pipeline.seeds import seed_for
from stages.artifacts.dvc import write_metrics
from stages.artifacts.models import load_chain, load_pose
from stages.artifacts.paths import INTEGRITY_FIGURE, PAPER, ROBUST_METRICS, SHIPPED, SURROGATE
from stages.artifacts.paths import ROBUSTNESS_FIGURE as FIGURE
from stages.artifacts.paths import ROBUSTNESS_METRICS as METRICS
from stages.artifacts.paths import ROBUSTNESS_REPORT as REPORT
from stages.artifacts.readers import read_eval_render
from stages.config.device import torch_setup
from stages.config.evaluation import Robustness, attack_name
from stages.config.schema import Params
from stages.errors import StageError
from stages.pages.calibrate import unmet_banner
from stages.pages.robustness import pose_models, robustness_page


def main(params: Params) -> None:
    """Run every attack and corruption row on held-out test frames; write the report, metrics and figure."""
    from tqdm import tqdm

    from pipeline.attacks.adaptive import PerFrameChain
    from pipeline.evaluation.robustness import run_attack_rows, worst_by_eps
    from pipeline.report.figures import robustness_vs_eps

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
    bar = tqdm(total=-(-n // r.batch_size) * (len(specs) + n_corr + 1), desc="robustness", unit="batch",
               dynamic_ncols=True)

    def progress(it: Any) -> Any:
        for item in it:
            yield item
            bar.update(1)

    t0 = time.perf_counter()
    rows = run_attack_rows(chain, images, targets, specs, r.harm_m, r.batch_size, progress,
                           pgd_is_lambda0="pgd" in r.transfer and 0.0 in r.lambdas)
    shipped_threshold = shipped.defended.settings.threshold
    clean_harm, corruptions = _corruption_rows(chain, images, targets, r, seed, shipped_threshold, progress)
    bar.close()
    fused = _integrity(params, r, shipped, target, seed)
    standard = _standard_integrity(params, r, seed)
    seconds, figure = time.perf_counter() - t0, fused.pop("figure")
    metrics = {"rows": rows, "corruptions": corruptions, "frames": n, "test_frames": n_test, "harm_m": r.harm_m,
               "steps": r.steps, "gradients_per_frame": sum(s.cost for s in specs), "lambdas": r.lambdas,
               "eps": r.eps, "threshold": chain.threshold, "shipped_threshold": shipped_threshold,
               "clean_harmful_rate": clean_harm.value, "ci95_clean_harmful": clean_harm.ci(),
               "surrogate": {"best_epoch": int(surrogate.meta.get("epoch", 0)),
                             "validation_position_m": float(surrogate.meta.get("val_pos_m", float("nan")))},
               "model": SHIPPED.value, "model_hash": shipped.pose_hash, "surrogate_hash": surrogate.hash,
               "seconds": seconds,
               "minutes": seconds / 60, "worst_harmful_undetected": worst_by_eps(rows), **fused,
               "worst_harmful_undetected_fused": worst_by_eps(fused["fused_rows"]), "integrity_standard": standard,
               "pose_models": pose_models(read_json(ROBUST_METRICS))}
    write_metrics(METRICS, metrics, params.profile_name)
    atomic_write_text(REPORT, unmet_banner(fused["fused"]["calibration_unmet"])
                      + unmet_banner(standard.get("calibration_unmet", []), PAPER)
                      + robustness_page(metrics, params))
    worst_fused = [row for row in fused["fused_rows"] if row["lambda"] is None]
    save_figure(robustness_vs_eps([row for row in rows if row["attack"] != "adaptive pgd"] + worst_fused), FIGURE)
    save_figure(_integrity_figure(*figure), INTEGRITY_FIGURE)
    print(f"robustness: {len(rows)} attack rows, {len(corruptions)} corruption rows on {n} test frames and "
          f"{len(fused['integrity']['rows'])} integrity rows in {seconds:.0f} s -> {REPORT}, {METRICS}, {INTEGRITY_FIGURE}")


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
    return attack_specs(pose, surrogate, target, eps=r.eps, unseen_eps=r.unseen_eps, transfer=transfer,
                        lambdas=r.lambdas, surrogate_attacks=on_surrogate, steps=r.steps, mi_steps=a.steps,
                        momentum=float(a.momentum), loss=a.loss, seed=seed)


def _corruption_rows(chain: Any, images: np.ndarray, targets: np.ndarray, r: Robustness, seed: int,
                     shipped_threshold: float, progress: Any) -> tuple[Any, list[dict[str, Any]]]:
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
            rows.append(corruption_row(name, s, pose_errors(res.pose, targets)[0], res.flag,
                                       res.prob >= shipped_threshold))
    return rate(clean_pos > r.harm_m), rows


def _standard_integrity(p: Params, r: Robustness, seed: int) -> dict[str, Any]:
    """The integrity rows of the standard model's chain (the paper's reproduction, with the defense calibrated
    for it): `integrity.standard_attackers` on the first `integrity.standard_trajectories` trajectories
    ({"attackers": []} when none are asked for)."""
    from pipeline.attacks.adaptive import PerFrameChain

    i = p.integrity
    if not i.standard_attackers:
        return {"attackers": [], "model": PAPER.value}
    paper = load_chain(p, PAPER)
    chain = paper.onboard
    out = _integrity(p, r, paper, PerFrameChain(paper.model, chain.shap, chain.detector), seed,
                     list(i.standard_attackers), i.standard_trajectories)
    out.pop("figure")
    return {**out["integrity"], "model": PAPER.value, "model_hash": paper.pose_hash,
            "trajectories": out["fused"]["trajectories"],
            "false_alarm_rate": out["fused"]["false_alarm_rate"], "ci95_false_alarm": out["fused"]["ci95_false_alarm"],
            "calibration_unmet": out["fused"]["calibration_unmet"]}


def _integrity(p: Params, r: Robustness, safety: Any, target: Any, seed: int, attackers: list[str] | None = None,
               n_traj: int | None = None) -> dict[str, Any]:
    """The chain-level attackers (`attackers`, default integrity.attackers, at integrity.eps) on the eval_render
    trajectories (the first `n_traj`; None: all) through one chain (`safety`: a SafetyChain; `target`: its
    PerFrameChain) and the defense calibrated for it: pipeline.evaluation.campaign.fly_campaign. Returns the
    metrics and the figure's data."""
    from tqdm import tqdm

    from pipeline.evaluation.campaign import Campaign, fly_campaign
    from pipeline.evaluation.integrity_runs import Track
    from stages.config.build import alert_limit_settings, burst_attacker, drift_settings
    from stages.pages.integrity import worst_hmi

    t0 = time.perf_counter()
    images, labels, trajs, bursts, defended, info = _fused_setup(p, r, safety, n_traj)
    tracks = [Track(f"t{g}", images[ix], labels[ix]) for g, ix in enumerate(trajs)]
    i = p.integrity
    attackers = list(i.attackers) if attackers is None else attackers
    eps = sorted(float(e) for e in i.eps)
    drifts = [(a, drift_settings(p, a.split("/")[1])) for a in attackers if a != "burst"]
    campaign = Campaign(eps, burst_attacker(p, seed_for(seed, "robustness.burst")) if "burst" in attackers else None,
                        bursts, drifts, (i.drift_start, i.drift_start + i.drift_frames), i.drift_steps,
                        seed_for(seed, "robustness.drift"), alert_limit_settings(p), r.batch_size, r.harm_m, seed)
    with tqdm(total=len(tracks) * ("burst" in attackers) + bool(drifts) * len(eps) * i.drift_frames,
              desc="robustness (integrity)", unit="step", dynamic_ncols=True) as bar:
        flown = fly_campaign(safety.onboard, target, defended, tracks, campaign, lambda: bar.update(1))
    info.update(false_alarm_rate=flown.alarms.value, ci95_false_alarm=flown.alarms.ci())
    top = [(name, runs, masks) for name, e, runs, masks in flown.runs if e == eps[-1]]
    return {"fused_rows": flown.fused_rows, "fused": info,
            "integrity": {"rows": flown.rows, "worst_hmi": worst_hmi({"rows": flown.rows}), "clean": flown.clean_row,
                          "eps": eps, "attackers": attackers,
                          "alert_limit_m": i.alert_limit_m, "collision_range_m": i.collision_range_m,
                          "burst": {"steps": i.burst_steps, "restarts": i.burst_restarts,
                                    "lambdas": [float(v) for v in i.burst_lambdas], "cap": i.burst_cap,
                                    "bursts": info["bursts"], "burst_length": info["burst_length"]},
                          "drift": {"start": i.drift_start, "frames": i.drift_frames, "steps": i.drift_steps,
                                    "gate_fraction": i.drift_gate_fraction}, "seconds": time.perf_counter() - t0},
            "figure": (flown.clean, top, eps[-1])}


def _integrity_figure(clean: list[Any], top: list[tuple[str, list[Any], list[np.ndarray]]], eps: float) -> Any:
    """The Stanford diagram of every attacker at the largest eps (and the clean runs), and trajectory 0 over frames."""
    from pipeline.evaluation.integrity_runs import diagram_points
    from pipeline.report.figures import integrity_diagram
    from stages.pages.integrity import NAMES

    every = [np.ones(len(c.pose), bool) for c in clean]
    points = {"no attack": diagram_points(clean, every), **{f"{NAMES[name]}, eps {eps:g}": diagram_points(flown, masks)
                                                            for name, flown, masks in top}}
    series = {"no attack": clean[0].frames.error, **{f"{NAMES[name]}, eps {eps:g}": flown[0].frames.error
                                                     for name, flown, _ in top}}
    return integrity_diagram(points, series, clean[0].frames.alert,
                             f"Trusted estimate against its bound, eps {eps:g} (counted frames: from the first attacked one)")


def _fused_setup(p: Params, r: Robustness, safety: Any, n_traj: int | None) -> tuple[Any, ...]:
    """(eval_render images, labels (N, 9), frame indices per trajectory (the first `n_traj`; None: all), bursts per
    trajectory, the defended-chain settings of the chain `safety`, facts about the defense)."""
    from pipeline.evaluation.robustness import burst_schedule

    images, poses, _ = read_eval_render(p)
    labels = poses[TARGET].to_numpy(np.float64)
    trajs = [np.flatnonzero(poses["trajectory"].to_numpy() == t) for t in np.unique(poses["trajectory"])][:n_traj]
    # the chain's defense as `rpod calibrate` recorded it (the noise model fitted on validation trajectories)
    defended, cal = safety.defended, safety.calibration
    length = p.integrity.burst_length
    try:
        bursts = [burst_schedule(len(ix), length, r.burst_every) for ix in trajs]
    except ValueError as e:
        raise StageError(f"params.yaml robustness.burst_every / integrity.burst_length: {e}") from None
    info = {"trajectories": len(trajs), "bursts": sum(len(b) for b in bursts), "burst_length": length,
            "burst_every": r.burst_every, "noise_model": defended.noise.as_dict(), "gate": defended.motion.gate,
            "gate_false_alarm": defended.motion.false_alarm, "noise_inflation": cal.inflation,
            "fusion": defended.settings.fusion, "calibration_unmet": list(cal.unmet),
            "noise_fitted_on": "validation trajectories (models/defense.json, rpod calibrate)"}
    return images, labels, trajs, bursts, defended, info
