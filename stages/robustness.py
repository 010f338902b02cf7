"""`rpod robustness`: the shipped safety chain against attacks its detector never saw (SPEC 11).

Reads models/pose.pt, models/detector.pt, models/surrogate.pt (`rpod train --surrogate`) and a
seeded sample of `robustness.frames` held-out test frames; every attacked image is stored as 8-bit
(`pipeline.attacks.quantize`) before it goes through the chain, as in the other stages. Rows:
- seen: FGSM on the training loss at robustness.eps (the attack the detector was trained on);
- transfer: FGSM at robustness.unseen_eps, and robustness.transfer (pgd, mifgsm, fgsm/position,
  fgsm/rotation: method[/loss]) at robustness.eps;
- adaptive: L-inf PGD on pose_loss - lambda * detector logit (pipeline.adaptive) per lambda and eps,
  plus the per-frame worst case over lambda;
- surrogate: robustness.surrogate_attacks crafted on the surrogate pose model, evaluated on ours;
- corruptions (not attacks): robustness.corruptions at camera-realistic strengths;
- fused (the chain that ships, issue 16: LSTM flag OR motion gate): the adaptive attack on the
  fused chain over whole bursts of the eval_render trajectories, evaluated by the real defense
  (pipeline.defense.run_defense) over each whole trajectory, clean frames included.
Params are checked on load (stages.schema.Robustness). Writes reports/robustness.md,
reports/metrics/robustness.json, reports/figures/robustness.png (text: stages/pages/robustness.py).
"""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

import numpy as np

from stages import params as params_mod
from stages.artifacts import Pose, load_defense, load_detector, load_pose, read_eval_render
from stages.checkpoint import POSE
from stages.io import StageError, atomic_write_text, save_figure, write_metrics
from stages.pages.robustness import robustness_page
from stages.schema import Robustness, attack_name

SURROGATE = Path("models/surrogate.pt")
REPORT = Path("reports/robustness.md")
METRICS = Path("reports/metrics/robustness.json")
FIGURE = Path("reports/figures/robustness.png")
SEED_OFFSET = 1500


def main() -> None:
    """Run every attack and corruption row on held-out test frames; write the report, metrics and figure."""
    from tqdm import tqdm

    from pipeline.chain import SafetyChain
    from pipeline.figures import robustness_vs_eps
    from pipeline.robustness import run_attack_rows, worst_by_eps
    from stages.data import load_split

    p = params_mod.load()
    r = params_mod.typed(p).robustness
    if not SURROGATE.exists():
        raise StageError(f"{SURROGATE} not found: run `rpod train --surrogate` (dvc repro surrogate) first")
    params_mod.set_threads(p)
    seed = int(p["seed"]) + SEED_OFFSET
    pose, surrogate = load_pose(p), load_pose(p, SURROGATE)
    detector, ckpt = load_detector(model_hash=pose.hash)
    try:
        chain = SafetyChain.from_model(pose.model, np.asarray(ckpt["background_mean"]), detector,
                                       threshold=float(ckpt["threshold"]))
    except ValueError as err:
        raise StageError(f"{POSE}: {err}") from None

    split = load_split(p, "test")
    n = min(r.frames, len(split))
    pick = np.sort(np.random.default_rng(seed).choice(len(split), n, replace=False))
    images = np.stack([np.asarray(split.images[int(i)]) for i in pick])
    targets = split.targets[pick]

    from pipeline.adaptive import ShapChain

    target = ShapChain(pose.model, chain.weight, chain.background_mean, chain.detector)
    specs = _specs(p, r, target, pose, surrogate, seed)
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
    fused = _fused_rows(p, r, chain, target, seed, pose.hash)
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
    write_metrics(METRICS, metrics, p)
    atomic_write_text(REPORT, robustness_page(metrics, p))
    worst_fused = [row for row in fused["fused_rows"] if row["lambda"] is None]
    save_figure(robustness_vs_eps([row for row in rows if row["attack"] != "adaptive pgd"] + worst_fused), FIGURE)
    print(f"robustness: {len(rows)} attack rows and {len(corruptions)} corruption rows on {n} test frames in "
          f"{seconds:.0f} s -> {REPORT}, {METRICS}, {FIGURE}")


