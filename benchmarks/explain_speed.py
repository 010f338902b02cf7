"""Per-image cost of the SHAP explanation and of the LSTM detector, next to the pose network itself.

Times, on the pose network's head (1000 GAP features -> 9 outputs) with the default background:
the closed-form DeepSHAP of pipeline/shap.py, the shap library's DeepExplainer, and captum's
DeepLiftShap when captum is installed; then the LSTM detector and the pose network per frame.
Uses models/pose.pt and models/detector.pt when they exist, else randomly initialised models of
the default architecture (timings do not depend on the weights). Prints a table and writes the
`## Explanations` section of reports/benchmarks.md.

    .venv/bin/python benchmarks/explain_speed.py [--background 200] [--threads 1]
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

from pipeline.detectors.lstm import LSTMConfig, LSTMDetector  # noqa: E402
from pipeline.pose.model import PoseNet  # noqa: E402
from pipeline.report.markdown import markdown_table  # noqa: E402
from pipeline.shap import Explainer, deep_shap  # noqa: E402
from stages.report import write_benchmark  # noqa: E402


def per_call(fn: Callable[[], object], min_seconds: float = 1.0, max_calls: int = 10_000) -> float:
    """Median seconds per call of fn (one warm-up call, then repeated for about min_seconds)."""
    fn()
    times: list[float] = []
    start = time.perf_counter()
    while len(times) < max_calls and (time.perf_counter() - start < min_seconds or len(times) < 3):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def load_models(width: float) -> tuple[PoseNet, LSTMDetector, str]:
    """The standard chain's trained pose model and detector when a run left them in models/ (read by the one door,
    pipeline.formats.chain.load_chain), else random ones of the default architecture."""
    os.chdir(ROOT)
    if Path("models/pose.pt").exists() and Path("models/detector.pt").exists():
        from pipeline.formats.chain import load_chain

        chain = load_chain(Path("models"), "standard", defended=False)
        return chain.model, chain.onboard.detector, "models/pose.pt, models/detector.pt"
    return (
        PoseNet(width=width).eval(),
        LSTMDetector(LSTMConfig()).eval(),
        f"random PoseNet(width={width}), random LSTM detector (100 units, dense [64])",
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--background", type=int, default=200, help="background images (shap.background)")
    ap.add_argument("--deep-images", type=int, default=4, help="images explained by DeepExplainer per call")
    ap.add_argument("--threads", type=int, default=1, help="torch threads")
    ap.add_argument("--width", type=float, default=0.25, help="pose width when models/pose.pt is absent")
    ap.add_argument("--size", type=int, nargs=2, default=[90, 160], metavar=("H", "W"), help="input size")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    pose, det, source = load_models(args.width)
    h, w = args.size
    with torch.no_grad():
        background = pose.forward_features(torch.rand(args.background, 3, h, w)).numpy()
        feats = pose.forward_features(torch.rand(256, 3, h, w)).numpy()
    explainer = Explainer(pose, background, method="auto")
    assert explainer.method == "exact", "the pose heads are expected to be linear"

    rows = []
    t_exact_1 = per_call(lambda: explainer(feats[:1]))
    t_exact_b = per_call(lambda: explainer(feats)) / len(feats)
    rows.append({"method": "closed form (pipeline.shap), 1 image", "ms / image": t_exact_1 * 1e3})
    rows.append({"method": "closed form, batch of 256", "ms / image": t_exact_b * 1e3})
    k = args.deep_images
    t_deep = per_call(lambda: deep_shap(pose, feats[:k], background, batch_size=k), min_seconds=3.0) / k
    rows.append({"method": f"shap.DeepExplainer on the head, batch of {k}", "ms / image": t_deep * 1e3})
    rows.append(_captum_row(pose, background, feats[:k], k))

    values = torch.as_tensor(explainer(feats))
    with torch.no_grad():
        t_det_1 = per_call(lambda: det(values[:1]))
        t_det_b = per_call(lambda: det(values)) / len(values)
        x1 = torch.rand(1, 3, h, w)
        t_pose = per_call(lambda: pose(x1))
    timing = [
        {"per frame": "pose network forward (1 image)", "ms": t_pose * 1e3},
        {"per frame": "closed-form SHAP (1 image)", "ms": t_exact_1 * 1e3},
        {"per frame": "LSTM detector (1 frame)", "ms": t_det_1 * 1e3},
        {"per frame": "LSTM detector (batch of 256, per frame)", "ms": t_det_b * 1e3},
        {"per frame": "safety chain = pose + SHAP + detector (1 frame)", "ms": (t_pose + t_exact_1 + t_det_1) * 1e3},
    ]
    ratios = (t_deep / t_exact_1, t_deep / t_exact_b, (t_pose + t_exact_1 + t_det_1) / t_pose)
    body = _body(args, source, (w, h), rows, timing, ratios)
    print(body)
    print(f"-> {write_benchmark('Explanations', body)} (## Explanations)")


def _captum_row(pose: PoseNet, background: np.ndarray, feats: np.ndarray, k: int) -> dict[str, object]:
    """The row of captum's DeepLiftShap on the pose head (9 targets) over the features `feats` (k, 1000), a batch
    of k: ms per image, or "not installed"."""
    try:
        from captum.attr import DeepLiftShap

        from pipeline.shap import Head

        head = Head(pose).eval()
        dls = DeepLiftShap(head)
        bg_t, x_t = torch.as_tensor(background), torch.as_tensor(feats)
        t_captum = (
            per_call(lambda: [dls.attribute(x_t, baselines=bg_t, target=j) for j in range(9)], min_seconds=3.0) / k
        )
        return {"method": f"captum DeepLiftShap on the head (9 targets), batch of {k}", "ms / image": t_captum * 1e3}
    except ImportError:
        return {"method": "captum DeepLiftShap", "ms / image": "not installed"}


def _body(
    args: argparse.Namespace,
    source: str,
    size: tuple[int, int],
    rows: list[dict[str, object]],
    timing: list[dict[str, object]],
    ratios: tuple[float, float, float],
) -> str:
    """The Markdown of the `## Explanations` section: the models' `source`, input size (W, H) pixels, the tables,
    and the ratios (DeepExplainer / closed form at 1 image and batched, whole chain / pose network)."""
    (w, h), (ratio, batched, chain) = size, ratios
    load = os.getloadavg()[0]
    return f"""`benchmarks/explain_speed.py` on {platform.processor() or platform.machine()} ({os.cpu_count()} cores, load
average {load:.1f} when it ran), torch {torch.__version__}, {args.threads} thread(s); models: {source};
input {w}x{h}; background of {args.background} images.
Explaining the 9 outputs over the 1000 GAP features (a 9 x 1000 array per image):

{markdown_table(rows, decimals=4)}
The closed form is **{ratio:,.0f} times** faster per image than shap's DeepExplainer on the same head
(batched: {batched:,.0f} times), and gives the same values (tests/test_explain.py: max
difference < 1e-5).

{markdown_table(timing, decimals=3)}
The whole safety chain costs {chain:.2f}x the pose network alone.
"""


if __name__ == "__main__":
    main()
