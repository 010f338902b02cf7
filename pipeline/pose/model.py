"""The relative-pose CNN: a modified Darknet-19 with a 1000-feature GAP layer and two linear heads.

Architecture: Darknet-19's layer plan with a 7x7 first convolution, every max-pool replaced
by a 3x3 stride-2 convolution, and Darknet-53-style residual blocks (1x1 bottleneck to half the
channels, 3x3 back, identity skip) in place of Darknet-19's 1x1/3x3 pairs. Every convolution is
followed by BatchNorm and its own LeakyReLU(0.1) instance (inplace=False, so shap's DeepExplainer
can hook each one). A 1x1 convolution to 1000 channels and Global Average Pooling give the "GAP
layer" features; dropout (training only) and two separate linear heads give the nine outputs:
position (tx, ty, tz) in metres in the OpenCV camera frame, then the 6-D rotation (Zhou et al.).

Input: (B, 3, H, W) float RGB in [0, 1], any H, W (the GAP makes the heads size-independent).
Devices: `place(device, amp)` moves the weights; inputs on another device (CPU tensors from numpy)
are moved to the weights' device and the outputs come back on the input's device, so callers need
not know where the network runs (gradients flow through the moves). On CUDA, `amp` runs the backbone
under bf16 autocast (features back in float32) and the weights use the channels_last layout; on the
CPU the network computes exactly as without `place`.
There is no input normalisation layer: the first convolution has no bias and is followed by
BatchNorm, which absorbs any affine rescaling of the pixels.

Black-level clamp (`black_level` t > 0, the robust model; 0 = off, the standard model): the first
operation of the network is x -> max(x - t, 0), per pixel and channel, so every pixel darker than t
reaches the backbone as exactly 0 and its input gradient is exactly 0 (at x = t too). Inside the module,
it is part of every forward pass an attack differentiates (adaptive attacks included): an L-inf
perturbation of at most eps < t cannot lift a black background pixel out of the clamp. It is
1-Lipschitz (a perturbation of eps moves the clamped pixel by at most eps), unlike a hard threshold
x * [x > t], which an attacker could use to drop a pixel just above t by t + eps. How the robust
model's t is chosen from data: stages/pages/pose.py (`black_level_line`).
"""

from __future__ import annotations

import torch
from torch import nn

N_FEATURES = 1000
LEAKY_SLOPE = 0.1
# Darknet-19 stages after the stem: (channels at full width, residual blocks). Each stage starts with
# the stride-2 3x3 convolution that replaces Darknet-19's max-pool.
STAGES: tuple[tuple[int, int], ...] = ((64, 0), (128, 1), (256, 1), (512, 2), (1024, 2))
STEM_CHANNELS = 32
# A typical label used as the initial output bias (metres; identity 6-D) until set from data.
DEFAULT_POSITION = (0.0, 0.0, 35.0)
IDENTITY_6D = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0)


