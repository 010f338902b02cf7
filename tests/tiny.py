"""A pose network in miniature for the attack and robustness tests: Conv -> BN -> LeakyReLU -> GAP (16 features) ->
an affine 9-output head, with PoseNet's two halves (`forward_features`, `forward_head`)."""

from __future__ import annotations

import torch
from torch import nn

FEATURES = 16


class TinyPose(nn.Module):
    def __init__(self) -> None:
        super().__init__()
        self.features = nn.Sequential(
            nn.Conv2d(3, 8, 3, padding=1),
            nn.BatchNorm2d(8),
            nn.LeakyReLU(0.1),
            nn.Conv2d(8, FEATURES, 3, stride=2, padding=1),
            nn.LeakyReLU(0.1),
            nn.AdaptiveAvgPool2d(1),
            nn.Flatten(),
        )
        self.head = nn.Linear(FEATURES, 9)

    def forward_features(self, x: torch.Tensor) -> torch.Tensor:
        return self.features(x)

    def forward_head(self, f: torch.Tensor) -> torch.Tensor:
        return self.head(f)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.forward_head(self.forward_features(x))


# params overrides (`rpod params smoke -S ...`) for a render of a few tiny frames (32x18, 2 per sequence)
RENDER = [
    "render.width=32",
    "render.height=18",
    "render.frames_per_sequence=2",
    "render.samples=2",
    "render.chunk=4",
    "render.previews=1",
]
