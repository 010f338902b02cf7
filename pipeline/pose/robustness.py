"""Robustness helpers of the pose models: a seeded sample of rows (the test frames the strongest-attack suite
attacks, stages/engine/suite.py) and how the black-level clamp's threshold meets the data.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def sample_rows(n_total: int, n: int | None, seed: int) -> np.ndarray:
    """Sorted indices of a seeded sample of min(n, n_total) rows (all rows when n is None)."""
    if n is None or n >= n_total:
        return np.arange(n_total)
    return np.sort(np.random.default_rng(seed).permutation(n_total)[:n])


def black_level_stats(
    images: Any,
    threshold: float,
    noise_std: float,
    blur_sigma: float,
    seed: int,
    n: int = 200,
    margin: int = 3,
    backgrounds: np.ndarray | None = None,
) -> dict[str, float]:
    """How a clamp threshold t (pixel units in [0, 1]) meets the data, on n seeded images of `images` (uint8
    (N, H, W, 3) renders; anything indexable by an int) rendered on a black background: with `backgrounds` (each
    row's kind: black, space, earth) the black rows only, since over the Earth or stars with a sensor offset no
    pixel is exactly black and every background value would count as the target's:
    - render_black: share of the pixels whose three channels are exactly 0 (the background);
    - target_erased: share of the other pixels' channel values below t (what the clamp takes from the target);
    - lab_black_999: the 99.9th percentile of the channel values of the background (pixels at least
      `margin` px from any non-black pixel) under the lab domain shift (blur, then Gaussian noise,
      pipeline.images.domain_shift): the lab black level;
    - lab_passed: the share of those background values at or above t (background the clamp lets through)."""
    import cv2

    from pipeline.images import domain_shift

    rng = np.random.default_rng(seed)
    kernel = np.ones((2 * margin + 1, 2 * margin + 1), np.uint8)
    black, lit, lab = [], [], []
    rows = np.arange(len(images)) if backgrounds is None else np.flatnonzero(np.asarray(backgrounds) == "black")
    if not len(rows):
        raise ValueError(
            f"the clamp's statistics sample black-background images and none of the {len(images)} given has one "
            "(every frame rendered over the Earth or stars: a background share of 1)"
        )
    for i in rows[sample_rows(len(rows), n, seed)]:
        image = np.asarray(images[int(i)])
        dark = image.max(axis=-1) == 0
        far = cv2.erode(dark.astype(np.uint8), kernel) > 0
        black.append(dark.ravel())
        lit.append(image[~dark].ravel().astype(np.float32) / 255.0)
        lab.append(domain_shift(image, noise_std, blur_sigma, rng)[far].ravel().astype(np.float32) / 255.0)
    lit_all, lab_all = np.concatenate(lit), np.concatenate(lab)
    return {
        "threshold": float(threshold),
        "render_black": float(np.concatenate(black).mean()),
        "target_erased": float((lit_all < threshold).mean()) if lit_all.size else 0.0,
        "lab_black_999": float(np.quantile(lab_all, 0.999)) if lab_all.size else 0.0,
        "lab_passed": float((lab_all >= threshold).mean()) if lab_all.size else 0.0,
        "images": len(black),
    }
