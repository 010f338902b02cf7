"""What capping torch's CPU kernels at AVX2 costs and what it buys (issue 27, item 5); writes the
`## CPU instruction set` section of reports/benchmarks.md (other sections are kept).

Configurations, each in its own processes (the variables act only before torch loads):
native (`RPOD_CPU_ISA=native`: torch's own choice), each pin alone (`ATEN_CPU_CAPABILITY=avx2`,
`ONEDNN_MAX_CPU_ISA=AVX2`, `MKL_CBWR=AVX2`), and all three (what `rpod` sets by default
for torch, stages/config/cpu.py; it pins numpy's OpenBLAS and AVX-512 loops too, which this benchmark leaves alone).
- Speed: training images/s of the default pose network (train.width at render.width x height, batch
  train.batch_size, random images) and the pose forward of one image: the process's CPU time (all
  threads) and wall time, medians over --rounds rounds in which the configurations take turns.
- Same result: `rpod train` for --epochs epochs on the rendered default data (datasets/render and
  datasets/labels.parquet of --data), twice capped and twice native: are the weights bit-identical run
  to run, and how far apart are capped and native (largest weight difference, validation/test errors).
- Cycles: the same frames with the AVX2 kernel (what Cycles takes on any AVX2 CPU), its SSE4.2 kernel
  (debug flag) and 1 thread instead of render.threads: images/s and whether the pixels are identical.

Usage: python benchmarks/cpu_isa.py [--rounds 3] [--epochs 2] [--data /work/main] [--frames 40]
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
PINS = {"ATEN_CPU_CAPABILITY": "avx2", "ONEDNN_MAX_CPU_ISA": "AVX2", "MKL_CBWR": "AVX2"}
CONFIGS: dict[str, dict[str, str]] = {
    "native": {},
    **{f"{k}={v} alone": {k: v} for k, v in PINS.items()},
    "all three (rpod default)": PINS,
}


def env_of(pins: dict[str, str]) -> dict[str, str]:
    """The environment of a configuration: these pins and no others (`rpod` adds none: RPOD_CPU_ISA=native)."""
    env = {k: v for k, v in os.environ.items() if k not in PINS}
    env.update(
        {
            "RPOD_CPU_ISA": "native",
            "OMP_WAIT_POLICY": "PASSIVE",
            **pins,
            "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])),
        }
    )
    return env


def probe(kind: str, pins: dict[str, str], *extra: str) -> dict[str, Any]:
    """Run this script's `--probe kind` in a fresh process with `pins`; its JSON answer (last line)."""
    out = subprocess.run(
        [sys.executable, __file__, "--probe", kind, *extra], env=env_of(pins), cwd=ROOT, capture_output=True, text=True
    )
    if out.returncode != 0:
        raise SystemExit(f"probe {kind} failed:\n{out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def speed_probe(batches: int) -> dict[str, Any]:
    """(in a probe process) the default pose network: a training step (forward, backward, Adam; batch
    train.batch_size, random images) and the forward of one image, each timed `batches` x (and 4x as
    many forwards) after warm-ups: medians of wall time and of the process's CPU time (all threads; the
    figure other processes on the machine disturb least)."""
    import torch

    from pipeline.pose.loss import PoseLoss
    from pipeline.pose.model import PoseNet
    from stages.config import params as params_mod

    p = params_mod.load(ROOT / "params.yaml")
    torch.set_num_threads(p.threads or os.cpu_count() or 1)
    torch.manual_seed(0)
    h, w, b = p.render.height, p.render.width, p.train.batch_size
    model, loss = PoseNet(float(p.train.width)).to(memory_format=torch.channels_last), PoseLoss()
    opt = torch.optim.Adam([*model.parameters(), *loss.parameters()], lr=1e-4)
    x, y = torch.rand(b, 3, h, w).contiguous(memory_format=torch.channels_last), torch.rand(b, 9)

    def step() -> None:
        opt.zero_grad()
        loss(model(x), y).backward()
        opt.step()

    train = _timed(step, batches)
    model.eval()
    one = x[:1].contiguous(memory_format=torch.channels_last)
    with torch.inference_mode():
        forward = _timed(lambda: model(one), 4 * batches)
    return {
        "train_ips": b / train[0],
        "train_cpu_ms": 1000 * train[1] / b,
        "forward_ms": 1000 * forward[0],
        "forward_cpu_ms": 1000 * forward[1],
        "kernels": torch.backends.cpu.get_cpu_capability(),
    }


def _timed(call: Any, n: int) -> tuple[float, float]:
    """(median wall s, median process CPU s) of `n` calls after two warm-up calls."""
    call(), call()
    wall, cpu = [], []
    for _ in range(n):
        t0, c0 = time.perf_counter(), time.process_time()
        call()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return statistics.median(wall), statistics.median(cpu)


def render_probe(frames: int) -> dict[str, Any]:
    """(in a probe process) Cycles: images/s and a pixel hash per kernel and thread setting."""
    import bpy
    from render_speed import poses

    from pipeline.render.scene import Renderer
    from stages.config import params as params_mod
    from stages.config.build import intrinsics, scene_settings

    p = params_mod.load(ROOT / "params.yaml")
    K, base = intrinsics(p), scene_settings(p.render)
    R, t = poses(p, frames)
    out = {}
    for name, threads, avx2 in (
        (f"AVX2 kernel, {base.threads} threads", base.threads, True),
        ("AVX2 kernel, 1 thread", 1, True),
        (f"SSE4.2 kernel, {base.threads} threads", base.threads, False),
    ):
        r = Renderer(K, dataclasses.replace(base, threads=threads))
        prefs = bpy.context.preferences  # the scene's Cycles debug flags apply only with these two set
        prefs.experimental.use_cycles_debug = prefs.view.show_developer_ui = not avx2
        r.scene.cycles.debug_use_cpu_avx2 = avx2
        try:
            r.render(R[0], t[0])
            digest, t0, c0 = hashlib.sha256(), time.perf_counter(), time.process_time()
            for Ri, ti in zip(R, t):
                digest.update(r.render(Ri, ti).tobytes())
            out[name] = {
                "images_per_s": len(R) / (time.perf_counter() - t0),
                "cpu_ms": 1000 * (time.process_time() - c0) / len(R),
                "pixels": digest.hexdigest()[:16],
            }
        finally:
            r.close()
    return out


def train_runs(data: Path, epochs: int, work: Path) -> list[dict[str, Any]]:
    """`rpod train` for `epochs` epochs on data's renders in a scratch workspace: capped, native, capped,
    native; each run's weights (a checkpoint copy), errors and seconds."""
    from stages.config import params as params_mod

    (work / "datasets").mkdir(parents=True)
    for name in ("render", "labels.parquet"):
        (work / "datasets" / name).symlink_to(data / "datasets" / name)
    params_mod.write_params(params_mod.compose("default", [f"train.epochs={epochs}"]), work / "params.yaml")
    runs = []
    for i, cap in enumerate(("avx2", "native", "avx2", "native")):
        env = env_of({})
        env["RPOD_CPU_ISA"] = cap
        t0 = time.perf_counter()
        out = subprocess.run(
            [sys.executable, "-m", "stages.cli", "train"], cwd=work, env=env, capture_output=True, text=True
        )
        if out.returncode != 0:
            raise SystemExit(f"rpod train ({cap}) failed:\n{out.stderr[-2000:]}")
        m = json.loads((work / "reports/metrics/train.json").read_text())
        ckpt = work / f"pose_{i}_{cap}.pt"
        shutil.copy(work / "models/pose.pt", ckpt)
        runs.append(
            {
                "cap": cap,
                "checkpoint": ckpt,
                "seconds": time.perf_counter() - t0,
                "kernels": m["cpu_isa"]["kernels"],
                "val": m["val"],
                "test": m["test"],
            }
        )
    return runs


def weight_gap(a: Path, b: Path) -> tuple[bool, float]:
    """(bit-identical, largest difference relative to the tensor's largest magnitude) of two pose
    checkpoints' weights and buffers."""
    import torch

    wa, wb = (torch.load(x, weights_only=True)["model"] for x in (a, b))
    gap = max(
        float((wa[k].double() - wb[k].double()).abs().max() / max(float(wa[k].double().abs().max()), 1e-12))
        for k in wa
        if wa[k].numel()
    )
    return all(torch.equal(wa[k], wb[k]) for k in wa), gap


def speed_table(rounds: int, batches: int) -> list[dict[str, Any]]:
    """The configurations' speed, interleaved over `rounds` rounds (medians), relative to native."""
    seen: dict[str, list[dict[str, Any]]] = {name: [] for name in CONFIGS}
    for r in range(rounds):
        for name, pins in CONFIGS.items():
            seen[name].append(probe("speed", pins, "--batches", str(batches)))
            print(f"round {r + 1}: {name}: {seen[name][-1]}", flush=True)
    keys = ("train_ips", "train_cpu_ms", "forward_ms", "forward_cpu_ms")
    med = {name: {k: statistics.median(x[k] for x in v) for k in keys} for name, v in seen.items()}
    base = med["native"]
    return [
        {
            "configuration": name,
            "torch kernels": seen[name][0]["kernels"],
            "training CPU ms/image": m["train_cpu_ms"],
            "training cost vs native": m["train_cpu_ms"] / base["train_cpu_ms"],
            "training images/s (wall)": m["train_ips"],
            "forward CPU ms": m["forward_cpu_ms"],
            "forward cost vs native": m["forward_cpu_ms"] / base["forward_cpu_ms"],
            "forward ms (wall)": m["forward_ms"],
        }
        for name, m in med.items()
    ]


def train_table(runs: list[dict[str, Any]]) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Rows per training run and the comparisons: capped twice, native twice, capped against native."""
    rows = [
        {
            "run": f"{i + 1}: {r['cap']}",
            "torch kernels": r["kernels"],
            "seconds": r["seconds"],
            "val position (m)": r["val"]["pos_mean_m"],
            "val attitude (deg)": r["val"]["att_mean_deg"],
            "test position (m)": r["test"]["pos_mean_m"],
            "test attitude (deg)": r["test"]["att_mean_deg"],
        }
        for i, r in enumerate(runs)
    ]
    ck = [r["checkpoint"] for r in runs]
    same = {
        "capped twice": weight_gap(ck[0], ck[2]),
        "native twice": weight_gap(ck[1], ck[3]),
        "capped vs native": weight_gap(ck[0], ck[1]),
    }
    return rows, same


def write(
    speed: list[dict[str, Any]],
    train: tuple[list[dict[str, Any]], dict[str, Any]],
    render: dict[str, Any],
    args: argparse.Namespace,
    load: tuple[float, float],
) -> None:
    from pipeline.report.markdown import markdown_table
    from stages.report import write_benchmark

    rows, same = train
    verdict = "; ".join(
        f"{k}: {'bit-identical' if eq else f'differ (largest relative weight difference {gap:.1e})'}"
        for k, (eq, gap) in same.items()
    )
    capped = speed[-1]
    cost = (
        f"Capping all three costs {100 * (capped['training cost vs native'] - 1):+.0f}% CPU time per training "
        f"image and {100 * (capped['forward cost vs native'] - 1):+.0f}% per 1-image forward here."
    )
    rrows = [
        {
            "Cycles setting": k,
            "images/s": v["images_per_s"],
            "CPU ms/image (all threads)": v["cpu_ms"],
            "pixels (sha256 of all frames)": v["pixels"],
        }
        for k, v in render.items()
    ]
    body = f"""`benchmarks/cpu_isa.py` on {platform.processor() or platform.machine()}, {os.cpu_count()} cores; load
average {load[0]:.1f} at the start, {load[1]:.1f} at the end (other processes were not stopped: the
configurations take turns, {args.rounds} rounds, medians; the CPU-time columns, all threads of the
process, are the ones other processes disturb least, the wall-clock ones are as measured). `rpod` caps
torch's CPU kernels at AVX2
(stages/config/cpu.py; `RPOD_CPU_ISA=native` lifts the cap) so that a seed trains the same pose model on
machines with and without AVX-512 (without the cap: another model, then another detector verdict, on an AVX2 machine).

{markdown_table(speed, decimals=3)}
{cost}

`rpod train`, {args.epochs} epochs of the default recipe on the rendered default data, capped (AVX2)
and native, twice each: {verdict}.

{markdown_table(rows, decimals=3)}
Cycles (the renders): its CPU kernels are SSE4.2 and AVX2 only, and it takes AVX2 on any CPU that has
it, so it needs no pin; {args.frames} frames of the approach sequences at the default settings. The SSE4.2
row sets Cycles' debug flag (`debug_use_cpu_avx2` off, with the debug preferences on); whether Cycles
honoured it cannot be told from identical pixels and CPU time.

{markdown_table(rrows, decimals=3)}"""
    print(body)
    print(f"-> {write_benchmark('CPU instruction set', body)} (## CPU instruction set)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3, help="speed rounds (the configurations take turns)")
    ap.add_argument("--epochs", type=int, default=2, help="epochs of each `rpod train` run")
    ap.add_argument(
        "--data",
        type=Path,
        default=ROOT,
        help="repository whose datasets/render and datasets/labels.parquet to train on",
    )
    ap.add_argument("--frames", type=int, default=40, help="frames per Cycles setting")
    ap.add_argument("--batches", type=int, default=12, help="timed training steps per speed probe")
    ap.add_argument("--probe", choices=["speed", "render"], help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.probe:
        print(json.dumps(speed_probe(args.batches) if args.probe == "speed" else render_probe(args.frames)))
        return
    load0 = os.getloadavg()[0]
    speed = speed_table(args.rounds, args.batches)
    render = probe("render", PINS, "--frames", str(args.frames))
    with tempfile.TemporaryDirectory(prefix="cpu_isa_") as work:
        train = train_table(train_runs(args.data.resolve(), args.epochs, Path(work)))
    write(speed, train, render, args, (load0, os.getloadavg()[0]))


if __name__ == "__main__":
    main()
