"""Rendering scale-out on Ray: images/s with 1 and 2 Ray workers at 160x90 and 480x270 beside the
one-process path, Ray's overhead (start-up, workers, per chunk), and optionally the default render
stage both ways; writes the '## Rendering on Ray' section of reports/benchmarks.md.

Usage: .venv/bin/python benchmarks/render_scale.py [--frames 320 120] [--chunk 20] [--stage]
Settings from params.yaml (render.*, camera.*); poses spread over the approach sequences (60 to 10 m).
Every path writes a real zarr store through stages/engine/chunks.py, the same code `rpod render` runs.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import psutil

from pipeline.report.markdown import markdown_table
from stages.config import params as params_mod
from stages.config.build import intrinsics, scene_settings
from stages.config.schema import Params
from stages.engine import pool as engine
from stages.engine.chunks import FrameRange, render_to_store
from stages.report import write_benchmark

SIZES = [(160, 90), (480, 270)]


@dataclass(frozen=True)
class NoSetup:
    """A Noop worker's setup: nothing."""


class Noop:
    """A worker that does nothing: its chunks time the engine's own cost per chunk."""

    def __init__(self, setup: NoSetup) -> None:
        pass

    def run(self, job: FrameRange) -> dict[str, str]:
        return {}

    def close(self) -> None:
        pass


class CpuMeter:
    """CPU seconds (user + system) of this process and every process it started (Ray's workers), sampled
    every 0.2 s by a thread, since a worker's time is lost once Ray stops it (so up to 0.2 s per worker
    may be missed)."""

    def __init__(self) -> None:
        import threading

        self.seen: dict[int, float] = {}
        self.sample()
        self.start = sum(self.seen.values())
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._loop, daemon=True)
        self.thread.start()

    def _loop(self) -> None:
        while not self.done.wait(0.2):
            self.sample()

    def sample(self) -> None:
        for proc in [psutil.Process(), *psutil.Process().children(recursive=True)]:
            try:
                t = proc.cpu_times()
                self.seen[proc.pid] = max(self.seen.get(proc.pid, 0.0), t.user + t.system)
            except psutil.Error:
                pass

    def stop(self) -> float:
        """CPU seconds used since the meter started."""
        self.done.set()
        self.thread.join()
        self.sample()
        return sum(self.seen.values()) - self.start


def timed_render(
    p: Params, w: int, h: int, n: int, chunk: int, es: engine.EngineSettings
) -> tuple[float, float, np.ndarray]:
    """(wall s, CPU s of all processes, images) of rendering n poses at w x h into a fresh store."""
    import zarr

    from stages.render import frames

    K = intrinsics(dataclasses.replace(p, render=dataclasses.replace(p.render, width=w, height=h)))
    _, _, R, t = frames(p)
    idx = np.linspace(0, len(t) - 1, n).round().astype(int)
    meter = CpuMeter()
    with tempfile.TemporaryDirectory() as d:
        url = str(Path(d) / "images.zarr")
        t0 = time.perf_counter()
        render_to_store(url, K, scene_settings(p.render), R[idx], t[idx], chunk, es, f"{w}x{h}")
        wall = time.perf_counter() - t0
        images = zarr.open_group(url, mode="r")["images"][:]
    return wall, meter.stop(), images


