"""Chain-level attacks: the burst attack's gradients/s against the training loop's images/s, and the burst
attacker's sanity checks on the shipped chain at reduced scale.

1. Speed: frame-gradients per second of the burst attack (`BurstAttacker` on one eval_render burst through
   the shipped chain and calibrated defense: steps x restarts x K images per lambda, the filter mirror and
   the real defense's verdicts included), of a bare input gradient of the pose network at batch 1, restarts
   x K and 64, and the training loop's images/s (forward, backward, Adam step; batch train.batch_size) of
   the same architecture (benchmarks/train_speed.py).
2. No checks: with the defense and the detector removed (the bare pose network, lambda 0, a cap no error
   reaches) the burst's raw position error against plain PGD's (`pipeline.attacks.gradient.pgd` on the
   position loss, same steps and seed) on the same bursts, at each integrity.eps.
3. Convergence: the burst's HMI frames (its own verdict on the real chain and defense) at integrity.burst_steps
   x burst_restarts and at twice both, on the same bursts at `--eps`: the change against the 95% interval
   (percentile bootstrap over bursts); when it is larger, the attack has not converged and the section says so.
Reads params.yaml, models/ and datasets/eval_render of the working folder (run `rpod eval_render` and the
model stages first); writes the `## Chain-level attacks` section of reports/benchmarks.md.

    .venv/bin/python benchmarks/attack_speed.py [--tracks 3] [--per-track 2] [--eps 0.05]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from pipeline.attackers.base import AttackRun  # noqa: E402
from pipeline.report.markdown import markdown_table  # noqa: E402
from pipeline.stats import bootstrap_rate, percent_ci  # noqa: E402
from stages.report import write_benchmark  # noqa: E402


class Counting(nn.Module):
    """A chain that counts the images it differentiates (forward passes with gradients on the input)."""

    def __init__(self, chain: nn.Module):
        super().__init__()
        self.chain, self.images = chain, 0

    def forward(self, x: torch.Tensor) -> Any:
        self.images += len(x) if torch.is_grad_enabled() and x.requires_grad else 0
        return self.chain(x)


def setup(p: Any, n_tracks: int, per_track: int) -> tuple[Any, ...]:
    """(the standard model's SafetyChain, its PerFrameChain, its Defended without availability, runs): per track its
    frames as an AttackRun with its first bursts attacked."""
    from pipeline.attacks.adaptive import PerFrameChain
    from pipeline.evaluation.integrity_runs import Track
    from pipeline.evaluation.robustness import burst_schedule
    from pipeline.geometry.labels import TARGET
    from stages.artifacts.models import load_chain
    from stages.artifacts.paths import PAPER
    from stages.artifacts.readers import read_eval_render

    pose = load_chain(p, PAPER)
    chain = pose.onboard
    images, poses, _ = read_eval_render(p)
    labels = poses[TARGET].to_numpy(np.float64)
    runs = []
    for g in np.unique(poses["trajectory"])[:n_tracks]:
        ix = np.flatnonzero(poses["trajectory"].to_numpy() == g)
        t = Track(str(g), images[ix], labels[ix])
        mask = np.zeros(len(t), bool)
        for a, b in burst_schedule(len(t), p.integrity.burst_length, p.robustness.burst_every)[:per_track]:
            mask[a:b] = True
        runs.append(AttackRun(t.frames(), torch.as_tensor(t.labels, dtype=torch.float32), t.R_cam, t.u, mask))
    target = PerFrameChain(pose.model, chain.shap, chain.detector)
    return pose, target, dataclasses.replace(pose.defended, alert=None), runs


def speed(p: Any, pose: Any, target: nn.Module, defended: Any, run: AttackRun) -> list[dict[str, Any]]:
    """Rows: the burst attack's frame-gradients/s, bare input gradients/s at three batches, training images/s."""
    from train_speed import throughput

    from pipeline.attackers.burst import bursts_of
    from pipeline.defense.fusion import Defense
    from stages.config.build import burst_attacker

    lo, hi = bursts_of(run.mask)[0]
    one = dataclasses.replace(run, attacked=(np.arange(len(run)) >= lo) & (np.arange(len(run)) < hi))  # one burst
    counting = Counting(target).eval()
    t0 = time.perf_counter()
    burst_attacker(p, 0).nested(counting, Defense(defended.settings, defended.motion, defended.noise), one, [0.05])
    rows = [
        {
            "what": "burst attack (chain + filter mirror + verdicts), eps 0.05, one burst (batch: restarts x K)",
            "batch": p.integrity.burst_restarts * (hi - lo),
            "images/s": counting.images / (time.perf_counter() - t0),
        }
    ]
    model = pose.model.eval()
    for batch in (1, p.integrity.burst_restarts * (hi - lo), 64):
        x = run.images[:1].expand(batch, -1, -1, -1).clone().requires_grad_(True)
        torch.autograd.grad(model(x)[:, :3].sum(), x)
        n, t0 = max(3, 192 // batch), time.perf_counter()
        for _ in range(n):
            torch.autograd.grad(model(x)[:, :3].sum(), x)
        rows.append(
            {
                "what": "input gradient of the pose network",
                "batch": batch,
                "images/s": n * batch / (time.perf_counter() - t0),
            }
        )
    h, w = run.images.shape[2:]
    train_ips, _ = throughput(float(p.train.width), h, w, p.train.batch_size, 3)
    rows.append(
        {"what": "training loop (forward, backward, Adam step)", "batch": p.train.batch_size, "images/s": train_ips}
    )
    return rows


def no_checks(p: Any, pose: Any, runs: list[AttackRun], seed: int = 3) -> list[dict[str, Any]]:
    """Per eps: mean raw position error (m) of plain PGD and of the burst with every check removed."""
    from pipeline.attackers.burst import BurstAttacker, bursts_of
    from pipeline.attacks.gradient import attack_loss, pgd, quantize

    i, rows = p.integrity, []
    loss = attack_loss("position", pose.loss)
    for e in sorted(i.eps):
        plain, ours = [], []
        for run in runs:
            for lo, hi in bursts_of(run.mask):
                x, y = run.images[lo:hi], run.labels[lo:hi]
                adv = pgd(pose.model, x, y, e, loss, steps=i.burst_steps, generator=torch.Generator().manual_seed(seed))
                with torch.no_grad():
                    out = pose.model(quantize(adv, x).float() / 255)
                plain.append(float((out[:, :3] - y[:, :3]).double().norm(dim=1).mean()))
                sub = AttackRun(x, y, run.R_cam[lo:hi], None if run.u is None else run.u[lo:hi])
                res = BurstAttacker(
                    alert_limit=1e6, steps=i.burst_steps, restarts=i.burst_restarts, lambdas=(0.0,), seed=seed
                ).nested(pose.model, None, sub, [e])
                ours.append(float(res.bursts[0][0].raw_error.mean()))
        rows.append(
            {
                "eps": f"{e:g}",
                "bursts": len(plain),
                "plain PGD raw error (m)": float(np.mean(plain)),
                "burst, no checks (m)": float(np.mean(ours)),
                "bursts where burst >= PGD - 1 cm": f"{sum(b >= a - 0.01 for a, b in zip(plain, ours))}/{len(plain)}",
            }
        )
    return rows


def convergence(p: Any, target: nn.Module, defended: Any, runs: list[AttackRun], eps: float) -> list[dict[str, Any]]:
    """The burst's HMI frames and mean capped trusted error at (steps, restarts) and twice both, same bursts."""
    from pipeline.defense.fusion import Defense
    from stages.config.build import burst_attacker

    rows = []
    for k in (1, 2):
        attacker = dataclasses.replace(
            burst_attacker(p, 0), steps=k * p.integrity.burst_steps, restarts=k * p.integrity.burst_restarts
        )
        hmi, group, score = [], [], []
        for r, run in enumerate(runs):
            res = attacker.nested(target, Defense(defended.settings, defended.motion, defended.noise), run, [eps])
            for b, o in enumerate(res.bursts[0]):
                hmi.append(o.hmi)
                group.append(np.full(len(o.hmi), 100 * r + b))
                score.append(o.score)
        rate = bootstrap_rate(np.concatenate(hmi), np.concatenate(group))
        means = np.random.default_rng(0).choice(score, (2000, len(score))).mean(1)  # bootstrap over bursts
        lo, hi = np.percentile(means, [2.5, 97.5])
        rows.append(
            {
                "steps x restarts": f"{attacker.steps} x {attacker.restarts}",
                "bursts": len(score),
                "HMI frames (%)": percent_ci(rate.value, rate.ci()),
                "rate": rate,
                "mean capped trusted error (m)": f"{np.mean(score):.2f} [{lo:.2f}, {hi:.2f}]",
                "score": (float(np.mean(score)), float(lo), float(hi)),
            }
        )
    return rows


def verdict(rows: list[dict[str, Any]]) -> str:
    """Whether doubling steps and restarts moved the worst case (HMI frames, then the mean capped trusted
    error) by less than the base run's 95% interval."""
    a, b = rows[0]["rate"], rows[1]["rate"]
    (m0, lo, hi), (m1, _, _) = rows[0]["score"], rows[1]["score"]
    hmi = (
        f"the HMI rate moved by {100 * abs(b.value - a.value):.1f} points (base interval "
        f"[{100 * a.lo:.1f}, {100 * a.hi:.1f}])"
    )
    score = f"the mean capped trusted error by {m1 - m0:+.2f} m (base interval [{lo:.2f}, {hi:.2f}] m)"
    if a.lo <= b.value <= a.hi and lo <= m1 <= hi:
        return f"Doubling steps and restarts: {hmi}, {score}: both within the base run's interval, converged at this scale."
    return (
        f"Doubling steps and restarts: {hmi}, {score}: outside the base run's interval, so **the burst attack "
        f"has not converged** at {rows[0]['steps x restarts']}; its worst cases are lower bounds."
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tracks", type=int, default=3, help="eval_render trajectories used")
    ap.add_argument("--per-track", type=int, default=2, help="bursts per trajectory (its first ones)")
    ap.add_argument("--eps", type=float, default=0.05, help="eps of the convergence check")
    args = ap.parse_args()
    from stages.config import params as params_mod

    p = params_mod.load()
    torch.set_num_threads(p.threads or os.cpu_count() or 1)
    load0, t0 = os.getloadavg()[0], time.perf_counter()
    pose, target, defended, runs = setup(p, args.tracks, args.per_track)
    fast = speed(p, pose, target, defended, runs[0])
    checks = no_checks(p, pose, runs)
    conv = convergence(p, target, defended, runs, args.eps)
    text = (
        f"`benchmarks/attack_speed.py` on {platform.machine()}, torch {torch.__version__}, {p.threads} threads, "
        f"the {p.profile_name} profile's models and eval_render trajectories ({args.tracks} trajectories, their "
        f"first {args.per_track} bursts of {p.integrity.burst_length} frames: the reduced scale of checks 2 and 3); "
        f"load average {load0:.1f} at the start, {os.getloadavg()[0]:.1f} at the end (other processes were not "
        f"stopped); {time.perf_counter() - t0:.0f} s in all.\n\n"
        f"Speed (frame-gradients per second):\n\n{markdown_table(fast, decimals=1)}\n"
        f"With every check removed (no defense, no detector, lambda 0), the burst against plain PGD, "
        f"{p.integrity.burst_steps} steps each (the burst from {p.integrity.burst_restarts} starts):\n\n"
        f"{markdown_table(checks, decimals=2)}\n"
        f"Convergence on the shipped chain and defense at eps {args.eps:g} (HMI frames as the attacker judges its "
        f"worst case on the real chain; 95% bootstrap over bursts):\n\n"
        f"{markdown_table([{k: v for k, v in r.items() if k not in ('rate', 'score')} for r in conv], decimals=2)}\n"
        f"{verdict(conv)}"
    )
    print(text)
    print(f"-> {write_benchmark('Chain-level attacks', text)} (## Chain-level attacks)")


if __name__ == "__main__":
    main()
