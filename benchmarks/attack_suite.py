"""The strongest-attack suite (issue 37) against today's PGD-50 on the committed pose models, and what it costs.

On a seeded sample of test frames (`--frames`) of the working folder (params.yaml, datasets/, models/pose.pt and
models/pose_robust.pt), at each `--eps`: PGD-50 (position objective, one random start, last iterate: the attack
reports/pose_robust.md used before the suite) and the lean suite (LEAN, or `--members`); on a seeded subsample of those
(`--full-frames`) also the full suite (FULL, Square at `--square-eps`) and the lean suite with doubled steps and
restarts. Every image stored as 8 bits before it is scored; the worst case nested in eps. Prints and writes
(`## Strongest attack suite` of reports/benchmarks.md): position and attitude means with 95% intervals, the CPU
seconds per frame and eps (process time, `--threads` torch threads: the cost on a busy machine, where wall
time is not), the ratios lean / full and doubled lean / lean on the subsample, and which full-suite member
finds each worst case.

    .venv/bin/python benchmarks/attack_suite.py [--frames 32] [--full-frames 8] [--eps 0.01 0.05 0.1]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import sys
from pathlib import Path
from typing import Any

# before torch loads (as stages/cli.py does): spinning OpenMP threads are many times slower on a shared machine
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402
import torch  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from pipeline.attacks.strongest import (  # noqa: E402
    FULL,
    LEAN,
    PGD50,
    SuiteResult,
    ratio_rows,
    run_suite,  # noqa: E402
    sanity_rows,
)
from pipeline.pose.robustness import sample_rows  # noqa: E402
from pipeline.report.markdown import markdown_table  # noqa: E402
from pipeline.stats import mean_interval  # noqa: E402
from stages.artifacts import data  # noqa: E402
from stages.artifacts.models import load_pose  # noqa: E402
from stages.artifacts.paths import POSE, POSE_ROBUST  # noqa: E402
from stages.config import params as params_mod  # noqa: E402
from stages.report import write_benchmark  # noqa: E402


def _ci(values: np.ndarray) -> str:
    mean, lo, hi = mean_interval(values, floor=0.0)
    return f"{mean:.2f} [{lo:.2f}, {hi:.2f}]"


def comparison_rows(model: str, runs: dict[str, SuiteResult]) -> list[dict[str, Any]]:
    """Per eps and run: the worst case's position and attitude means with 95% intervals and CPU s/frame."""
    rows = []
    first = next(iter(runs.values()))
    rows.append(
        {
            "model": model,
            "eps": 0.0,
            "attack": "clean",
            "frames": first.frames,
            "position (m)": _ci(first.clean["position_m"]),
            "attitude (deg)": _ci(first.clean["attitude_deg"]),
            "CPU s / frame": 0.0,
        }
    )
    for ei, e in enumerate(first.eps):
        for name, r in runs.items():
            rows.append(
                {
                    "model": model,
                    "eps": e,
                    "attack": name,
                    "frames": r.frames,
                    "position (m)": _ci(r.worst("position_m")[ei]),
                    "attitude (deg)": _ci(r.worst("attitude_deg")[ei]),
                    "CPU s / frame": float(r.cpu_seconds[:, ei].sum()),
                }
            )
    return rows


