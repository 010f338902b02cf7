"""Whether an image is a camera frame that shows the target: the two rules of `rpodguard.api` (an image that fails
either gets no pose) and the producers' refusal of a store or split that is mostly empty (`empty_problem`).

No target in view: under MIN_LIT_FRACTION of the pixels (at the model input) have a channel >= LIT_LEVEL. Space
behind the target renders black (0), so lit pixels are the target. Over the default profile's 3,900 rendered
frames (160x90, ranges 66.7..10 m) the least lit frame has 1.49% of its pixels at >= 16/255 (1st percentile
1.60%, median 4.7%); a quarter of that minimum leaves margin for a darker camera.

Not a camera frame: neighbouring pixels do not correlate (`structure` under MIN_STRUCTURE), as in noise. A lens
image is smooth at the pixel scale: over the default profile's renders (3,900 training frames and 16,500 of the
evaluation, validation and detector sets, black sky) the least correlation of neighbouring pixels (brightest
channel, at the model input) is 0.87, and with the Earth, stars and a heavy sensor offset and read noise behind
the target (`render.background`: black_offset 0.08, noise_std 0.03) 0.61; uniform or Gaussian noise gives 0.01.

What the rules cannot tell: with the Earth or a sensor offset behind it every frame is lit, so a frame of the
Earth alone (no target) passes the lit-pixel rule and gets the network's guess of a pose; the rules keep out
black frames, specks and noise, not every image without the target.
"""

from __future__ import annotations

from typing import Any

import numpy as np

LIT_LEVEL = 16 / 255  # pixel value in [0, 1] (brightest channel) from which a pixel counts as lit
MIN_LIT_FRACTION = 0.0037  # fraction of lit pixels below which a frame has no target in view
MIN_STRUCTURE = 0.3  # correlation of neighbouring pixels below which an image is not a camera frame (noise)
MAX_EMPTY_SHARE = 0.25  # a producer refuses a store or split with more of its frames than this out of view


def lit_fraction(images: np.ndarray) -> np.ndarray:
    """(N,) fraction of lit pixels (brightest channel >= LIT_LEVEL) of uint8 (N, H, W, 3) images."""
    return (np.asarray(images).max(axis=-1) >= round(LIT_LEVEL * 255)).mean(axis=(1, 2))


def structure(images: np.ndarray) -> np.ndarray:
    """(N,) correlation of each pixel's brightest channel with its right and lower neighbours, of (N, H, W, 3)
    images (uint8, or float in [0, 1]): about 0.9 for a rendered frame, 0 for noise and for a flat image (no
    variation at all)."""
    g = np.asarray(images, dtype=np.float64).max(axis=-1)
    n = len(g)
    a = np.concatenate([g[:, :, :-1].reshape(n, -1), g[:, :-1, :].reshape(n, -1)], axis=1)
    b = np.concatenate([g[:, :, 1:].reshape(n, -1), g[:, 1:, :].reshape(n, -1)], axis=1)
    a -= a.mean(axis=1, keepdims=True)
    b -= b.mean(axis=1, keepdims=True)
    norm = np.sqrt((a * a).sum(axis=1) * (b * b).sum(axis=1))
    return np.divide((a * b).sum(axis=1), norm, out=np.zeros(n), where=norm > 0)


def out_of_view(images: Any) -> np.ndarray:
    """(N,) bool: the frames of a uint8 (N, H, W, 3) array (a zarr array is read one chunk at a time) without
    the target in view."""
    chunks = getattr(images, "chunks", None)
    n = int(images.shape[0])
    step = int(chunks[0]) if chunks else max(n, 1)
    return np.concatenate(
        [lit_fraction(images[lo : lo + step]) < MIN_LIT_FRACTION for lo in range(0, n, step)] or [np.zeros(0, bool)]
    )


def empty_problem(empty: np.ndarray, what: str) -> str | None:
    """ "K of N WHAT have no target in view ..." when more than MAX_EMPTY_SHARE of the frames flagged in
    `empty` ((N,) bool) are out of view, else None."""
    n, k = len(empty), int(np.sum(empty))
    if k <= MAX_EMPTY_SHARE * n:
        return None
    return (
        f"{k} of {n} {what} have no target in view (under {MIN_LIT_FRACTION:.2%} of their pixels lit; at most "
        f"{MAX_EMPTY_SHARE:.0%} may be)"
    )


def split_problem(empty: np.ndarray, index: np.ndarray, split: np.ndarray) -> str | None:
    """An empty split, or `empty_problem` of each split ("train", "test") of a label table (`index`: its image
    rows, `split`: its split values) over the frames of its render flagged in `empty` ((N,) bool,
    `out_of_view`): the first found, or None."""
    for name in ("train", "test"):
        if not (split == name).any():
            return f"the {name} split is empty (check label.test_fraction and the number of frames)"
        problem = empty_problem(empty[index[split == name]], f"{name} frames")
        if problem:
            return (
                f"{problem}; the render is degenerate (check render.mesh, render.mesh_scale, or render.source's images)"
            )
    return None
