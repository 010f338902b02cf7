"""Per-frame latency of the safety chain (pose + exact SHAP + LSTM detector) against the pose forward alone.

At batch 1 (one camera frame, as onboard), for the default (160x90, width 0.25) and the paper
(480x270, width 1.0) configurations, with randomly initialised models (timings do not depend on
the weights). The two are timed interleaved (pose, chain, pose, chain, ...) so load from other
processes hits both alike; medians are reported. Target: chain <= 1.05x the pose forward.
Prints a table and writes the `## Safety chain latency` section of reports/benchmarks.md.

    .venv/bin/python benchmarks/chain_latency.py [--threads 2] [--seconds 4]
"""
from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from pipeline.chain import SafetyChain  # noqa: E402
from pipeline.detectors.lstm import LSTMConfig, LSTMDetector  # noqa: E402
from pipeline.model import PoseNet  # noqa: E402
from pipeline.report import markdown_table, replace_section  # noqa: E402

REPORT = ROOT / "reports" / "benchmarks.md"
CONFIGS = [("default", 0.25, 90, 160), ("paper", 1.0, 270, 480)]


def interleaved(a, b, seconds: float) -> tuple[float, float]:
    """Median seconds per call of a() and b(), timed alternately for about `seconds` in all."""
    a(), b()
    ta, tb = [], []
    start = time.perf_counter()
    while time.perf_counter() - start < seconds or len(ta) < 5:
        t = time.perf_counter()
        a()
        ta.append(time.perf_counter() - t)
        t = time.perf_counter()
        b()
        tb.append(time.perf_counter() - t)
    return float(np.median(ta)), float(np.median(tb))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--threads", type=int, default=1,
                    help="torch CPU threads (1: steadier on a CPU shared with other jobs)")
    ap.add_argument("--seconds", type=float, default=4.0, help="timing budget per configuration")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    rows = []
    for name, width, h, w in CONFIGS:
        model = PoseNet(width=width).eval()
        detector = LSTMDetector(LSTMConfig()).eval()
        x = torch.rand(1, 3, h, w)
        with torch.no_grad():
            bg_mean = model.forward_features(torch.rand(4, 3, h, w)).mean(0)
        chain = SafetyChain.from_model(model, bg_mean, detector)
        t_pose, t_chain = interleaved(lambda: chain.pose_only(x), lambda: chain(x), args.seconds)
        rows.append({"config": name, "input": f"{w}x{h}", "width": width, "pose forward (ms)": t_pose * 1e3,
                     "whole chain (ms)": t_chain * 1e3, "ratio": t_chain / t_pose,
                     "target <= 1.05x": "yes" if t_chain / t_pose <= 1.05 else "no"})
        print(f"{name:8s} {w}x{h}: pose {t_pose * 1e3:.2f} ms, chain {t_chain * 1e3:.2f} ms, "
              f"ratio {t_chain / t_pose:.3f}", flush=True)
    table = markdown_table(rows, decimals=3)
    print(table)
    body = f"""`benchmarks/chain_latency.py` on {platform.processor() or platform.machine()}, torch
{torch.__version__}, {args.threads} threads, batch 1, random weights, medians of interleaved calls.
The chain computes the GAP features once and uses them for the pose heads and for the closed-form
SHAP values (pipeline/chain.py), then runs the LSTM detector (100 units, 9 steps; traced with
TorchScript so its recurrence has no Python overhead).

{table}"""
    text = REPORT.read_text() if REPORT.exists() else "# Benchmarks\n"
    REPORT.parent.mkdir(parents=True, exist_ok=True)
    REPORT.write_text(replace_section(text, "Safety chain latency", body))
    print(f"-> {REPORT}")


if __name__ == "__main__":
    main()
