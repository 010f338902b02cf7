"""Attacked pose errors: the position and attitude error of a pose model under FGSM and PGD-n at a list of
L-inf budgets, on clean 8-bit images, every adversarial image stored as 8 bits (`gradient.quantize`) and
read back before it is scored, as a camera would deliver it.

Both attacks ascend the position term ||p - p_gt|| of the model's own loss (the harm is a position error),
PGD-n from a seeded random start with steps of 2.5 eps / n. Errors: position in metres (camera frame),
attitude in degrees; each mean comes with a 95% interval (normal approximation, mean +- 1.96 s / sqrt(n)).
"""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np
import torch
from torch import nn

from pipeline.attacks.gradient import attack_loss, fgsm, get_attack, stored_attack
from pipeline.pose.metrics import pose_errors
from pipeline.stats import mean_interval


def sample_rows(n_total: int, n: int | None, seed: int) -> np.ndarray:
    """Sorted indices of a seeded sample of min(n, n_total) rows (all rows when n is None)."""
    if n is None or n >= n_total:
        return np.arange(n_total)
    return np.sort(np.random.default_rng(seed).permutation(n_total)[:n])


def attacked_errors(model: nn.Module, apply: Any, images: np.ndarray, targets: np.ndarray,
                    batch_size: int = 64, device: str | torch.device = "cpu") -> tuple[np.ndarray, np.ndarray]:
    """Position (m) and attitude (deg) errors, per image, of `model` on uint8 (N, H, W, 3) `images` after
    `apply(x, y) -> x'` (a `stored_attack`, or None for the clean images); `targets` (N, 9)."""
    preds = []
    for lo in range(0, len(images), batch_size):
        x = torch.tensor(np.asarray(images[lo:lo + batch_size])).permute(0, 3, 1, 2).float() / 255.0
        y = torch.tensor(np.asarray(targets[lo:lo + batch_size], np.float32))
        x, y = x.to(device), y.to(device)
        if apply is not None:
            x = apply(x, y)
        with torch.no_grad():
            preds.append(model(x).float().cpu())
    return pose_errors(torch.cat(preds).numpy(), np.asarray(targets))


def attack_table(model: nn.Module, pose_loss: nn.Module, images: np.ndarray, targets: np.ndarray,
                 eps: Sequence[float], pgd_steps: int = 50, seed: int = 0, batch_size: int = 64,
                 device: str | torch.device = "cpu") -> list[dict[str, Any]]:
    """Rows {attack, eps, n, pos_m, pos_ci, att_deg, att_ci} for the clean images (eps 0) and FGSM and
    PGD-`pgd_steps` at every budget in `eps` (model in eval mode; `pose_loss` its PoseLoss)."""
    was = model.training
    model.eval()
    loss_fn = attack_loss("position", pose_loss)
    runs: list[tuple[str, float, Any]] = [("clean", 0.0, None)]
    for i, e in enumerate(eps):
        pgd = get_attack("pgd", steps=pgd_steps, generator=torch.Generator().manual_seed(seed + i))
        runs += [("fgsm", float(e), stored_attack(model, loss_fn, e, fgsm)),
                 (f"pgd-{pgd_steps}", float(e), stored_attack(model, loss_fn, e, pgd))]
    rows = []
    for name, e, apply in runs:
        pos, att = attacked_errors(model, apply, images, targets, batch_size, device)
        p, a = mean_interval(pos), mean_interval(att)
        rows.append({"attack": name, "eps": e, "n": int(len(pos)), "pos_m": p[0], "pos_ci": [p[1], p[2]],
                     "att_deg": a[0], "att_ci": [a[1], a[2]]})
    model.train(was)
    return rows


def black_level_stats(images: Any, threshold: float, noise_std: float, blur_sigma: float, seed: int,
                      n: int = 200, margin: int = 3) -> dict[str, float]:
    """How a clamp threshold t (pixel units in [0, 1]) meets the data, on n seeded images of `images` (uint8
    (N, H, W, 3) renders on a black background; anything indexable by an int):
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
    for i in sample_rows(len(images), n, seed):
        image = np.asarray(images[int(i)])
        dark = image.max(axis=-1) == 0
        far = cv2.erode(dark.astype(np.uint8), kernel) > 0
        black.append(dark.ravel())
        lit.append(image[~dark].ravel().astype(np.float32) / 255.0)
        lab.append(domain_shift(image, noise_std, blur_sigma, rng)[far].ravel().astype(np.float32) / 255.0)
    lit_all, lab_all = np.concatenate(lit), np.concatenate(lab)
    return {"threshold": float(threshold), "render_black": float(np.concatenate(black).mean()),
            "target_erased": float((lit_all < threshold).mean()) if lit_all.size else 0.0,
            "lab_black_999": float(np.quantile(lab_all, 0.999)) if lab_all.size else 0.0,
            "lab_passed": float((lab_all >= threshold).mean()) if lab_all.size else 0.0, "images": len(black)}
