"""Benign image corruptions at fixed strengths, as a real camera produces them.

A detector must not flag these: they are not attacks. Each function maps uint8 (N, H, W, 3) RGB
frames to corrupted uint8 frames of the same shape, with OpenCV, deterministically (the noise
takes a seeded generator). Strengths and units:
- noise: Gaussian sensor noise, standard deviation in [0, 1] pixel units;
- blur: Gaussian blur (defocus, motion smear), sigma in pixels;
- jpeg: JPEG compression and decoding, quality 1..100;
- brightness: multiplicative gain (exposure), 1 = unchanged;
- contrast: scale of each pixel's distance from its image's mean grey level, 1 = unchanged.
"""

from __future__ import annotations

from typing import Callable

import cv2
import numpy as np

CORRUPTIONS = ("noise", "blur", "jpeg", "brightness", "contrast")


def _check(images: np.ndarray) -> np.ndarray:
    images = np.asarray(images)
    if images.dtype != np.uint8 or images.ndim != 4 or images.shape[3] != 3:
        raise ValueError(f"expected uint8 (N, H, W, 3) frames, got {images.dtype} {images.shape}")
    return images


def noise(images: np.ndarray, std: float, rng: np.random.Generator) -> np.ndarray:
    """Additive Gaussian noise of standard deviation `std` ([0, 1] pixel units), rounded and clipped."""
    images = _check(images)
    out = images.astype(np.float32) + rng.normal(0.0, std * 255.0, size=images.shape).astype(np.float32)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)


def blur(images: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur of `sigma` pixels (kernel size chosen by OpenCV from sigma)."""
    images = _check(images)
    return np.stack([cv2.GaussianBlur(im, (0, 0), sigmaX=sigma, sigmaY=sigma) for im in images])


def jpeg(images: np.ndarray, quality: float) -> np.ndarray:
    """JPEG-encode at `quality` (1..100) and decode, per frame."""
    images = _check(images)
    out = np.empty_like(images)
    for i, im in enumerate(images):
        ok, buf = cv2.imencode(".jpg", cv2.cvtColor(im, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
        if not ok:
            raise RuntimeError("cv2.imencode failed to JPEG-encode a frame")
        out[i] = cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    return out


def brightness(images: np.ndarray, gain: float) -> np.ndarray:
    """Multiply every pixel by `gain` (exposure), rounded and saturated to 0..255."""
    images = _check(images)
    return np.stack([cv2.convertScaleAbs(im, alpha=gain, beta=0) for im in images])


def contrast(images: np.ndarray, factor: float) -> np.ndarray:
    """Scale each pixel's distance from its frame's mean grey level by `factor`, saturated to 0..255."""
    images = _check(images)
    mean = images.reshape(len(images), -1).mean(1).reshape(-1, 1, 1, 1)
    return np.clip(np.rint(mean + factor * (images.astype(np.float64) - mean)), 0, 255).astype(np.uint8)


def check_strength(name: str, strength: float) -> float:
    """Validate a corruption strength (see the module docstring for units)."""
    s = float(strength)
    ok = {
        "noise": 0 <= s <= 1,
        "blur": 0 < s <= 20,
        "jpeg": 1 <= s <= 100,
        "brightness": 0 < s <= 10,
        "contrast": 0 <= s <= 10,
    }
    if name not in ok:
        raise ValueError(f"unknown corruption {name!r}; choose one of {', '.join(CORRUPTIONS)}")
    if not np.isfinite(s) or not ok[name]:
        raise ValueError(f"corruption {name} strength {strength} is out of range")
    return s


def corrupt(name: str, strength: float, seed: int = 0) -> Callable[[np.ndarray], np.ndarray]:
    """The corruption `name` at `strength` as frames -> frames (the noise seeded with `seed`)."""
    s = check_strength(name, strength)
    if name == "noise":
        rng = np.random.default_rng(seed)
        return lambda images: noise(images, s, rng)
    return {
        "blur": lambda im: blur(im, s),
        "jpeg": lambda im: jpeg(im, s),
        "brightness": lambda im: brightness(im, s),
        "contrast": lambda im: contrast(im, s),
    }[name]
