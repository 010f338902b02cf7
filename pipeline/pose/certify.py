"""A certified per-frame bound on how far an L-inf attack of budget eps can move the pose network's outputs:
interval bound propagation (IBP, Gowal et al. 2018) through pipeline/pose/model.py's PoseNet in eval mode.

Each layer maps a box of inputs (centre c, radius r >= 0, elementwise) to a box that contains every output:
the black-level clamp max(x - t, 0) and LeakyReLU are monotone (the box's ends map to the ends); a
convolution or linear map W gives centre W c (+ bias) and radius |W| r; BatchNorm in eval is a per-channel
affine map a x + b (radius |a| r); a residual add sums the two boxes; global average pooling averages
them. The input box is [x - eps, x + eps] clipped to the image range [0, 1]. Sound (every attacked output
lies in the box, up to float64 rounding) and usually loose: the radius grows with every layer's |W|,
and the residual adds ignore that both terms come from the same input. The integrity bound uses the
empirical capacity (pipeline/attacks/capacity.py); this says how far it sits below a certificate.
(auto-LiRPA's CROWN would be tighter; its last release predates the torch we pin.)
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from pipeline.pose.model import PoseNet, Residual

Box = tuple[torch.Tensor, torch.Tensor]  # (centre, radius), float64


def _through(module: nn.Module, box: Box) -> Box:
    """The box of `module`'s outputs over the input box (float64)."""
    c, r = box
    if isinstance(module, nn.Sequential):
        for m in module:
            c, r = _through(m, (c, r))
        return c, r
    if isinstance(module, Residual):
        cb, rb = _through(module.body, (c, r))
        return c + cb, r + rb
    if isinstance(module, nn.Conv2d):
        w = module.weight.double()
        bias = None if module.bias is None else module.bias.double()
        kw = {"stride": module.stride, "padding": module.padding, "dilation": module.dilation, "groups": module.groups}
        return F.conv2d(c, w, bias, **kw), F.conv2d(r, w.abs(), None, **kw)
    if isinstance(module, nn.BatchNorm2d):
        a = module.weight.double() / torch.sqrt(module.running_var.double() + module.eps)
        b = module.bias.double() - module.running_mean.double() * a
        return c * a[:, None, None] + b[:, None, None], r * a.abs()[:, None, None]
    if isinstance(module, nn.LeakyReLU):
        lo, hi = F.leaky_relu(c - r, module.negative_slope), F.leaky_relu(c + r, module.negative_slope)
        return (lo + hi) / 2, (hi - lo) / 2
    raise ValueError(f"interval bounds: no rule for {type(module).__name__}")


@torch.no_grad()
def output_bounds(model: PoseNet, x: torch.Tensor, eps: float) -> tuple[torch.Tensor, torch.Tensor]:
    """(lower, upper) (B, 9) float64 on the CPU: every output of `model` (in eval mode) on an image within eps (L-inf,
    pixels in [0, 1]) of x (B, 3, H, W), clipped to [0, 1], lies between them (position m, then 6-D)."""
    if model.training:
        raise ValueError("interval bounds need the model in eval mode (BatchNorm's running statistics)")
    if not eps >= 0:
        raise ValueError(f"interval bounds: eps must be >= 0, got {eps}")
    x = x.detach().to(model.device).double()
    lo, hi = (x - eps).clamp(0, 1), (x + eps).clamp(0, 1)
    if model.black_level > 0:  # the clamp is monotone
        lo, hi = torch.relu(lo - model.black_level), torch.relu(hi - model.black_level)
    c, r = _through(model.backbone, ((lo + hi) / 2, (hi - lo) / 2))
    c, r = c.mean(dim=(2, 3)), r.mean(dim=(2, 3))
    W = torch.cat([model.head_pos.weight, model.head_rot.weight]).double()
    b = torch.cat([model.head_pos.bias, model.head_rot.bias]).double()
    c, r = c @ W.T + b, r @ W.abs().T
    return (c - r).cpu(), (c + r).cpu()


def certified_shift(model: PoseNet, x: torch.Tensor, eps: float) -> torch.Tensor:
    """(B, 3) per camera axis the largest shift (m) of the estimated position that an attack within eps can
    cause from the clean estimate on x (B, 3, H, W): max(upper - clean, clean - lower)."""
    lower, upper = output_bounds(model, x, eps)
    with torch.no_grad():
        clean = model(x).double().cpu()[:, :3]
    return torch.maximum(upper[:, :3] - clean, clean - lower[:, :3])
