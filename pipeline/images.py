"""Lab images: background segmentation, resizing to the network's input size, and the sensor domain
shift (blur, noise) applied to rendered lab recordings. Images are RGB uint8 (H, W, 3)."""

from __future__ import annotations

import cv2
import numpy as np


def segment(image: np.ndarray, mask: np.ndarray | None = None, threshold: float = 0.08) -> np.ndarray:
    """Black out the background of an RGB uint8 image (H, W, 3).

    With a mask (H, W; nonzero = target) the mask decides; otherwise pixels whose grey level is
    below `threshold` (in [0, 1]) are set to black.
    """
    if mask is None:
        grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        keep = grey >= threshold * 255.0
    else:
        if mask.shape[:2] != image.shape[:2]:
            raise ValueError(f"mask size {mask.shape[:2]} differs from image size {image.shape[:2]}")
        keep = (mask if mask.ndim == 2 else mask[..., 0]) > 0
    return np.where(keep[..., None], image, 0).astype(np.uint8)


def resize(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """Resize an image to width x height (area averaging when shrinking)."""
    if image.shape[1] == width and image.shape[0] == height:
        return image
    shrink = image.shape[1] > width
    return cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)


def domain_shift(image: np.ndarray, noise_std: float, blur_sigma: float, rng: np.random.Generator) -> np.ndarray:
    """Sensor blur (Gaussian, sigma in pixels) then Gaussian noise (std in [0, 1] units) on a uint8 image."""
    x = image.astype(np.float32) / 255.0
    if blur_sigma > 0:
        x = cv2.GaussianBlur(x, (0, 0), blur_sigma)
    if noise_std > 0:
        x = x + rng.normal(0.0, noise_std, x.shape).astype(np.float32)
    return np.clip(np.rint(x * 255.0), 0, 255).astype(np.uint8)


def shift_recording(
    rgb: np.ndarray, alpha: np.ndarray, noise_std: float, blur_sigma: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """A lab recording's rendered frames (RGB (N, H, W, 3) uint8 on black, alpha (N, H, W) in [0, 1])
    with the domain shift applied frame by frame in order (one rng stream) -> images (N, H, W, 3)
    uint8 and target masks (N, H, W) uint8 (255 = target)."""
    images = np.stack([domain_shift(x, noise_std, blur_sigma, rng) for x in rgb])
    return images, np.where(alpha > 0.5, 255, 0).astype(np.uint8)
