"""Interval bound propagation through the pose network (pipeline/pose/certify.py): sound on sampled attacks."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pipeline.pose.certify import certified_shift, output_bounds
from pipeline.pose.model import PoseNet


def small_model(black_level: float) -> PoseNet:
    """A narrow PoseNet in eval mode with BatchNorm statistics that are not the identity."""
    torch.manual_seed(0)
    model = PoseNet(width=0.125, black_level=black_level)
    for m in model.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-0.2, 0.2)
            m.running_var.uniform_(0.5, 2.0)
            m.weight.data.uniform_(0.5, 1.5)
            m.bias.data.uniform_(-0.1, 0.1)
    return model.eval()


@pytest.mark.parametrize("black_level", [0.0, 0.07])
def test_every_sampled_attack_lies_within_the_bounds(black_level: float) -> None:
    model = small_model(black_level)
    g = torch.Generator().manual_seed(1)
    x = torch.rand(2, 3, 32, 48, generator=g) * 0.5
    x[:, :, :10] = 0.0  # a black background band
    eps = 0.01
    lower, upper = output_bounds(model, x, eps)
    assert (upper >= lower).all()
    with torch.no_grad():
        for _ in range(20):
            sign = torch.randint(0, 2, x.shape, generator=g) * 2.0 - 1.0
            scale = torch.rand(x.shape, generator=g).pow(0.1)  # mostly at the box's corners
            out = model((x + eps * sign * scale).clamp(0, 1)).double()
            assert (out >= lower - 1e-4).all() and (out <= upper + 1e-4).all()
    shift = certified_shift(model, x, eps)
    assert shift.shape == (2, 3) and (shift >= 0).all()


def test_no_budget_gives_the_clean_output_and_the_clamp_keeps_black_pixels_exact() -> None:
    model = small_model(0.07)
    x = torch.rand(1, 3, 32, 48, generator=torch.Generator().manual_seed(2))
    lower, upper = output_bounds(model, x, 0.0)
    with torch.no_grad():
        clean = model(x).double()
    np.testing.assert_allclose(lower.numpy(), clean.numpy(), atol=1e-4)
    np.testing.assert_allclose(upper.numpy(), clean.numpy(), atol=1e-4)
    black = torch.zeros(1, 3, 32, 48)
    lower, upper = output_bounds(model, black, 0.05)  # eps < t: the clamp holds every pixel at 0
    np.testing.assert_allclose(lower.numpy(), upper.numpy(), atol=1e-9)
    with pytest.raises(ValueError, match="eval mode"):
        output_bounds(model.train(), x, 0.01)
