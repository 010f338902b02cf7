"""Photometric augmentations for training images, with OpenCV on uint8 (H, W, 3) RGB arrays.

Each augmentation is applied independently with probability `p`, in a fixed order: brightness,
Gaussian blur, Gaussian noise, JPEG compression (the camera chain: scene light, optics, sensor,
encoder). Geometry is never changed, so the pose labels stay valid.
"""

from __future__ import annotations

import cv2
import numpy as np

from pipeline.pose.settings import AugmentConfig


def augment(image: np.ndarray, rng: np.random.Generator, cfg: AugmentConfig) -> np.ndarray:
    """Return an augmented copy of a uint8 (H, W, 3) RGB image."""
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"expected a uint8 (H, W, 3) image, got {image.dtype} {image.shape}")
    out = image
    if rng.random() < cfg.p:
        gain = rng.uniform(*cfg.brightness)
        out = cv2.convertScaleAbs(out, alpha=gain, beta=0)
    if rng.random() < cfg.p:
        sigma = rng.uniform(*cfg.blur_sigma)
        if sigma > 0:
            out = cv2.GaussianBlur(out, (0, 0), sigmaX=sigma, sigmaY=sigma)
    if rng.random() < cfg.p:
        std = rng.uniform(*cfg.noise_std) * 255.0
        noise = rng.normal(0.0, std, size=out.shape).astype(np.float32)
        out = cv2.add(out.astype(np.float32), noise)
        out = np.clip(out, 0, 255).astype(np.uint8)
    if rng.random() < cfg.p:
        quality = int(rng.integers(cfg.jpeg_quality[0], cfg.jpeg_quality[1] + 1))
        bgr = cv2.cvtColor(out, cv2.COLOR_RGB2BGR)  # OpenCV's JPEG colour transform expects BGR
        ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, quality])
        if not ok:
            raise RuntimeError("cv2.imencode failed to JPEG-encode an image")
        out = cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    return out if out is not image else image.copy()
