"""Checks of params that the typed schema's sections call from their `__post_init__` (stages/config/sections.py,
evaluation.py; issue 42, item 10); each raises a ValueError naming the key, as the schema's own checks do, so
`rpod params` and every stage refuse the value with one line before any work starts:
    attack.eps, shap.eps, guidance.eps, evaluate.eps, robustness.eps, robustness.unseen_eps -> distinct
    (integrity.eps checks its repeats itself), train.range_bins -> range_bins, detect.squeeze_median -> odd
"""

from __future__ import annotations

import math
from typing import Any, Sequence


def distinct(values: Sequence[Any], key: str) -> None:
    """Refuse a list that gives a value twice (a repeated eps runs its rows twice and skews every mean over eps)."""
    seen: set[float] = set()
    for v in values:
        if float(v) in seen:
            raise ValueError(f"{key} lists {v!r} twice; give each value once")
        seen.add(float(v))


def range_bins(values: Sequence[Any], key: str = "train.range_bins") -> None:
    """Refuse range-bin edges the per-range error tables cannot use: none, not finite and positive (metres), or
    an edge given twice (an empty bin)."""
    if not values:
        raise ValueError(f"{key} is empty; give the range-bin edges in metres, e.g. [60, 45, 30, 20, 10]")
    bad = [
        v
        for v in values
        if not (isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0)
    ]
    if bad:
        raise ValueError(f"{key}: {bad[0]!r} is not a range in metres (finite, > 0)")
    distinct(values, key)


def odd(value: int, key: str) -> None:
    """Refuse an even filter size (a median filter needs a centre pixel: cv2.medianBlur takes odd sizes)."""
    if value % 2 != 1:
        raise ValueError(f"{key}={value} must be odd (a median filter has a centre pixel), e.g. {value + 1}")