def ray_overhead(p: Params, cores: int, jobs: int = 200) -> dict[str, float]:
    """Seconds: starting and stopping a local Ray, creating a worker, one chunk's dispatch, and
    starting a Blender worker (bpy import, scene build) that renders one frame at 160x90."""
    import ray

    es = engine.EngineSettings(workers=1, address="local", timeout_s=600, retries=2)
    t0 = time.perf_counter()
    with engine.session(engine.EngineSettings(cores, None, 600, 2)):
        up = time.perf_counter() - t0
        t0 = time.perf_counter()
        engine.run(Noop, NoSetup(), [FrameRange(0, 1)], es)
        first = time.perf_counter() - t0
        t0 = time.perf_counter()
        engine.run(Noop, NoSetup(), [FrameRange(0, 1)], es)  # a warm worker pool: the baseline for the per-chunk cost
        one = time.perf_counter() - t0
        t0 = time.perf_counter()
        engine.run(Noop, NoSetup(), [FrameRange(i, i + 1) for i in range(jobs + 1)], es)
        per_chunk = (time.perf_counter() - t0 - one) / jobs
        blender = timed_render(p, 160, 90, 1, 1, es)[0]
        t0 = time.perf_counter()
    down = time.perf_counter() - t0
    assert not ray.is_initialized()
    return {
        "Ray start-up (s)": up,
        "Ray shut-down (s)": down,
        "worker start + first chunk (s)": first,
        "per chunk (s)": max(per_chunk, 0.0),
        "Blender worker start + 1 frame (s)": blender,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, nargs=2, default=[640, 160], help="poses at 160x90 and at 480x270")
    ap.add_argument("--chunk", type=int, default=20, help="frames per chunk (one job)")
    ap.add_argument("--stage", action="store_true", help="also time the default render stage both ways")
    args = ap.parse_args()
    p = params_mod.load()
    cores, load = os.cpu_count() or 1, os.getloadavg()
    over = ray_overhead(p, cores)
    print(over, flush=True)
    rows = []
    for (w, h), n in zip(SIZES, args.frames):
        ref = None
        for label, es in [
            ("one process", engine.EngineSettings(1, None, 600, 2)),
            ("Ray, 1 worker", engine.EngineSettings(1, "local", 600, 2)),
            ("Ray, 2 workers", engine.EngineSettings(2, None, 600, 2)),
        ]:
            with engine.session(engine.EngineSettings(cores, None, 600, 2) if es.address else es):
                wall, cpu, images = timed_render(p, w, h, n, args.chunk, es)
            ref = images if ref is None else ref
            rows.append(
                {
                    "size": f"{w}x{h}",
                    "path": label,
                    "images": n,
                    "wall s": wall,
                    "images/s": n / wall,
                    "CPU s/image (all processes)": cpu / n,
                    "same pixels as one process": np.array_equal(images, ref),
                }
            )
            print(rows[-1], flush=True)
    body = [
        f"`benchmarks/render_scale.py` ({platform.processor() or platform.machine()}, {cores} CPU cores; "
        f"load average {load[0]:.1f} at the start, {os.getloadavg()[0]:.1f} at the end: other processes on "
        f"the machine were not stopped). {p.render.samples} samples, denoiser {p.render.denoiser}; "
        f"chunks of {args.chunk} frames written straight into one zarr store by whichever path renders them. "
        f"Wall times include starting the workers (Ray's own start-up is in the second table); a Ray worker "
        f"renders with render.threads / workers Blender threads ({p.render.threads} / 1, 1 each for 2) and "
        f"is bound to as many cores of its own (`stages.engine.pool.pin_cores`): unbound, a Blender scene at 1 thread "
        f"still used both cores (its scene sync runs on a pool sized to the machine) and two workers collided.",
        "",
        markdown_table(rows, decimals=3),
        "",
        "Ray's overhead, measured with a worker that does nothing (one local Ray started and stopped once per "
        "stage; every stage builds its workers and their Blender scenes once), and the start of one Blender "
        "worker:",
        "",
        markdown_table([over], decimals=3),
    ]
    if args.stage:
        body += ["", stage_times(p)]
    print(f"wrote the Rendering on Ray section of {write_benchmark('Rendering on Ray', chr(10).join(body))}")


def stage_times(p: Params) -> str:
    """The default render stage (`render_all`, no previews) in-process and with Ray on every core, each twice
    in the order in-process, Ray, Ray, in-process so that a drift in the machine's load hits both alike."""
    from stages.render import render_all

    rows = []
    ways = [("in-process (engine.workers: 1)", 1), ("Ray on every core (engine.workers: null)", None)]
    for label, workers in [*ways, *ways[::-1]]:
        q = dataclasses.replace(p, engine=dataclasses.replace(p.engine, workers=workers))
        with tempfile.TemporaryDirectory() as d:
            meter, t0 = CpuMeter(), time.perf_counter()
            render_all(q, Path(d))
            wall = time.perf_counter() - t0
            rows.append(
                {
                    "render stage": label,
                    "frames": 13 * p.render.frames_per_sequence,
                    "wall s": wall,
                    "CPU s (all processes)": meter.stop(),
                    "load average after": os.getloadavg()[0],
                }
            )
        print(rows[-1], flush=True)
    mean = {label: np.mean([r["wall s"] for r in rows if r["render stage"] == label]) for label, _ in ways}
    (one, _), (ray_, _) = ways
    return (
        "The whole default render stage (params.yaml, previews left out), both ways, twice (in the order "
        "in-process, Ray, Ray, in-process); the Ray rows include starting and stopping Ray, and their CPU time "
        "that of Ray's own service processes (raylet, GCS server) and of each worker's bpy import:\n\n"
        + markdown_table(rows, decimals=1)
        + f"\n\nMean wall time: in-process {mean[one]:.1f} s, Ray {mean[ray_]:.1f} s "
        f"({mean[one] / mean[ray_]:.2f}x the in-process speed)."
    )


if __name__ == "__main__":
    main()
