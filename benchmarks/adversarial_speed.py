"""Adversarial-training throughput against plain training, measured in the same run (issue 28's budget).

At params.yaml's train.width, render size and batch: a plain training step (forward, backward, Adam) and
an adversarial one (pipeline.pose.adversarial.Adversary.perturb: PGD-k on the batch, model in eval mode,
then the same training step), alternated batch by batch on random images so machine load hits both alike;
median of the timed batches after a warm-up. An adversarial image costs k input gradients and one weight
gradient: its gradients/s = images/s x (k + 1), to compare with plain training's images/s (target: plain
images/s within 1.3x of the adversarial gradients/s). Writes the `## Adversarial training` section of
reports/benchmarks.md.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

# before torch loads (as stages/cli.py does): spinning OpenMP threads made training 10-20x slower on the
# shared 2-core machine
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import torch  # noqa: E402

from pipeline.pose.adversarial import AdversarialConfig, Adversary  # noqa: E402
from pipeline.pose.loss import PoseLoss  # noqa: E402
from pipeline.pose.model import PoseNet  # noqa: E402
from pipeline.report.markdown import markdown_table  # noqa: E402
from stages.config import params as params_mod  # noqa: E402
from stages.report import write_benchmark  # noqa: E402

TARGET_RATIO = 1.3


def step_seconds(
    width: float, black_level: float, h: int, w: int, batch: int, k: int, batches: int, eps: float
) -> tuple[float, float]:
    """Median seconds of (a plain training step, an adversarial PGD-k one) on (batch, 3, h, w) inputs."""
    torch.manual_seed(0)
    model = PoseNet(width, black_level=black_level).to(memory_format=torch.channels_last)
    loss = PoseLoss()
    opt = torch.optim.Adam([*model.parameters(), *loss.parameters()], lr=1e-4)
    adversary = Adversary(AdversarialConfig(eps=eps, steps=k, ramp_epochs=0), loss, 1, 0)
    x = torch.rand(batch, 3, h, w).contiguous(memory_format=torch.channels_last)
    y = torch.rand(batch, 9)
    times: dict[bool, list[float]] = {False: [], True: []}
    for i in range(batches + 1):
        for adversarial in (False, True):
            t0 = time.perf_counter()
            inputs = adversary.perturb(model, x, y, 0) if adversarial else x
            model.train()
            opt.zero_grad()
            loss(model(inputs), y).backward()
            opt.step()
            if i:
                times[adversarial].append(time.perf_counter() - t0)
    return statistics.median(times[False]), statistics.median(times[True])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batches", type=int, default=5, help="timed batches of each kind (after one warm-up)")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    p = params_mod.load()
    a, batch = p.train.adversarial, p.train.batch_size
    load0 = os.getloadavg()[0]
    rows = []
    for k in sorted({1, a.steps}):
        plain, adv = step_seconds(
            float(p.train.width),
            float(a.black_level),
            p.render.height,
            p.render.width,
            batch,
            k,
            args.batches,
            float(a.eps),
        )
        plain_ips, adv_ips = batch / plain, batch / adv
        rows.append(
            {
                "PGD steps k": k,
                "plain images/s": plain_ips,
                "adversarial images/s": adv_ips,
                "adversarial gradients/s": adv_ips * (k + 1),
                "plain images/s / adversarial gradients/s": plain_ips / (adv_ips * (k + 1)),
            }
        )
        print(
            f"k={k}: plain {plain_ips:.1f} img/s, adversarial {adv_ips:.1f} img/s = "
            f"{adv_ips * (k + 1):.1f} gradients/s",
            flush=True,
        )
    load1 = os.getloadavg()[0]
    table = markdown_table(rows, decimals=2)
    met = all(r["plain images/s / adversarial gradients/s"] <= TARGET_RATIO for r in rows)
    body = (
        f"`benchmarks/adversarial_speed.py` on {platform.machine()}, torch {torch.__version__}, {args.threads} "
        f"threads, width {p.train.width:g}, {p.render.width}x{p.render.height}, batch {batch}, channels_last, "
        f"float32, the black-level clamp on; plain and adversarial steps alternated, median of {args.batches} "
        f"each after a warm-up; load average {load0:.1f} at the start, {load1:.1f} at the end (other processes "
        f"were not stopped).\n\n{table}\n"
        f"An adversarial image costs k input gradients (PGD, eval mode: no weight gradients) and one training "
        f"step; target: plain images/s at most {TARGET_RATIO}x the adversarial gradients/s "
        f"({'met' if met else 'not met'}). Data loading and augmentation are not included."
    )
    print(table)
    print(f"-> {write_benchmark('Adversarial training', body)} (## Adversarial training)")


if __name__ == "__main__":
    main()