def _specs(p: dict[str, Any], r: Robustness, target: Any, pose: Pose, surrogate: Pose, seed: int) -> list[Any]:
    """The attack rows to run, in report order. PGD at eps index i uses seed + 100 + i, so plain PGD
    and the adaptive attack at lambda = 0 are one run (the `pgd` row is then taken from it)."""
    import torch

    from pipeline.adaptive import adaptive_pgd
    from pipeline.attacks import attack_loss, get_attack
    from pipeline.robustness import AttackSpec

    a = p["attack"]

    def gen(k: int) -> torch.Generator:
        return torch.Generator().manual_seed(seed + k)

    def cost(method: str) -> int:
        """Gradients per frame: PGD takes robustness.steps, MI-FGSM attack.steps as in the attack stage."""
        return {"fgsm": 1, "pgd": r.steps}.get(method, int(a["steps"]))

    def spec(name: str, group: str, e: float, key: str, k: int, model: Pose = pose) -> AttackSpec:
        method, loss = attack_name(name, key)
        fn = get_attack(method, steps=cost(method), step_size=None, random_start=True,
                        momentum=float(a["momentum"]), generator=gen(k))
        lf = attack_loss(loss or a["loss"], model.loss)
        return AttackSpec(name, group, e, None, lambda x, y: fn(model.model, x, y, e, lf), cost(method))

    out = [spec("fgsm", "seen", e, "eps", 0) for e in r.eps]
    out += [spec("fgsm", "transfer", e, "unseen_eps", 0) for e in r.unseen_eps]
    pgd_is_lambda0 = "pgd" in r.transfer and 0.0 in r.lambdas
    out += [spec(name, "transfer", e, "transfer", 100 + i if name == "pgd" else 200 + 10 * j + i)
            for j, name in enumerate(r.transfer) for i, e in enumerate(r.eps) if not (name == "pgd" and pgd_is_lambda0)]
    full = attack_loss(a["loss"], pose.loss)
    out += [AttackSpec("adaptive pgd", "adaptive", e, lam,
                       lambda x, y, e=e, lam=lam, g=gen(100 + i): adaptive_pgd(target, x, y, e, full, lam,
                                                                               steps=r.steps, generator=g), r.steps)
            for i, e in enumerate(r.eps) for lam in r.lambdas]
    out += [dataclasses.replace(spec(name, "surrogate", e, "surrogate_attacks", 500 + 10 * j + i, surrogate),
                                attack=f"surrogate {name}")
            for j, name in enumerate(r.surrogate_attacks) for i, e in enumerate(r.eps)]
    return out


def _corruption_rows(chain: Any, images: np.ndarray, targets: np.ndarray, r: Robustness, seed: int,
                     progress: Any) -> tuple[Any, list[dict[str, Any]]]:
    """(rate of clean frames beyond harm_m, corruption rows: `none` first, then each corruption and strength)."""
    from pipeline.chain import run_sequence
    from pipeline.corruptions import corrupt
    from pipeline.robustness import corruption_row
    from pipeline.stats import rate
    from pipeline.training import pose_errors

    none = np.zeros(len(images), bool)
    clean = run_sequence(chain, images, targets, none, None, r.batch_size, progress)
    clean_pos = pose_errors(clean.pose, targets)[0]
    rows = [corruption_row("none", 0.0, clean_pos, clean.flag)]
    for name, strengths in dataclasses.asdict(r.corruptions).items():
        for s in strengths:
            res = run_sequence(chain, corrupt(name, s, seed)(images), targets, none, None, r.batch_size, progress)
            rows.append(corruption_row(name, s, pose_errors(res.pose, targets)[0], res.flag))
    return rate(clean_pos > r.harm_m), rows


