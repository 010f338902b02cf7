"""Training and inference throughput of the pose CNN (images/s) at the default and paper settings.

Default: params.yaml's train.width at 160x90; paper: width 1 at 480x270. Batch train.batch_size,
channels_last, random images; a warm-up batch, then the median of timed batches. Prints a table
and writes the `## Training` section of reports/benchmarks.md (other sections are kept).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

import torch

from pipeline.pose.loss import PoseLoss
from pipeline.pose.model import PoseNet
from pipeline.report.markdown import markdown_table
from stages.config import params as params_mod
from stages.report import write_benchmark


def throughput(width: float, h: int, w: int, batch: int, batches: int) -> tuple[float, float]:
    """(training images/s, inference images/s) for PoseNet(width) on (batch, 3, h, w) inputs."""
    torch.manual_seed(0)
    model = PoseNet(width).to(memory_format=torch.channels_last)
    loss = PoseLoss()
    opt = torch.optim.Adam([*model.parameters(), *loss.parameters()], lr=1e-4)
    x = torch.rand(batch, 3, h, w).contiguous(memory_format=torch.channels_last)
    y = torch.rand(batch, 9)
    train_s = []
    for i in range(batches + 1):
        t0 = time.perf_counter()
        opt.zero_grad()
        loss(model(x), y).backward()
        opt.step()
        if i:
            train_s.append(time.perf_counter() - t0)
    model.eval()
    infer_s = []
    with torch.inference_mode():
        for i in range(batches + 1):
            t0 = time.perf_counter()
            model(x)
            if i:
                infer_s.append(time.perf_counter() - t0)
    return batch / statistics.median(train_s), batch / statistics.median(infer_s)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batches", type=int, default=3, help="timed batches per setting (after one warm-up)")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    p = params_mod.load()
    batch = p.train.batch_size
    settings = [("default", float(p.train.width), p.render.height, p.render.width), ("paper", 1.0, 270, 480)]
    load0 = os.getloadavg()[0]
    rows = []
    for name, width, h, w in settings:
        train_ips, infer_ips = throughput(width, h, w, batch, args.batches)
        rows.append(
            {
                "setting": name,
                "input": f"{w}x{h}",
                "width": f"{width:g}",
                "batch": batch,
                "train images/s": train_ips,
                "inference images/s": infer_ips,
                "train seconds per 1,000 images": 1000 / train_ips,
            }
        )
        print(
            f"{name}: {w}x{h} width {width}: train {train_ips:.1f} img/s, inference {infer_ips:.1f} img/s", flush=True
        )
    load1 = os.getloadavg()[0]
    table = markdown_table(rows, decimals=1)
    body = (
        f"`benchmarks/train_speed.py` on {platform.machine()}, torch {torch.__version__}, "
        f"{args.threads} threads, batch {batch}, channels_last, float32 (bf16 autocast is 10-30x slower on "
        f"this CPU), median of {args.batches} batches after a warm-up; load average {load0:.1f} at the start, "
        f"{load1:.1f} at the end (other processes were not stopped).\n\n{table}\n"
        f"Training images/s include the backward pass and the Adam step, not data loading or augmentation."
    )
    print(table)
    print(f"-> {write_benchmark('Training', body)} (## Training)")


if __name__ == "__main__":
    main()
