import numpy as np
import pytest
import torch
from torch import nn

from pipeline.defense.chain import OnboardChain
from pipeline.detectors.lstm import LSTMConfig, LSTMDetector
from pipeline.pose.model import PoseNet
from pipeline.shap import Explainer


@pytest.fixture(scope="module")
def parts():
    torch.manual_seed(0)
    model = PoseNet(width=0.125).eval()
    x = torch.rand(4, 3, 36, 64)
    with torch.no_grad():
        bg = model.forward_features(torch.rand(6, 3, 36, 64)).numpy()
    det = LSTMDetector(LSTMConfig(hidden=8, dense=[4])).eval()
    det.set_normalisation(np.random.default_rng(0).normal(size=(5, 9, 1000)).astype(np.float32) * 0.01)
    return model, bg, det, x


def test_chain_matches_its_parts(parts):
    model, bg, det, x = parts
    chain = OnboardChain.from_model(model, bg.mean(0), det, threshold=0.5)
    out = chain(x)
    with torch.no_grad():
        torch.testing.assert_close(out.pose, model(x), rtol=1e-5, atol=1e-5)
        feats = model.forward_features(x).numpy()
    expected_shap = Explainer(model, bg, method="exact")(feats)
    np.testing.assert_allclose(out.shap.numpy(), expected_shap, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(out.prob.numpy(), det.predict_proba(expected_shap), rtol=1e-4, atol=1e-6)
    assert torch.equal(out.flag, out.prob >= 0.5)
    # SHAP additivity: each output's values sum to the output minus its background mean
    with torch.no_grad():
        bg_out = model.forward_head(torch.as_tensor(bg)).mean(0)
    torch.testing.assert_close(out.shap.sum(-1), out.pose - bg_out, rtol=1e-3, atol=1e-3)


def test_chain_is_stateless_per_frame(parts):
    model, bg, det, x = parts
    chain = OnboardChain.from_model(model, bg.mean(0), det, threshold=0.3)
    batch = chain(x)
    for i in range(len(x)):
        one = chain(x[i])
        torch.testing.assert_close(one.prob, batch.prob[i : i + 1], rtol=1e-4, atol=1e-6)
        torch.testing.assert_close(one.pose, batch.pose[i : i + 1], rtol=1e-4, atol=1e-5)


class _ReluHead(nn.Module):
    def __init__(self):
        super().__init__()
        self.lin = nn.Linear(1000, 9)

    def forward_features(self, x):
        return x.mean(dim=(2, 3)).repeat(1, 334)[:, :1000]

    def forward_head(self, f):
        return torch.relu(self.lin(f))


def test_chain_refuses_a_non_affine_head(parts):
    _, bg, det, _ = parts
    with pytest.raises(ValueError, match="affine"):
        OnboardChain.from_model(_ReluHead(), bg.mean(0), det)
    with pytest.raises(ValueError, match="do not fit"):
        OnboardChain(_ReluHead(), np.zeros((9, 1000)), np.zeros(999), det)


def test_run_sequence_attacks_only_scheduled_frames_with_their_own_labels(parts):
    from pipeline.defense.chain import run_sequence

    model, bg, det, _ = parts
    chain = OnboardChain.from_model(model, bg.mean(0), det)
    rng = np.random.default_rng(1)
    images = rng.integers(0, 256, (7, 36, 64, 3), dtype=np.uint8)
    targets = np.arange(7 * 9, dtype=np.float32).reshape(7, 9)
    attacked = np.array([0, 1, 1, 0, 0, 1, 0], bool)
    seen = []

    def attack(x, y):
        seen.append(y[:, 0].numpy().copy())
        return torch.zeros_like(x)

    res = run_sequence(chain, images, targets, attacked, attack, batch_size=3)
    assert np.concatenate(seen).tolist() == targets[attacked, 0].tolist()
    clean = chain(torch.from_numpy(images).permute(0, 3, 1, 2).float() / 255)
    zero = chain(torch.zeros(1, 3, 36, 64))
    np.testing.assert_allclose(res.pose[~attacked], clean.pose.numpy()[~attacked], rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(res.pose[attacked], np.repeat(zero.pose.numpy(), 3, 0), rtol=1e-4, atol=1e-4)
    with pytest.raises(ValueError, match="no attack"):
        run_sequence(chain, images, targets, attacked, None)


def test_fast_path_equals_the_plain_chain_at_real_sizes():
    """1000 features, 100 LSTM units, 9 rows, random weights: the folded path (`FoldedShapLSTM`) gives the
    plain chain's pose and SHAP values exactly and its probabilities within 1e-4, batched or not."""
    torch.manual_seed(3)
    model = PoseNet(width=0.125).eval()
    x = torch.rand(6, 3, 36, 64)
    with torch.no_grad():
        bg = model.forward_features(torch.rand(6, 3, 36, 64)).numpy()
    det = LSTMDetector(LSTMConfig()).eval()
    plain = OnboardChain.from_model(model, bg.mean(0), det, fast=False)
    det.set_normalisation(plain(x).shap.numpy())
    with torch.no_grad():  # sharper than the initialisation, so that the probabilities spread
        det.lstm.input_proj.weight.mul_(5.0)
        det.classifier[0].weight.mul_(5.0)
    fast = OnboardChain.from_model(model, bg.mean(0), det, threshold=0.5)
    assert fast._fast is not None and plain._fast is None
    a, b = fast(x), plain(x)
    assert torch.equal(a.pose, b.pose) and torch.equal(a.shap, b.shap)
    assert b.prob.std() > 0.02
    np.testing.assert_allclose(a.prob.numpy(), b.prob.numpy(), rtol=0, atol=1e-4)
    assert torch.equal(a.flag, a.prob >= 0.5)
    for i in (0, 5):
        np.testing.assert_allclose(fast(x[i]).prob.numpy(), b.prob.numpy()[i : i + 1], rtol=0, atol=1e-4)