def strongest_members(model: str, full: SuiteResult) -> list[dict[str, Any]]:
    """Per eps and error: how many frames' worst case each full-suite member found (ties to the first)."""
    rows = []
    for key in ("position_m", "attitude_deg"):
        values = np.where(np.isnan(full.errors[key]), -np.inf, full.errors[key])
        for ei, e in enumerate(full.eps):
            top = np.bincount(values[:, ei].argmax(0), minlength=len(full.members))
            rows.append({"model": model, "eps": e, "error": key, **{m: int(c) for m, c in zip(full.members, top)}})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=32, help="seeded test frames of PGD-50 and the lean suite")
    ap.add_argument("--full-frames", type=int, default=8, help="seeded subsample of those for the full suite")
    ap.add_argument("--eps", type=float, nargs="+", default=[0.01, 0.05, 0.1])
    ap.add_argument("--square-eps", type=float, default=0.05, help="the eps of the full suite's Square members")
    ap.add_argument("--models", nargs="+", default=["standard", "robust"], choices=["standard", "robust"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument(
        "--members",
        nargs="+",
        default=list(LEAN.members),
        help="the lean suite's members (method/objective; default LEAN's; params.yaml suite.members is the page's)",
    )
    args = ap.parse_args()
    lean = dataclasses.replace(LEAN, members=tuple(args.members))
    torch.set_num_threads(args.threads)
    p = params_mod.load()
    test = data.load_split(p, "test")
    rows = sample_rows(len(test), args.frames, args.seed)
    images = np.stack([test.images[int(i)] for i in rows])
    targets = np.asarray(test.targets[rows], np.float64)
    sub = np.arange(min(args.full_frames, len(rows)))  # the first of the (already random) sample
    full_cfg = dataclasses.replace(FULL, square_eps=args.square_eps)
    load0 = os.getloadavg()[0]
    table, members, checks = [], {}, []
    for model in args.models:
        net = load_pose(p, POSE if model == "standard" else POSE_ROBUST).model
        print(f"{model}: PGD-50 and lean on {len(rows)} frames", flush=True)
        runs = {
            "pgd-50": run_suite(net, images, targets, args.eps, PGD50),
            "lean": run_suite(net, images, targets, args.eps, lean),
        }
        table += comparison_rows(model, runs)
        print(f"{model}: full and doubled lean on {len(sub)} frames", flush=True)
        on_sub = {
            "pgd-50": runs["pgd-50"].select(sub),
            "lean": runs["lean"].select(sub),
            "lean x2": run_suite(net, images[sub], targets[sub], args.eps, lean.doubled()),
            "full": run_suite(net, images[sub], targets[sub], args.eps, full_cfg),
        }
        table += comparison_rows(model, on_sub)[1:]
        members[model] = strongest_members(model, on_sub["full"])
        checks += _checks(model, on_sub)
        print(markdown_table([r for r in table if r["model"] == model]), flush=True)
    load1 = os.getloadavg()[0]
    body = _body(args, len(rows), len(sub), (load0, load1), (lean, full_cfg), table, checks, members)
    print(body)
    print(f"-> {write_benchmark('Strongest attack suite', body)} (## Strongest attack suite)")


def _checks(model: str, on_sub: dict[str, SuiteResult]) -> list[dict[str, Any]]:
    """The subsample's check rows of `model`: ratios lean / full, pgd-50 / full, doubled lean / lean, and the
    full suite against each of its members."""
    checks = []
    for name, r, ref in (
        ("lean / full", on_sub["lean"], on_sub["full"]),
        ("pgd-50 / full", on_sub["pgd-50"], on_sub["full"]),
        ("lean x2 / lean", on_sub["lean x2"], on_sub["lean"]),
    ):
        checks += [{"model": model, "check": name, **row} for row in ratio_rows(r, ref)]
    checks += [
        {
            "model": model,
            "check": "full >= each member (reference: the strongest)",
            "eps": row["eps"],
            "error": row["error"],
            "result": row["suite"],
            "reference": row["strongest_mean"],
            "ratio": row["suite"] / row["strongest_mean"],
            "ok": row["ok"],
        }
        for row in sanity_rows(on_sub["full"])
    ]
    return checks


def _body(
    args: argparse.Namespace,
    frames: int,
    sub: int,
    load: tuple[float, float],
    configs: tuple[Any, Any],
    table: list[dict[str, Any]],
    checks: list[dict[str, Any]],
    members: dict[str, list[dict[str, Any]]],
) -> str:
    """The Markdown of the `## Strongest attack suite` section: `frames` sampled frames, `sub` of them for the
    full suite, the load average at the start and the end, the tables."""
    load0, load1 = load
    lean, full_cfg = configs
    return (
        f"`benchmarks/attack_suite.py` on {platform.machine()}, torch {torch.__version__}, {args.threads} "
        f"thread(s), CPU; {frames} seeded test frames (seed {args.seed}), the full suite and the doubled "
        f"lean suite on a seeded subsample of {sub} of them; load average {load0:.1f} at the start, "
        f"{load1:.1f} at the end (other processes were not stopped). Worst case per frame nested in eps; "
        f"means with 95% Student-t intervals floored at 0; CPU s / frame: process time per frame at that eps "
        f"(all members).\n\nLean: {', '.join(lean.members)}; {lean.steps} steps, {lean.restarts} restarts "
        f"({'/'.join(lean.starts)} starts). Full: {', '.join(full_cfg.members)}; {full_cfg.steps} steps, "
        f"{full_cfg.restarts} restarts ({'/'.join(full_cfg.starts)}), Square {full_cfg.queries} queries at eps "
        f"{full_cfg.square_eps:g}; on a model without a clamp a bpda member is skipped beside the apgd member of "
        f"its objective (the same attack).\n\n"
        f"{markdown_table(table)}\nRatios of mean worst cases on the subsample (ok: within 5%):\n\n"
        f"{markdown_table(checks, decimals=3)}\nFrames whose full-suite worst case each member found:\n\n"
        + "\n".join(markdown_table(rows) for rows in members.values())
    )


if __name__ == "__main__":
    main()
