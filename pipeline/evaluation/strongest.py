"""The pose models under the strongest-attack suite (issue 37; the suite: pipeline/attacks/strongest.py), as
JSON-ready dicts: a model's attacked-error table on test frames with its checks and its split by background, and
a model's attacker capacity on validation frames with its fitted overbound (pipeline/attacks/capacity.py).

Table (`attacked_table`, `table`): the suite over N frames at every eps, the worst case nested in eps (it cannot drop as
eps grows); rows (`suite_rows`): the clean images, then per eps each member's mean errors and the suite's worst
case: position (m), attitude (deg), range and lateral (m), each mean with its 95% interval. Checks, each per eps
and error (position, attitude):
- sanity (`sanity_rows`): the worst case is >= every member's on every frame and does not drop as eps grows;
- stability: the suite with doubled steps, restarts and queries on a seeded subsample moves the mean worst case
  by less than `TOLERANCE`;
- full: the suite over the full suite on a subsample within `TOLERANCE` (otherwise the suite's figures are lower
  bounds of the full suite's).
Backgrounds (`background_rows`): the clean errors and the worst case per eps on the frames of each background
kind (pipeline/render/backgrounds.py KINDS; no kinds given = every frame black).

Capacity (`capacity_frames`, `fit_overbound`): per validation frame and eps the largest shift of the estimate
from its clean estimate that the suite reached (along the true line of sight, across it, attitude change; the
frame's true range), and per eps its overbound in range bins (`fit_capacity`: a quantile times 1 + margin).
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np
import pandas as pd
import torch
from torch import nn

from pipeline.attacks.capacity import Capacity as Overbound
from pipeline.attacks.capacity import Shifts, fit_capacity
from pipeline.attacks.strongest import (
    SuiteConfig,
    SuiteResult,
    frame_capacity,
    ratio_rows,
    run_suite,
    sanity_rows,
    suite_rows,
)
from pipeline.render.backgrounds import KINDS, background_kinds

TOLERANCE = 0.05  # the stability and lean-vs-full checks: mean worst cases within 5% of each other


def attacked_table(
    model: nn.Module,
    images: np.ndarray,
    targets: np.ndarray,
    eps: Sequence[float],
    config: SuiteConfig,
    *,
    backgrounds: Sequence[str] | None = None,
    check: np.ndarray | None = None,
    full_check: np.ndarray | None = None,
    full: SuiteConfig | None = None,
    device: str | torch.device = "cpu",
) -> dict[str, Any]:
    """The suite `config` on clean uint8 images (N, H, W, 3) with true poses `targets` (N, 9: camera-frame
    position in m, 6-D rotation) at the increasing L-inf budgets `eps` (pixel units): its `table` (`backgrounds`
    (N,) each frame's background kind) with `stability` (the suite with doubled steps and restarts over it on the
    frames `check`, indices into the N) and `full_check` (it over the `full` suite on the frames `full_check`), each
    a `compare` or None when its frames are None or empty, and `cpu_seconds`: the process time of it all."""
    result = run_suite(model, images, targets, eps, config, device=device)
    out = {**table(result, backgrounds), "stability": None, "full_check": None}
    cpu = float(result.cpu_seconds.sum()) * result.frames
    for key, frames, other in (("stability", check, config.doubled()), ("full_check", full_check, full)):
        if frames is None or not len(frames):
            continue
        if other is None:
            raise ValueError("a full-suite check needs the full suite's config")
        run = run_suite(model, images[frames], targets[frames], eps, other, device=device)
        out[key] = compare(run, result.select(frames)) if key == "stability" else compare(result.select(frames), run)
        cpu += float(run.cpu_seconds.sum()) * run.frames
    return {**out, "cpu_seconds": cpu}


def table(result: SuiteResult, backgrounds: Sequence[str] | None = None) -> dict[str, Any]:
    """A suite run as {frames, eps, members, rows (`suite_rows`), sanity (`sanity_rows`), backgrounds
    (`background_rows`)}."""
    return {
        "frames": result.frames,
        "eps": list(result.eps),
        "members": list(result.members),
        "rows": suite_rows(result),
        "sanity": sanity_rows(result),
        "backgrounds": background_rows(result, backgrounds),
    }


def compare(result: SuiteResult, reference: SuiteResult) -> dict[str, Any]:
    """{frames, rows}: `ratio_rows` of two runs over the same frames and eps, within `TOLERANCE`."""
    return {"frames": result.frames, "rows": ratio_rows(result, reference, tolerance=TOLERANCE)}


def background_rows(result: SuiteResult, backgrounds: Sequence[str] | None) -> dict[str, list[dict[str, Any]]]:
    """Per background kind present (in KINDS order) the `suite_rows` of its frames that are not a single member's:
    the clean row and the suite's worst case per eps; `backgrounds` (N,) each frame's kind, None = all black."""
    kinds = background_kinds(backgrounds, result.frames)
    return {
        kind: [r for r in suite_rows(result.select(kinds == kind)) if r["attack"] in ("clean", "suite")]
        for kind in KINDS
        if (kinds == kind).any()
    }


def capacity_frames(
    model: nn.Module,
    images: np.ndarray,
    targets: np.ndarray,
    eps: Sequence[float],
    config: SuiteConfig,
    index: np.ndarray,
    device: str | torch.device = "cpu",
) -> pd.DataFrame:
    """The per-frame attacker capacity of the suite `config` on N (validation) frames, one row per frame and eps
    (eps increasing, nested: a frame's shift cannot drop as eps grows): index (the frame's label index, `index`
    (N,)), range_m (true range, m), eps, along_m and across_m (|shift| of the estimate from the clean estimate
    along and across the true line of sight, m), attitude_deg (attitude change, deg)."""
    cap = frame_capacity(run_suite(model, images, targets, eps, config, device=device))
    n, e = len(cap.target_range_m), len(cap.eps)
    return pd.DataFrame(
        {
            "index": np.tile(np.asarray(index, np.int64), e),
            "range_m": np.tile(cap.target_range_m, e),
            "eps": np.repeat(np.asarray(cap.eps, np.float64), n),
            "along_m": cap.along_m.ravel(),
            "across_m": cap.across_m.ravel(),
            "attitude_deg": cap.attitude_deg.ravel(),
        }
    )


def top_up_bins(rows: np.ndarray, range_m: np.ndarray, edges: Sequence[float], min_count: int, seed: int) -> np.ndarray:
    """The frames `rows` (indices into frames at true ranges `range_m`, m) a capacity is measured on, topped up: in
    every range bin of `edges` (m, binned as pipeline.attacks.capacity.fit_capacity bins) that holds fewer than
    `min_count` of them, a seeded draw (bin k: numpy's generator on (seed, k)) of the missing number from the bin's
    other frames, all of them when too few; sorted. A sample that meets the minimum in every bin comes back
    unchanged, so the fit's per-bin minimum stops a stage only when the frames themselves are too few."""
    rows, range_m, edges = np.asarray(rows, np.int64), np.asarray(range_m, np.float64), np.asarray(edges, np.float64)
    inside = (range_m >= edges[0]) & (range_m <= edges[-1])
    b = np.clip(np.searchsorted(edges, range_m, side="right") - 1, 0, len(edges) - 2)
    chosen = np.zeros(len(range_m), bool)
    chosen[rows] = True
    added = []
    for k in range(len(edges) - 1):
        short = int(min_count) - int((chosen & inside & (b == k)).sum())
        if short > 0:
            pool = np.flatnonzero(~chosen & inside & (b == k))
            added.append(np.random.default_rng((int(seed), k)).permutation(pool)[:short])
    return np.sort(np.concatenate([rows, *added])) if added else rows


def fit_overbound(
    frames: pd.DataFrame, edges: Sequence[float], quantile: float, margin: float, min_count: int
) -> list[Overbound]:
    """Per eps of a `capacity_frames` table (increasing) the fitted overbound F(eps, range) in the range bins
    `edges` (m): `fit_capacity` with `quantile`, `margin` and `min_count`."""
    return [
        fit_capacity(
            Shifts(
                float(e),
                g["range_m"].to_numpy(),
                g["along_m"].to_numpy(),
                g["across_m"].to_numpy(),
                g["attitude_deg"].to_numpy(),
            ),
            edges,
            quantile,
            margin,
            min_count,
        )
        for e, g in frames.groupby("eps", sort=True)
    ]
