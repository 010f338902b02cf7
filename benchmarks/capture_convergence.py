"""Capture and drift convergence: do the integrity campaign's planner-driven attackers reach their worst case at
integrity.frame_steps targeted PGD steps per attacked frame, or does doubling the steps move it? And what one
trajectory's run costs.

The campaign of `rpod robustness` (stages/engine/campaigns.py `campaign_for`: every attacker of
integrity.attackers but the burst, the per-frame attack `TargetedPGD` from the lifting start with BPDA) on the
undefended robust control and on the shipped chain, on the first `--tracks` eval_render trajectories, at each
`--eps`, flown with frame_steps, twice and four times as many. Per chain, eps and steps: the largest error / AL on
an available frame (the measure that breaks a chain; AL the persistent-bias one), the mean trusted error on the last
frame (the bias the chaser would dock with), each the worst over the attackers. The verdict compares the base steps
with twice as many: a rise of more than 5% (or 2 cm, whichever is larger) says the attack has not converged, so the
campaign's figures are lower bounds for that chain and eps; a fall as large says the stronger per-frame attack did
worse on the judged measure (its target is a planned bias, not that measure), so the campaign's figure stands.
Reads params.yaml, models/ and datasets/eval_render of the working folder (run `dvc repro robustness` first);
writes the `## Capture and drift convergence` section of reports/benchmarks.md.

    .venv/bin/python benchmarks/capture_convergence.py [--tracks 2] [--eps 0.05 0.1] [--factors 1 2 4]
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

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from pipeline.report.markdown import markdown_table  # noqa: E402
from stages.report import write_benchmark  # noqa: E402

SECTION = "Capture and drift convergence"
TOLERANCE = (0.05, 0.02)  # relative change, metres: the larger is allowed before the verdict says "not converged"


def fly(p: Any, safety: Any, defended: Any, tracks: list[Any], eps: float, steps: int, seed: int) -> dict[str, Any]:
    """One campaign at one eps with `steps` per attacked frame: the worst over attackers of the largest error / AL
    (available frames) and of the mean final trusted error (m) over the tracks, and the seconds it took."""
    from pipeline.evaluation.campaign import fly_campaign
    from stages.engine.campaigns import attack_target, campaign_for

    i = dataclasses.replace(
        p.integrity,
        eps=[eps],
        frame_steps=steps,
        stop_at_break=False,
        attackers=[a for a in p.integrity.attackers if a != "burst"],
    )
    q = dataclasses.replace(p, integrity=i)
    campaign = campaign_for(q, seed, defended, [[] for _ in tracks])
    t0 = time.perf_counter()
    flown = fly_campaign(safety.onboard, attack_target(safety.onboard, defended), defended, tracks, campaign)
    seconds = time.perf_counter() - t0
    per = [m for by_eps in flown.measures.values() for m in by_eps[eps]]
    finals = {a: float(np.mean([m.final_error for m in by_eps[eps]])) for a, by_eps in flown.measures.items()}
    ratios = [m.max_error_al for m in per if np.isfinite(m.max_error_al)]
    return {
        "max_error_al": max(ratios) if ratios else float("nan"),
        "final": max(finals.values()),
        "final_by": max(finals, key=finals.get),
        "seconds": seconds,
    }


def change(a: float, b: float) -> int:
    """+1 when `b` exceeds `a` by more than TOLERANCE (relative, or absolute in metres, the larger), -1 when it falls
    short by more, 0 otherwise; a NaN (no available attacked frame: nothing to judge) below any figure."""
    if not (np.isfinite(a) and np.isfinite(b)):
        return int(np.isfinite(b)) - int(np.isfinite(a))
    if abs(b - a) <= max(TOLERANCE[0] * abs(a), TOLERANCE[1]):
        return 0
    return 1 if b > a else -1


def verdicts(rows: list[dict[str, Any]], base: int) -> list[str]:
    """Per chain and eps: how doubling the base steps moved the worst final error and the largest error / AL (each
    rose, fell or kept), and the verdict: not converged when either rose (the campaign's figures are lower bounds),
    else the campaign's figure stands (converged, or more steps found less: the per-frame attack aims at a planned
    bias, not at the judged measure)."""
    said = {1: "rose", -1: "fell", 0: "kept"}
    out = []
    for key in dict.fromkeys((r["chain"], r["eps"]) for r in rows):
        by = {r["steps per frame"]: r for r in rows if (r["chain"], r["eps"]) == key}
        a, b = by.get(base), by.get(2 * base)
        if a is None or b is None:
            continue
        final, ratio = change(a["final"], b["final"]), change(a["max_error_al"], b["max_error_al"])
        if 1 in (final, ratio):
            word = "**not converged**: more steps find more, so the campaign's figures are lower bounds"
        elif -1 in (final, ratio):
            word = "more steps found less (the per-frame attack aims at a planned bias, not at the judged measure): "
            word += "the campaign's figure is the larger"
        else:
            word = "converged"
        out.append(
            f"- {key[0]}, eps {key[1]:g}, {base} -> {2 * base} steps: worst final error {a['final']:.2f} -> "
            f"{b['final']:.2f} m ({said[final]}), largest error / AL {_ratio(a)} -> {_ratio(b)} ({said[ratio]}): "
            f"{word}."
        )
    return out


def _ratio(row: dict[str, Any]) -> str:
    """The largest error / AL of a row, "none" where no attacked frame was available."""
    x = row["max_error_al"]
    return f"{x:.2f}" if np.isfinite(x) else "none (no available attacked frame)"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tracks", type=int, default=2, help="eval_render trajectories flown (the first N)")
    ap.add_argument("--eps", type=float, nargs="+", default=[0.05, 0.1], help="eps flown (L-inf, pixels in [0, 1])")
    ap.add_argument("--factors", type=int, nargs="+", default=[1, 2, 4], help="multiples of integrity.frame_steps")
    args = ap.parse_args()
    if args.tracks < 1 or 1 not in args.factors or 2 not in args.factors or min(args.factors) < 1:
        ap.error("--tracks must be >= 1 and --factors positive, holding 1 and 2 (the verdict compares them)")
    if any(not 0 < e <= 1 for e in args.eps):
        ap.error(f"--eps {args.eps}: each must be in (0, 1] (L-inf, pixels in [0, 1])")
    from pipeline.seeds import seed_for
    from stages.artifacts.models import load_chain
    from stages.artifacts.paths import SHIPPED
    from stages.config import params as params_mod
    from stages.engine.campaigns import integrity_tracks

    p = params_mod.load()
    torch.set_num_threads(p.threads or os.cpu_count() or 1)
    load0, t0 = os.getloadavg()[0], time.perf_counter()
    shipped = load_chain(p, SHIPPED)
    tracks = integrity_tracks(p, shipped)[0][: args.tracks]
    seed, base = seed_for(p.seed, "robustness"), p.integrity.frame_steps
    attackers = [a for a in p.integrity.attackers if a != "burst"]
    rows = []
    for name, defended in (("undefended robust control", None), ("shipped chain", shipped.defended)):
        for e in args.eps:
            for k in sorted(args.factors):
                r = fly(p, shipped, defended, tracks, e, k * base, seed)
                rows.append({"chain": name, "eps": e, "steps per frame": k * base, **r})
                print(rows[-1], flush=True)
    table = [
        {
            "chain": r["chain"],
            "eps": f"{r['eps']:g}",
            "steps per frame": r["steps per frame"],
            "largest error / AL": _ratio(r).split(" (")[0],
            "worst mean final error (m)": r["final"],
            "by": r["final_by"],
            "s per run": r["seconds"] / (args.tracks * len(attackers)),
        }
        for r in rows
    ]
    text = (
        f"`benchmarks/capture_convergence.py` on {platform.machine()}, torch {torch.__version__}, {p.threads} "
        f"threads, the {p.profile_name} profile's chains and its first {args.tracks} eval_render trajectories; "
        f"attackers {', '.join(attackers)} (integrity.frame_steps = {base}); "
        f"load average {load0:.1f} at the start, {os.getloadavg()[0]:.1f} at the end (other processes were not "
        f"stopped); {time.perf_counter() - t0:.0f} s in all. Worst over the attackers; the last column is the "
        f"cost of one (trajectory, attacker, eps) run of {len(tracks[0])} frames: the campaign's seconds over its runs (the "
        f'integrity campaign\'s cost per trajectory, README "Scaling out").\n\n'
        f"{markdown_table(table, decimals=2)}\n" + "\n".join(verdicts(rows, base)) + "\n"
    )
    print(text)
    print(f"-> {write_benchmark(SECTION, text)} (## {SECTION})")


if __name__ == "__main__":
    main()
