"""The robust model's ablation rows (issue 37): what the black-level clamp and adversarial training each buy,
under the strongest-attack suite, on black and on Earth backgrounds.

`ablation_rows` runs one suite (pipeline/attacks/strongest.py: e.g. LEAN) on every model of an ablation over the
same frames (for instance the clamp only: the standard network behind the clamp, fine-tuned without attacks;
adversarial training only: the robust recipe without the clamp; both: the robust model), then splits each run by
the frames' background (the labels' `background` column: black, space, earth; or any grouping). Each row is one
model, background and eps: the clean errors (eps 0) or the suite's worst case nested in eps, as means over the
frames with 95% intervals: position (m), attitude (deg), range and lateral error (m).
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np
from torch import nn

from pipeline.attacks.strongest import SuiteConfig, run_suite, suite_rows

ROW_KEYS = ("n", "pos_m", "pos_ci", "att_deg", "att_ci", "range_m", "range_ci", "lateral_m", "lateral_ci")


def ablation_rows(
    models: Mapping[str, nn.Module],
    images: np.ndarray,
    targets: np.ndarray,
    eps: Sequence[float],
    config: SuiteConfig,
    backgrounds: np.ndarray | None = None,
    device: str = "cpu",
) -> list[dict[str, Any]]:
    """Rows (module doc) of each model of `models` (name -> pose network) on clean uint8 images (N, H, W, 3) with
    true poses `targets` (N, 9: camera-frame position in m, 6-D rotation), under `config` at the increasing
    budgets `eps` (L-inf, pixel units): per model, per background (the distinct values of `backgrounds` (N,) in
    order of first appearance; None = every frame "black"), the clean row then one per eps; keys model,
    background, eps, n, pos_m/pos_ci, att_deg/att_ci, range_m/range_ci, lateral_m/lateral_ci."""
    kinds = np.full(len(images), "black") if backgrounds is None else np.asarray(backgrounds).astype(str)
    if kinds.shape != (len(images),):
        raise ValueError(f"backgrounds must name one background per frame ({len(images)}), got {kinds.shape}")
    groups = list(dict.fromkeys(kinds.tolist()))
    rows = []
    for name, model in models.items():
        result = run_suite(model, images, targets, eps, config, device=device)
        for group in groups:
            for row in suite_rows(result.select(kinds == group)):
                if row["attack"] in ("clean", "suite"):
                    rows.append(
                        {"model": name, "background": group, "eps": row["eps"], **{k: row[k] for k in ROW_KEYS}}
                    )
    return rows