def _fused_rows(p: dict[str, Any], r: Robustness, chain: Any, target: Any, seed: int, model_hash: str) -> dict[str, Any]:
    """Adaptive attack on the fused chain (LSTM flag OR motion gate, pipeline.defense) over bursts of
    `evaluate.attack_length` frames every `robustness.burst_every` frames of each eval_render
    trajectory, per eps and lambda and the per-burst worst case over lambda; rates with bootstrap
    intervals over trajectories. Also the fused chain's false-alarm rate on the clean trajectories."""
    import torch
    from tqdm import tqdm

    from pipeline.adaptive import adaptive_pgd
    from pipeline.attacks import attack_loss
    from pipeline.robustness import fused_attack, fused_row, worst_burst_over_lambda
    from pipeline.training import pose_errors

    images, labels, trajs, bursts, defended, info = _fused_setup(p, r, chain, model_hash)
    full = attack_loss(p["attack"]["loss"], load_pose(p).loss)
    rows = []
    bar = tqdm(total=len(r.eps) * len(r.lambdas) * len(trajs), desc="robustness (fused)", unit="trajectory")
    for i, e in enumerate(r.eps):
        runs = []
        for lam in r.lambdas:
            def craft(fused: Any, x: Any, y: Any, e: float = e, lam: float = lam) -> Any:
                return adaptive_pgd(fused, x, y, e, full, lam, steps=r.steps,
                                    generator=torch.Generator().manual_seed(seed + 700 + i))
            pos, flag, grp, bid = [], [], [], []
            for g, (ix, bs) in enumerate(zip(trajs, bursts)):
                est, trace = fused_attack(chain, target, defended, images[ix], labels[ix], bs, craft, r.batch_size)
                err = pose_errors(est, labels[ix])[0]
                for k, (a, b) in enumerate(bs):
                    pos.append(err[a:b]), flag.append(trace.flag[a:b])
                    grp.append(np.full(b - a, g)), bid.append(np.full(b - a, 1000 * g + k))
                bar.update(1)
            runs.append(tuple(np.concatenate(v) for v in (pos, flag, grp, bid)))
            rows.append(fused_row("fused chain: adaptive pgd", e, lam, *runs[-1][:3], r.harm_m))
        wp, wf = worst_burst_over_lambda([v[0] for v in runs], [v[1] for v in runs], runs[0][3], r.harm_m)
        rows.append(fused_row("fused chain: adaptive pgd, worst over lambda", e, None, wp, wf, runs[0][2], r.harm_m))
    bar.close()
    return {"fused_rows": rows, "fused": info}


def _fused_setup(p: dict[str, Any], r: Robustness, chain: Any, model_hash: str) -> tuple[Any, ...]:
    """(eval_render images, labels (N, 9), frame indices per trajectory, bursts per trajectory, the
    defended-chain settings, facts incl. the fused chain's false-alarm rate on the clean trajectories)."""
    from pipeline.defense import run_defense
    from pipeline.robustness import Defended, burst_schedule, pose_estimates, world_motion
    from pipeline.rotations import sixd_to_matrix
    from pipeline.stats import bootstrap_rate

    images, poses, _ = read_eval_render(p)
    labels = poses[["tx", "ty", "tz", "r0", "r1", "r2", "r3", "r4", "r5"]].to_numpy(np.float64)
    trajs = [np.flatnonzero(poses["trajectory"].to_numpy() == t) for t in np.unique(poses["trajectory"])]
    # the defense that ships: params.defense with the noise model `rpod calibrate` fitted on validation trajectories
    shipped = load_defense(p, model_hash, chain.threshold)
    defended = Defended(shipped.settings, shipped.motion, shipped.noise)
    length = int(p["evaluate"]["attack_length"])
    try:
        bursts = [burst_schedule(len(ix), length, r.burst_every) for ix in trajs]
    except ValueError as e:
        raise StageError(f"params.yaml robustness.burst_every / evaluate.attack_length: {e}") from None
    clean_flags, groups = [], []
    for g, ix in enumerate(trajs):   # the fused chain on the clean trajectories: its false alarms
        est, prob = pose_estimates(chain, images[ix], r.batch_size)
        R_cam, u = world_motion(labels[ix])
        clean_flags.append(run_defense(defended.settings, defended.motion, defended.noise, est[:, :3], prob, R_cam,
                                       u, sixd_to_matrix(est[:, 3:])).flag)
        groups.append(np.full(len(ix), g))
    alarms = bootstrap_rate(np.concatenate(clean_flags), np.concatenate(groups))
    info = {"trajectories": len(trajs), "bursts": sum(len(b) for b in bursts), "burst_length": length,
            "burst_every": r.burst_every, "false_alarm_rate": alarms.value, "ci95_false_alarm": alarms.ci(),
            "noise_model": defended.noise.as_dict(), "gate": defended.motion.gate,
            "gate_false_alarm": defended.motion.false_alarm,
            "fusion": defended.settings.fusion,
            "noise_fitted_on": "validation trajectories (models/defense.json, rpod calibrate)"}
    return images, labels, trajs, bursts, defended, info
