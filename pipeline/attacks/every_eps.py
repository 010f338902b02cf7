"""A batch of test images attacked at every eps as the attack stage stores them (`rpod attack`, run on the
engine's workers: stages/engine/attack_worker.py): 8-bit adversarial images and the pose model's outputs."""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np
import torch
from torch import nn

from pipeline.attacks.gradient import AttackFn, LossFn, quantize


def attack_every_eps(
    model: nn.Module, loss_fn: LossFn, attack: AttackFn, images: np.ndarray, labels: torch.Tensor, eps: Sequence[float]
) -> dict[Any, Any]:
    """`attack` on uint8 `images` (B, H, W, 3) with their (B, 9) `labels` (m, 6-D) at each eps (L-inf, pixels in
    [0, 1]) -> {"clean": pose outputs (B, 9) on the clean images, eps: (stored uint8 images (B, H, W, 3), pose
    outputs on them, pose outputs on the float adversarial images, their stored L-inf)}; on the model's device."""
    x = torch.from_numpy(images).to(model.device).permute(0, 3, 1, 2).float() / 255  # uint8 over the bus
    y = labels.to(model.device)
    with torch.no_grad():
        out: dict[Any, Any] = {"clean": model(x).cpu().numpy()}
    for e in eps:
        x_adv = attack(model, x, y, e, loss_fn)
        stored = quantize(x_adv, x)
        with torch.no_grad():
            out[e] = (
                stored.permute(0, 2, 3, 1).cpu().numpy(),
                model(stored.float() / 255).cpu().numpy(),
                model(x_adv).cpu().numpy(),
                float((stored.float() / 255 - x).abs().max()),
            )
    return out
