"""Rendering speed (images/s at 160x90, 240x135, 480x270) and the quality/time trade-off of the
Cycles sample count and denoiser at the default size; writes the '## Rendering' section of
reports/benchmarks.md (other sections are kept).

Usage: .venv/bin/python benchmarks/render_speed.py [--frames 30]
Settings come from params.yaml (render.*, camera.*); poses from the approach sequences (60 to 10 m).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import time
from typing import Any

import numpy as np

from pipeline.report.markdown import markdown_table
from stages.config import params as params_mod
from stages.config.build import intrinsics, scene_settings
from stages.config.schema import Params
from stages.render import frames
from stages.report import write_benchmark

SIZES = [(160, 90), (240, 135), (480, 270)]


def poses(p: Params, n: int) -> tuple[np.ndarray, np.ndarray]:
    """n poses spread over all sequences and ranges."""
    _, _, R, t = frames(p)
    idx = np.linspace(0, len(t) - 1, n).round().astype(int)
    return R[idx], t[idx]


def speed(K, settings, R: np.ndarray, t: np.ndarray) -> tuple[float, float, float, list[np.ndarray]]:
    """(scene build s, median wall s per image, CPU s per image (all threads), images) after one
    warm-up frame. On a shared machine the median resists load spikes, and CPU time per image
    divided by the thread count estimates the wall time on an idle machine."""
    from pipeline.render.scene import Renderer

    t0 = time.perf_counter()
    r = Renderer(K, settings)
    build = time.perf_counter() - t0
    imgs, times = [], []
    try:
        r.render(R[0], t[0])
        c0 = time.process_time()
        for Ri, ti in zip(R, t):
            t0 = time.perf_counter()
            imgs.append(r.render(Ri, ti))
            times.append(time.perf_counter() - t0)
        cpu = (time.process_time() - c0) / len(R)
    finally:
        r.close()
    return build, float(np.median(times)), cpu, imgs


def psnr(a: list[np.ndarray], ref: list[np.ndarray]) -> float:
    """PSNR (dB) over the pixels near the target (reference non-black, dilated by 2 px): the black
    background would otherwise dominate the mean."""
    import cv2

    err, n = 0.0, 0
    for x, y in zip(a, ref):
        mask = cv2.dilate((y.max(-1) > 0).astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
        err += float(((x[mask].astype(np.float64) - y[mask].astype(np.float64)) ** 2).sum())
        n += int(mask.sum()) * 3
    return float(10 * np.log10(255.0**2 / max(err / max(n, 1), 1e-12)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=30, help="timed frames per resolution")
    args = ap.parse_args()
    p = params_mod.load()
    load = os.getloadavg()
    base = scene_settings(p.render)
    R, t = poses(p, args.frames)
    rows = _size_rows(p, base, R, t)

    # Quality vs time at the default size: PSNR against a 256-sample, undenoised reference of the same poses.
    K = intrinsics(p)
    nq = min(10, args.frames)
    Rq, tq = poses(p, nq)
    ref = speed(K, dataclasses.replace(base, samples=256, denoiser="NONE"), Rq, tq)[3]
    qrows = _quality_rows(K, base, Rq, tq, ref)
    body = _body(args.frames, base, load, rows, K, nq, qrows)
    print(f"wrote the Rendering section of {write_benchmark('Rendering', body)}")


def _size_rows(p: Params, base: Any, R: np.ndarray, t: np.ndarray) -> list[dict[str, Any]]:
    """Per size of SIZES the speed of the `base` scene settings over the poses R, t (one row each, printed)."""
    rows = []
    for w, h in SIZES:
        K = intrinsics(dataclasses.replace(p, render=dataclasses.replace(p.render, width=w, height=h)))
        build, per, cpu, _ = speed(K, base, R, t)
        idle = f"{1 / cpu:.1f} to {base.threads / cpu:.1f}"  # wall time per image lies in [cpu / threads, cpu]
        rows.append(
            {
                "size": f"{w}x{h}",
                "images/s": 1 / per,
                "median s/image": per,
                "CPU s/image": cpu,
                "images/s on an idle machine (est.)": idle,
                "scene build (s)": build,
            }
        )
        print(
            f"{w}x{h}: {1 / per:.1f} images/s ({per * 1000:.0f} ms/image; CPU {cpu * 1000:.0f} ms/image, "
            f"idle estimate {idle} images/s), scene build {build:.2f} s",
            flush=True,
        )
    return rows


def _quality_rows(K: Any, base: Any, Rq: np.ndarray, tq: np.ndarray, ref: list[np.ndarray]) -> list[dict[str, Any]]:
    """Per sample count and denoiser its time per image at K and PSNR (dB) against the reference images `ref` of
    the poses Rq, tq (one row each, printed)."""
    variants = [
        (2, "NONE"),
        (4, "NONE"),
        (8, "NONE"),
        (16, "NONE"),
        (32, "NONE"),
        (2, "OPENIMAGEDENOISE"),
        (4, "OPENIMAGEDENOISE"),
        (8, "OPENIMAGEDENOISE"),
        (16, "OPENIMAGEDENOISE"),
    ]
    qrows = []
    for spp, den in variants:
        s = dataclasses.replace(base, samples=spp, denoiser=den)
        _, per, cpu, imgs = speed(K, s, Rq, tq)
        chosen = spp == base.samples and den == base.denoiser.upper()
        qrows.append(
            {
                "samples": spp,
                "denoiser": den + (" (FAST)" if den != "NONE" else ""),
                "median s/image": per,
                "CPU s/image": cpu,
                "PSNR vs reference (dB)": psnr(imgs, ref),
                "chosen": "yes" if chosen else "",
            }
        )
        print(
            f"{spp:3d} spp {den:17s} {per * 1000:6.0f} ms/image  CPU {cpu * 1000:6.0f} ms  "
            f"PSNR {qrows[-1]['PSNR vs reference (dB)']:.1f} dB",
            flush=True,
        )
    return qrows


def _body(
    frames: int,
    base: Any,
    load: tuple[float, float, float],
    rows: list[dict[str, Any]],
    K: Any,
    nq: int,
    qrows: list[dict[str, Any]],
) -> str:
    """The Markdown of the '## Rendering' section: the speed `rows` of `frames` poses and the quality `qrows` of
    `nq` poses at K (the load average `load` at the start, the current one at the end)."""
    return "\n".join(
        [
            f"`benchmarks/render_speed.py` ({frames} poses spread over the 13 approach sequences, after one "
            f"warm-up frame; {platform.processor() or platform.machine()}, {os.cpu_count()} CPU cores, "
            f"threads={base.threads}; load average {load[0]:.1f} at the start, {os.getloadavg()[0]:.1f} at the end: "
            f"other processes on the machine were not stopped). Settings from params.yaml: "
            f"{base.samples} samples, denoiser {base.denoiser}"
            f"{f' ({base.denoise_quality}, prefilter FAST)' if base.denoiser.upper() != 'NONE' else ''}, "
            f"Cycles CPU, scene built once and the target moved per frame.",
            "",
            markdown_table(rows, decimals=3),
            "`images/s` is measured as is (median wall time per frame, so it depends on what else runs); the "
            "idle-machine range, 1 / (CPU time per image) to threads / (CPU time per image), depends much less "
            "on other load. The target is at least 10 images/s at 160x90 and 1 image/s at 480x270. The "
            "OpenImageDenoise rows show why the default renders without a denoiser: at these sizes it adds "
            "50-75% CPU time and no PSNR.",
            "",
            f"Quality against time at {K.width}x{K.height} ({nq} poses; PSNR over the pixels near the target "
            "against a 256-sample render without denoising).",
            "",
            markdown_table(qrows, decimals=3),
        ]
    )


if __name__ == "__main__":
    main()
