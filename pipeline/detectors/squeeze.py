"""Baseline: feature squeezing on the input image (Xu et al. 2018).

The pose network sees the image and two squeezed copies: bit-depth reduction to `bits` bits per
channel and an OpenCV median filter of `median_size` pixels. The score is the largest change of
the 9 outputs over the squeezers, an L1 distance (Xu et al. use L1 between softmax vectors). As
position (metres) and the 6-D rotation (unitless) have different scales, each output is divided
by its standard deviation over clean images first (set by `fit`).
"""

from __future__ import annotations

from typing import Callable, Iterable

import cv2
import numpy as np

Predict = Callable[[np.ndarray], np.ndarray]  # uint8 images (N, H, W, 3) -> pose outputs (N, 9)


def reduce_bit_depth(images: np.ndarray, bits: int) -> np.ndarray:
    """uint8 images with each channel quantised to 2**bits levels (rounded, back on 0..255)."""
    levels = 2**bits - 1
    return (np.round(np.asarray(images, dtype=np.float32) / 255.0 * levels) / levels * 255.0).round().astype(np.uint8)


def median_filter(images: np.ndarray, size: int) -> np.ndarray:
    """cv2.medianBlur (odd `size`) on each uint8 image (N, H, W, 3)."""
    return np.stack([cv2.medianBlur(np.ascontiguousarray(im), size) for im in images])


class SqueezeDetector:
    """score(images) = max over squeezers of sum_j |f_j(x) - f_j(squeeze(x))| / scale_j."""

    def __init__(self, predict: Predict, bits: int = 4, median_size: int = 3):
        if median_size % 2 != 1:
            raise ValueError(f"median filter size must be odd (cv2.medianBlur), got {median_size}")
        self.predict, self.bits, self.median_size = predict, bits, median_size

    def fit(self, clean_images: np.ndarray) -> "SqueezeDetector":
        """Output scales from clean images (N, H, W, 3) uint8."""
        self.scale_ = np.asarray(self.predict(clean_images), dtype=np.float64).std(0).clip(min=1e-6)
        return self

    def score(self, images: np.ndarray) -> np.ndarray:
        base = np.asarray(self.predict(images), dtype=np.float64)
        changes = [
            np.abs(base - np.asarray(self.predict(sq), dtype=np.float64)) / self.scale_
            for sq in (reduce_bit_depth(images, self.bits), median_filter(images, self.median_size))
        ]
        return np.max([c.sum(1) for c in changes], axis=0)


def model_predictor(model: Callable[[object], object]) -> Predict:
    """The pose network as a `Predict`: uint8 images (N, H, W, 3) -> outputs (N, 9), without gradients."""
    import torch

    def predict(images: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return model(torch.from_numpy(np.ascontiguousarray(images)).permute(0, 3, 1, 2).float() / 255).numpy()

    return predict


def score_batches(detector: SqueezeDetector, batches: Iterable[tuple[slice, np.ndarray]], n: int) -> np.ndarray:
    """Scores of n samples given as (slice, images) batches."""
    out = np.zeros(n)
    for sl, images in batches:
        out[sl] = detector.score(images)
    return out
