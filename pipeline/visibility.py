"""Whether a frame shows the target: the lit-pixel rule of `rpodguard.api` (a frame with no target in view gets no
pose) and the producers' refusal of a store or split that is mostly empty (`empty_problem`).

No target in view: under MIN_LIT_FRACTION of the pixels (at the model input) have a channel >= LIT_LEVEL. Space
behind the target renders black (0), so lit pixels are the target. Over the default profile's 3,900 rendered
frames (160x90, ranges 66.7..10 m) the least lit frame has 1.49% of its pixels at >= 16/255 (1st percentile
1.60%, median 4.7%); a quarter of that minimum leaves margin for a darker camera.
"""
from __future__ import annotations

from typing import Any

import numpy as np

LIT_LEVEL = 16 / 255          # pixel value in [0, 1] (brightest channel) from which a pixel counts as lit
MIN_LIT_FRACTION = 0.0037     # fraction of lit pixels below which a frame has no target in view
MAX_EMPTY_SHARE = 0.25        # a producer refuses a store or split with more of its frames than this out of view


def lit_fraction(images: np.ndarray) -> np.ndarray:
    """(N,) fraction of lit pixels (brightest channel >= LIT_LEVEL) of uint8 (N, H, W, 3) images."""
    return (np.asarray(images).max(axis=-1) >= round(LIT_LEVEL * 255)).mean(axis=(1, 2))


def out_of_view(images: Any) -> np.ndarray:
    """(N,) bool: the frames of a uint8 (N, H, W, 3) array (a zarr array is read one chunk at a time) without
    the target in view."""
    chunks = getattr(images, "chunks", None)
    n = int(images.shape[0])
    step = int(chunks[0]) if chunks else max(n, 1)
    return np.concatenate([lit_fraction(images[lo:lo + step]) < MIN_LIT_FRACTION
                           for lo in range(0, n, step)] or [np.zeros(0, bool)])


def empty_problem(empty: np.ndarray, what: str) -> str | None:
    """"K of N WHAT have no target in view ..." when more than MAX_EMPTY_SHARE of the frames flagged in
    `empty` ((N,) bool) are out of view, else None."""
    n, k = len(empty), int(np.sum(empty))
    if k <= MAX_EMPTY_SHARE * n:
        return None
    return (f"{k} of {n} {what} have no target in view (under {MIN_LIT_FRACTION:.2%} of their pixels lit; at most "
            f"{MAX_EMPTY_SHARE:.0%} may be)")


def split_problem(empty: np.ndarray, index: np.ndarray, split: np.ndarray) -> str | None:
    """An empty split, or `empty_problem` of each split ("train", "test") of a label table (`index`: its image
    rows, `split`: its split values) over the frames of its render flagged in `empty` ((N,) bool,
    `out_of_view`): the first found, or None."""
    for name in ("train", "test"):
        if not (split == name).any():
            return f"the {name} split is empty (check label.test_fraction and the number of frames)"
        problem = empty_problem(empty[index[split == name]], f"{name} frames")
        if problem:
            return (f"{problem}; the render is degenerate (check render.mesh, render.mesh_scale, or render.source's "
                    f"images)")
    return None
