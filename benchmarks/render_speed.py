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
from pathlib import Path

import numpy as np

from pipeline.report import markdown_table, replace_section
from stages import params as params_mod
from stages.render import frames, scene_settings

REPORT = Path("reports/benchmarks.md")
SIZES = [(160, 90), (240, 135), (480, 270)]


def poses(p: dict, n: int) -> tuple[np.ndarray, np.ndarray]:
    """n poses spread over all sequences and ranges."""
    _, _, R, t = frames(p)
    idx = np.linspace(0, len(t) - 1, n).round().astype(int)
    return R[idx], t[idx]


def speed(K, settings, R: np.ndarray, t: np.ndarray) -> tuple[float, float, list[np.ndarray]]:
    """(scene build seconds, seconds per image, images) after one warm-up frame."""
    from pipeline.scene import Renderer

    t0 = time.perf_counter()
    r = Renderer(K, settings)
    build = time.perf_counter() - t0
    try:
        r.render(R[0], t[0])
        t0 = time.perf_counter()
        imgs = [r.render(Ri, ti) for Ri, ti in zip(R, t)]
        per = (time.perf_counter() - t0) / len(R)
    finally:
        r.close()
    return build, per, imgs


def psnr(a: list[np.ndarray], b: list[np.ndarray]) -> float:
    mse = np.mean([(x.astype(np.float64) - y.astype(np.float64)) ** 2 for x, y in zip(a, b)])
    return float(10 * np.log10(255.0 ** 2 / max(mse, 1e-12)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=30, help="timed frames per resolution")
    args = ap.parse_args()
    p = params_mod.load()
    from stages.render import intrinsics

    base = scene_settings(p["render"])
    R, t = poses(p, args.frames)
    rows = []
    for w, h in SIZES:
        K = intrinsics({**p, "render": {**p["render"], "width": w, "height": h}})
        build, per, _ = speed(K, base, R, t)
        rows.append({"size": f"{w}x{h}", "images/s": 1 / per, "s/image": per, "scene build (s)": build})
        print(f"{w}x{h}: {1 / per:.1f} images/s ({per * 1000:.0f} ms/image), scene build {build:.2f} s", flush=True)

    # Quality vs time at the default size: PSNR against a 64-sample, OIDN-HIGH reference of the same poses.
    K = intrinsics(p)
    nq = min(10, args.frames)
    Rq, tq = poses(p, nq)
    ref = speed(K, dataclasses.replace(base, samples=64, denoiser="OPENIMAGEDENOISE", denoise_quality="HIGH"), Rq, tq)
    variants = [(2, "NONE"), (8, "NONE"), (32, "NONE"), (2, "OPENIMAGEDENOISE"), (4, "OPENIMAGEDENOISE"),
                (8, "OPENIMAGEDENOISE"), (16, "OPENIMAGEDENOISE")]
    qrows = []
    for spp, den in variants:
        s = dataclasses.replace(base, samples=spp, denoiser=den)
        _, per, imgs = speed(K, s, Rq, tq)
        chosen = spp == base.samples and den == base.denoiser.upper()
        qrows.append({"samples": spp, "denoiser": den + (" (FAST)" if den != "NONE" else ""),
                      "s/image": per, "PSNR vs reference (dB)": psnr(imgs, ref[2]), "chosen": "yes" if chosen else ""})
        print(f"{spp:3d} spp {den:17s} {per * 1000:6.0f} ms/image  PSNR {qrows[-1]['PSNR vs reference (dB)']:.1f} dB",
              flush=True)

    body = "\n".join([
        f"`benchmarks/render_speed.py` ({args.frames} poses spread over the 13 approach sequences, after one "
        f"warm-up frame; {platform.processor() or platform.machine()}, {os.cpu_count()} CPU cores, "
        f"threads={base.threads}; other processes on the machine were not stopped). Settings from params.yaml: "
        f"{base.samples} samples, denoiser {base.denoiser} ({base.denoise_quality}, prefilter FAST), "
        f"Cycles CPU, scene built once and the target moved per frame.",
        "",
        markdown_table(rows, decimals=3),
        f"Quality against time at {K.width}x{K.height} ({nq} poses; reference: 64 samples + OIDN HIGH). "
        "OIDN with albedo and normal passes removes most of the noise of a few samples; its accurate "
        "prefilter alone costs about twice the render time here, so the FAST prefilter is used.",
        "",
        markdown_table(qrows, decimals=3),
    ])
    REPORT.parent.mkdir(parents=True, exist_ok=True)
    md = REPORT.read_text() if REPORT.exists() else "# Benchmarks\n\nMeasured on the project machine.\n"
    REPORT.write_text(replace_section(md, "Rendering", body))
    print(f"wrote the Rendering section of {REPORT}")


if __name__ == "__main__":
    main()
