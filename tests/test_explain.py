"""The closed-form DeepSHAP of pipeline/shap.py against the shap library, on PoseNet-shaped models."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

from pipeline.shap import Explainer, affine_head, background_mean, deep_shap, exact_shap

N_FEATURES = 1000


class TinyPoseNet(nn.Module):
    """A PoseNet-shaped stand-in: conv -> 1000 GAP features -> dropout -> position (3) + 6-D (6) heads."""

    def __init__(self, nonlinear_head: bool = False):
        super().__init__()
        self.backbone = nn.Sequential(
            nn.Conv2d(3, 8, 3, stride=2, padding=1), nn.LeakyReLU(0.1), nn.Conv2d(8, N_FEATURES, 1), nn.LeakyReLU(0.1)
        )
        nn.init.normal_(self.backbone[2].weight, std=1.0)  # GAP features of order 1, like a trained net
        self.dropout = nn.Dropout(0.2)
        self.nonlinear_head = nonlinear_head
        if nonlinear_head:
            self.hidden = nn.Sequential(nn.Linear(N_FEATURES, 32), nn.ReLU())
            self.head_pos, self.head_rot = nn.Linear(32, 3), nn.Linear(32, 6)
        else:
            self.head_pos, self.head_rot = nn.Linear(N_FEATURES, 3), nn.Linear(N_FEATURES, 6)

    def forward_features(self, x: torch.Tensor) -> torch.Tensor:
        return self.backbone(x).mean(dim=(2, 3))

    def forward_head(self, f: torch.Tensor) -> torch.Tensor:
        f = self.dropout(f)
        if self.nonlinear_head:
            f = self.hidden(f)
        return torch.cat([self.head_pos(f), self.head_rot(f)], dim=1)


def _features(model: nn.Module, n: int, seed: int) -> np.ndarray:
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        brightness = 4.0 * torch.rand(n, 1, 1, 1, generator=gen)  # so that images differ in their features
        return model.eval().forward_features(brightness * torch.rand(n, 3, 16, 24, generator=gen)).numpy()


@pytest.fixture(scope="module")
def linear_model() -> TinyPoseNet:
    torch.manual_seed(0)
    return TinyPoseNet().eval()


def test_closed_form_equals_shap_deep_explainer(linear_model):
    background, x = _features(linear_model, 40, 1), _features(linear_model, 6, 2)
    explainer = Explainer(linear_model, background, method="auto")
    assert explainer.method == "exact"
    closed = explainer(x)
    reference = deep_shap(linear_model, x, background)
    assert closed.shape == reference.shape == (6, 9, N_FEATURES)
    assert closed.dtype == np.float32
    assert np.abs(closed).max() > 1e-3  # 100x the bound below, so the bound means something
    assert np.abs(closed - reference).max() < 1e-5


def test_closed_form_is_additive(linear_model):
    background, x = _features(linear_model, 30, 3), _features(linear_model, 5, 4)
    values = Explainer(linear_model, background)(x)
    with torch.no_grad():
        out = linear_model.forward_head(torch.as_tensor(x)).numpy()
        out_bg = linear_model.forward_head(torch.as_tensor(background)).numpy().mean(0)
    np.testing.assert_allclose(values.sum(axis=2), out - out_bg, atol=1e-4, rtol=1e-4)


def test_affine_head_reads_the_stacked_head_weights(linear_model):
    head = affine_head(linear_model, N_FEATURES)
    assert head is not None
    weight = torch.cat([linear_model.head_pos.weight, linear_model.head_rot.weight]).detach().numpy()
    bias = torch.cat([linear_model.head_pos.bias, linear_model.head_rot.bias]).detach().numpy()
    np.testing.assert_allclose(head.weight, weight, atol=1e-6)
    np.testing.assert_allclose(head.bias, bias, atol=1e-6)
    # the model itself is left as it was (float32, eval) by the float64 probing
    assert linear_model.head_pos.weight.dtype == torch.float32


def test_exact_shap_formula_by_hand():
    weight = np.array([[1.0, -2.0], [0.5, 0.0]], dtype=np.float32)
    mu = np.array([1.0, 1.0], dtype=np.float32)
    x = np.array([[3.0, 0.0]], dtype=np.float32)
    phi = exact_shap(x, weight, mu).numpy()
    np.testing.assert_allclose(phi[0], [[2.0, 2.0], [1.0, 0.0]])


def test_nonlinear_head_uses_shap_and_stays_additive():
    torch.manual_seed(1)
    model = TinyPoseNet(nonlinear_head=True).eval()
    background, x = _features(model, 20, 5), _features(model, 3, 6)
    assert affine_head(model, N_FEATURES, probe=background) is None
    explainer = Explainer(model, background, method="auto")
    assert explainer.method == "deep"
    values = explainer(x)
    with torch.no_grad():
        out = model.forward_head(torch.as_tensor(x)).numpy()
        out_bg = model.forward_head(torch.as_tensor(background)).numpy().mean(0)
    np.testing.assert_allclose(values.sum(axis=2), out - out_bg, atol=1e-3, rtol=1e-3)
    with pytest.raises(ValueError, match="affine"):
        Explainer(model, background, method="exact")


def test_background_mean_and_bad_inputs():
    feats = np.arange(6, dtype=np.float32).reshape(3, 2)
    np.testing.assert_allclose(background_mean(feats), [2.0, 3.0])
    with pytest.raises(ValueError):
        background_mean(np.zeros((0, 4)))
    with pytest.raises(ValueError, match="unknown SHAP method"):
        Explainer(TinyPoseNet(), feats, method="fast")  # type: ignore[arg-type]


def test_real_posenet_head_is_read_as_affine_and_matches_shap():
    from pipeline.pose.model import PoseNet

    torch.manual_seed(2)
    model = PoseNet(width=0.125).eval()
    with torch.no_grad():  # trained heads are far larger than the 0.01-std initialisation
        model.head_pos.weight.normal_(std=0.5)
        model.head_rot.weight.normal_(std=0.5)
        gen = torch.Generator().manual_seed(0)
        background = model.forward_features(torch.rand(12, 3, 36, 64, generator=gen)).numpy()
        x = model.forward_features(torch.rand(3, 3, 36, 64, generator=gen)).numpy()
    explainer = Explainer(model, background)
    assert explainer.method == "exact"
    weight = torch.cat([model.head_pos.weight, model.head_rot.weight]).detach().numpy()
    np.testing.assert_allclose(explainer.affine.weight, weight, atol=1e-6)
    closed = explainer(x)
    assert np.abs(closed).max() > 1e-3
    assert np.abs(closed - deep_shap(model, x, background)).max() < 1e-5