def conv_bn_act(c_in: int, c_out: int, k: int, stride: int = 1) -> nn.Sequential:
    """Conv (no bias) + BatchNorm + a fresh LeakyReLU; 'same' padding for odd k."""
    return nn.Sequential(
        nn.Conv2d(c_in, c_out, k, stride=stride, padding=k // 2, bias=False),
        nn.BatchNorm2d(c_out),
        nn.LeakyReLU(LEAKY_SLOPE, inplace=False),
    )


class Residual(nn.Module):
    """Darknet-53 residual block: x + conv3x3(conv1x1(x)), the 1x1 halving the channels."""

    def __init__(self, channels: int):
        super().__init__()
        self.body = nn.Sequential(
            conv_bn_act(channels, max(channels // 2, 1), 1), conv_bn_act(max(channels // 2, 1), channels, 3)
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.body(x)


def scaled(channels: int, width: float) -> int:
    """Channel count at a width multiplier, at least 4."""
    return max(4, int(round(channels * width)))


class PoseNet(nn.Module):
    """Modified Darknet-19 pose regressor; `forward(x) = forward_head(forward_features(x))`.

    width: channel multiplier of the backbone (the 1000-feature layer is fixed);
    dropout: probability on the GAP features, active in training mode only;
    black_level: the input clamp's threshold t in [0, 1) pixel units (0 = no clamp).
    """

    def __init__(self, width: float = 1.0, dropout: float = 0.2, black_level: float = 0.0):
        super().__init__()
        if not width > 0:
            raise ValueError(f"width must be positive, got {width}")
        if not 0 <= dropout < 1:
            raise ValueError(f"dropout must be in [0, 1), got {dropout}")
        if not 0 <= black_level < 1:
            raise ValueError(f"black_level must be in [0, 1) (pixel units), got {black_level}")
        self.width, self.dropout_p, self.black_level = float(width), float(dropout), float(black_level)
        self.amp = False  # bf16 autocast of the backbone (CUDA only; set by `place`)
        c = scaled(STEM_CHANNELS, width)
        layers: list[nn.Module] = [conv_bn_act(3, c, 7)]
        for channels, blocks in STAGES:
            c_out = scaled(channels, width)
            layers.append(conv_bn_act(c, c_out, 3, stride=2))
            layers += [Residual(c_out) for _ in range(blocks)]
            c = c_out
        layers.append(conv_bn_act(c, N_FEATURES, 1))
        self.backbone = nn.Sequential(*layers)
        self.gap = nn.AdaptiveAvgPool2d(1)
        self.dropout = nn.Dropout(dropout)
        self.head_pos = nn.Linear(N_FEATURES, 3)
        self.head_rot = nn.Linear(N_FEATURES, 6)
        self._init_weights()
        self.set_output_bias(DEFAULT_POSITION, IDENTITY_6D)

    def _init_weights(self) -> None:
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_normal_(m.weight, a=LEAKY_SLOPE, nonlinearity="leaky_relu")
        for head in (self.head_pos, self.head_rot):
            nn.init.normal_(head.weight, std=0.01)

    @torch.no_grad()
    def set_output_bias(
        self, position: tuple[float, ...] | torch.Tensor, rotation6d: tuple[float, ...] | torch.Tensor
    ) -> None:
        """Set the heads' biases (position in metres, 6-D rotation), e.g. to the training-label mean."""
        self.head_pos.bias.copy_(torch.as_tensor(position, dtype=torch.float32))
        self.head_rot.bias.copy_(torch.as_tensor(rotation6d, dtype=torch.float32))

    def place(self, device: str | torch.device, amp: bool = False) -> "PoseNet":
        """Move the weights to `device`; on CUDA use the channels_last layout and, with `amp`, bf16
        autocast of the backbone. On the CPU both are off (outputs as before). Returns self."""
        device = torch.device(device)
        self.to(device)
        if device.type == "cuda":
            self.to(memory_format=torch.channels_last)
        self.amp = bool(amp) and device.type == "cuda"
        return self

    @property
    def device(self) -> torch.device:
        """Where the weights are."""
        return self.head_pos.weight.device

    def clamp(self, x: torch.Tensor) -> torch.Tensor:
        """The black-level clamp max(x - black_level, 0) ((B, 3, H, W) in [0, 1]); x itself when off."""
        return torch.relu(x - self.black_level) if self.black_level > 0 else x

    def _features(self, x: torch.Tensor) -> torch.Tensor:
        """forward_features on the weights' device (x already there), through the clamp."""
        x = self.clamp(x)
        if not self.amp:
            return torch.flatten(self.gap(self.backbone(x)), 1)
        with torch.autocast("cuda", dtype=torch.bfloat16):
            f = self.backbone(x.contiguous(memory_format=torch.channels_last))
        return torch.flatten(self.gap(f.float()), 1)

    def _head(self, features: torch.Tensor) -> torch.Tensor:
        f = self.dropout(features)
        return torch.cat([self.head_pos(f), self.head_rot(f)], dim=1)

    def forward_features(self, x: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) in [0, 1] -> (B, 1000) GAP-layer features, on x's device."""
        return self._features(x.to(self.device, non_blocking=True)).to(x.device)

    def forward_head(self, features: torch.Tensor) -> torch.Tensor:
        """(B, 1000) features -> (B, 9): position (m) then 6-D rotation, on the features' device."""
        return self._head(features.to(self.device)).to(features.device)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self._head(self._features(x.to(self.device, non_blocking=True))).to(x.device)

    def forward_paired(self, x: torch.Tensor, pairs: int) -> torch.Tensor:
        """forward(x) (B, 9) where the last `pairs` images of x are other views (attacked copies) of its first
        `pairs` (TRADES-style training, pipeline/pose/adversarial.py): in training mode each pair shares one
        dropout mask, so the two outputs of a pair differ by their images only."""
        f = self._features(x.to(self.device, non_blocking=True))
        keep = self.dropout(torch.ones_like(f[: len(f) - pairs]))
        f = f * torch.cat([keep, keep[:pairs]])
        return torch.cat([self.head_pos(f), self.head_rot(f)], dim=1).to(x.device)

    def arch(self) -> dict[str, float]:
        """The constructor arguments (stored in checkpoints; black_level only when the clamp is on, so a
        standard model's checkpoint reads as before)."""
        arch = {"width": self.width, "dropout": self.dropout_p}
        return {**arch, "black_level": self.black_level} if self.black_level > 0 else arch
