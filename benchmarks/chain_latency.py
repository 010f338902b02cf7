"""Per-frame latency of the safety chain (pose + exact SHAP + LSTM detector, and the defense) against the pose forward alone.

At batch 1 (one camera frame, as onboard), for the default (160x90, width 0.25) and the paper
(480x270, width 1.0) configurations, with random weights (timings do not depend on them; the
detector is standardised on the chain's own SHAP values so that its probabilities spread). Timed
interleaved on the same model object (pose, chain, chain + defense step, plain chain, ...) so that
load from other processes, and the caches the pose network leaves behind, hit all alike; medians of
process CPU time (wall time for the chain ratio too). Target: chain + defense <= 1.05x the pose
forward. Also checks that the fast chain equals the plain one (same pose, probabilities within 1e-4).
Prints a table and writes the `## Safety chain latency` section of reports/benchmarks.md.

    .venv/bin/python benchmarks/chain_latency.py [--threads 1] [--seconds 20]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from pipeline.defense.chain import OnboardChain  # noqa: E402
from pipeline.defense.fusion import Defense  # noqa: E402
from pipeline.defense.gate import MotionSettings  # noqa: E402
from pipeline.defense.noise import NoiseModel  # noqa: E402
from pipeline.defense.settings import DefenseSettings  # noqa: E402
from pipeline.detectors.lstm import LSTMConfig, LSTMDetector  # noqa: E402
from pipeline.geometry.trajectories import look_at  # noqa: E402
from pipeline.pose.model import PoseNet  # noqa: E402
from pipeline.report.markdown import markdown_table  # noqa: E402
from stages.report import write_benchmark  # noqa: E402

CONFIGS = [("default", 0.25, 90, 160), ("paper", 1.0, 270, 480)]
NOISE = NoiseModel((0.05, 0.05, 0.1), (0.004, 0.004, 0.015), 1.0, 0.02)


def interleaved(fns: dict[str, Callable[[], object]], seconds: float) -> dict[str, dict[str, float]]:
    """Median process CPU and wall seconds per call of each function, called in turn for about
    `seconds` in all (at least 5 rounds, at most 4000). On a CPU shared with other jobs the CPU time is the
    steadier measure of what a call costs."""
    for fn in fns.values():
        fn()
    cpu: dict[str, list[float]] = {k: [] for k in fns}
    wall: dict[str, list[float]] = {k: [] for k in fns}
    start = time.perf_counter()
    while (time.perf_counter() - start < seconds or len(cpu[next(iter(fns))]) < 5) and len(cpu[next(iter(fns))]) < 4000:
        for key, fn in fns.items():
            w, c = time.perf_counter(), time.process_time()
            fn()
            cpu[key].append(time.process_time() - c)
            wall[key].append(time.perf_counter() - w)
    return {k: {"cpu": float(np.median(cpu[k])), "wall": float(np.median(wall[k]))} for k in fns}


def chains(width: float, h: int, w: int) -> tuple[OnboardChain, OnboardChain]:
    """(fast chain, plain chain) over one random PoseNet and LSTM detector."""
    model = PoseNet(width=width).eval()
    detector = LSTMDetector(LSTMConfig()).eval()
    with torch.no_grad():
        bg_mean = model.forward_features(torch.rand(8, 3, h, w)).mean(0)
    plain = OnboardChain.from_model(model, bg_mean, detector, fast=False)
    detector.set_normalisation(plain(torch.rand(8, 3, h, w)).shap.numpy())
    return OnboardChain.from_model(model, bg_mean, detector), plain


def equality(fast: OnboardChain, plain: OnboardChain, h: int, w: int) -> tuple[float, bool]:
    """Largest |fast - plain| probability over 16 random frames (batched and one by one), and
    whether the poses are identical."""
    x = torch.rand(16, 3, h, w)
    a, b = fast(x), plain(x)
    one = torch.cat([fast(x[i]).prob for i in range(len(x))])
    diff = max(float((a.prob - b.prob).abs().max()), float((one - b.prob).abs().max()))
    return diff, bool(torch.equal(a.pose, b.pose))


def defended(chain: OnboardChain, x: torch.Tensor, frames: int = 5000) -> Callable[[], object]:
    """One frame through the chain and then `Defense.step` (motion filter, gate, fusion, mode) on
    a smooth approach whose camera attitudes are computed beforehand (the chaser knows them).
    Random weights give meaningless poses, so the filter reads the approach's true position; the
    chain's probability goes in, against a threshold above the random detector's outputs, which
    keeps the defense on its common path (frames accepted)."""
    defense = Defense(DefenseSettings(threshold=0.999), MotionSettings(), NOISE)
    u = np.array([0.0, 0.0, -0.005])
    rel = np.array([3.0, -2.0, 40.0]) + np.arange(frames)[:, None] * u
    R_cam = look_at(rel)
    t_cam = np.einsum("nji,nj->ni", R_cam, rel)
    R_pred = np.swapaxes(R_cam, 1, 2).copy()
    frame = iter(range(frames))

    def step() -> object:
        out = chain(x)
        k = next(frame)
        return defense.step(t_cam[k], float(out.prob[0]), R_cam[k], u, R_pred[k])

    return step


def alone(fn: Callable[[], object], seconds: float) -> float:
    """Median process CPU seconds of `fn()` called over and over (caches warm), in batches of 100."""
    fn()
    times: list[float] = []
    start = time.perf_counter()
    while time.perf_counter() - start < seconds or len(times) < 20:
        c = time.process_time()
        for _ in range(100):
            fn()
        times.append((time.process_time() - c) / 100)
    return float(np.median(times))


def defense_alone(seconds: float) -> float:
    """`alone` for `Defense.step` on a smooth approach (its cost does not depend on the image size)."""
    d = Defense(DefenseSettings(), MotionSettings(), NOISE)
    rel, u = np.array([3.0, -2.0, 40.0]), np.array([0.0, 0.0, -0.005])
    R_cam = look_at(rel)
    state = {"rel": rel}

    def step() -> object:
        state["rel"] = state["rel"] + u
        return d.step(R_cam.T @ state["rel"], 0.0, R_cam, u, R_cam.T)

    return alone(step, seconds)


def row(name: str, width: float, h: int, w: int, seconds: float) -> dict[str, object]:
    fast, plain = chains(width, h, w)
    diff, same_pose = equality(fast, plain, h, w)
    x = torch.rand(1, 3, h, w)
    with torch.inference_mode():
        features = fast.model.forward_features(x)
        tail = alone(lambda: fast._fast(features), seconds / 8)
    t = interleaved(
        {
            "pose": lambda: fast.pose_only(x),
            "chain": lambda: fast(x),
            "defended": defended(fast, x),
            "plain": lambda: plain(x),
        },
        seconds,
    )
    pose = t["pose"]["cpu"]
    ratio = t["defended"]["cpu"] / pose
    return {
        "config": name,
        "input": f"{w}x{h}",
        "width": width,
        "pose CPU (ms)": pose * 1e3,
        "chain CPU (ms)": t["chain"]["cpu"] * 1e3,
        "SHAP + detector alone (ms)": tail * 1e3,
        "chain ratio": t["chain"]["cpu"] / pose,
        "chain wall ratio": t["chain"]["wall"] / t["pose"]["wall"],
        "defense in the loop (ms)": (t["defended"]["cpu"] - t["chain"]["cpu"]) * 1e3,
        "chain + defense ratio": ratio,
        "plain chain ratio": t["plain"]["cpu"] / pose,
        "max prob diff to plain": f"{diff:.1e}",
        "pose identical": "yes" if same_pose else "no",
        "target <= 1.05x": "yes" if ratio <= 1.05 else "no",
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--threads", type=int, default=1, help="torch CPU threads (1: steadier on a CPU shared with other jobs)"
    )
    ap.add_argument("--seconds", type=float, default=20.0, help="timing budget per configuration")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    load = os.getloadavg()[0]
    defense = defense_alone(args.seconds / 8)
    print(f"defense step alone: {defense * 1e3:.3f} ms CPU", flush=True)
    rows = []
    for name, width, h, w in CONFIGS:
        rows.append(row(name, width, h, w, args.seconds))
        print({k: v for k, v in rows[-1].items()}, flush=True)
    table = markdown_table(rows, decimals=3)
    print(table)
    print(f"-> {write_benchmark('Safety chain latency', body(table, rows, defense, args.threads, load))}")


def body(table: str, rows: list[dict[str, object]], defense: float, threads: int, load: float) -> str:
    """The benchmark section's text around `table`."""
    d = rows[0]
    in_chain = float(d["chain CPU (ms)"]) - float(d["pose CPU (ms)"])
    verdict = "meets" if float(d["chain + defense ratio"]) <= 1.05 else "does not meet"
    return f"""`benchmarks/chain_latency.py` on {platform.processor() or platform.machine()}, torch
{torch.__version__}, {threads} thread(s), batch 1, random weights, medians of interleaved calls on the
same model object; load average {load:.1f} at the start, {os.getloadavg()[0]:.1f} at the end, on
{os.cpu_count()} cores (ratios are of process CPU time, which other processes' CPU use would not
inflate, though their use of the shared caches would).

The chain computes the GAP features once and uses them for the pose heads and, in one traced and
frozen TorchScript graph (`pipeline.defense.chain.FoldedShapLSTM`), for the closed-form SHAP values and
the LSTM detector: the SHAP scaling and the detector's standardisation are folded into one
multiply-add, the gates are reordered so one sigmoid covers three of them, and the cell's ReLU on
c is dropped (c is never negative). "plain chain" is the unfolded path (SHAP values, then the
detector module), kept for other detectors and devices. The defense (pipeline/defense/fusion.py: motion
filter, chi-square gate, fusion, recovery mode) costs {defense * 1e3:.3f} ms of CPU per frame alone;
"defense in the loop" is what it adds after the chain. The fast chain's pose is the plain chain's,
and its probabilities equal the plain chain's within "max prob diff to plain" (tests/test_chain.py
checks 1e-4 at real sizes). At 480x270 one call takes ~180 ms and the medians of a few dozen
calls differ by a few ms from run to run, more than the defense costs: its column there is noise.

At the default size the defended chain {verdict} the 1.05x target. What the chain and the defense
add is not their arithmetic but the caches the pose network's convolutions leave cold: SHAP +
detector cost {float(d["SHAP + detector alone (ms)"]):.3f} ms alone and {in_chain:.3f} ms in the chain, the
defense {defense * 1e3:.3f} ms alone and {float(d["defense in the loop (ms)"]):.3f} ms in the loop. Each frame
the detector fetches its 1.6 MB input-projection weight (400 x 1000 fp32) and the code and data of
every small op again, after the convolutions have pushed them out of the core's caches (a small numpy
call costs 5-10 us there, ~1 us warm, which is why the motion filter's per-frame path is plain
floats).

Measured while this was built (same machine, load 1-9; ms alone / in the chain): the ratios are not
contention from other jobs: with nothing else on the machine (load 1.0, this benchmark alone) they
were 1.104x / 1.156x (chain / chain + defense), with other jobs running 1.098x / 1.147x. The folded graph
replaced a traced detector on the SHAP values that cost 0.40 / ~0.6; it is 1.8x faster on batches
of 64 frames (7.1 against 12.9 ms), but in the chain the two are within the noise of these runs
(1.095-1.102x against 1.100-1.108x the pose forward, interleaved). The float motion filter cut the
defense in the loop from 0.37-0.40 to 0.22-0.25 (chain + defense 1.194x -> 1.158x in one
interleaved run). Lower-precision weights would halve the projection's bytes but move the
probabilities by more than 1e-4 on the trained detector (fp16 weights through fbgemm: up to
3.0e-4 over 3000 rows of datasets/shap.zarr; bf16: 4.6e-3); folding the SHAP scaling into the
projection (9 distinct 1000 x 400 matrices) does the same multiply-adds from 9x the bytes (0.26-0.34
for the product alone against 0.12); a prepacked oneDNN weight speeds the projection alone (0.086
against 0.124) but not after the pose network (0.32 against 0.28); a numpy recurrence (0.30 / 0.59)
and torch.compile (0.17 alone, 77 s to compile) lose to the traced graph (0.28 / 0.51); a
numba-compiled recurrence would save ~0.09 in the chain (0.22 / 0.42), but numba is not a
dependency (it comes with the test extra's shap).

{table}"""


if __name__ == "__main__":
    main()
