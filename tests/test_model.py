"""PoseNet, PoseLoss and the augmentations: shapes, valid rotations, gradients, overfitting."""

from __future__ import annotations

import time

import numpy as np
import pytest
import torch
from torch import nn

from pipeline.geometry.rotations import quat_to_6d, sixd_to_matrix
from pipeline.pose.augment import augment
from pipeline.pose.loss import PoseLoss
from pipeline.pose.model import N_FEATURES, PoseNet
from pipeline.pose.settings import AugmentConfig


@pytest.fixture(autouse=True)
def _threads():
    torch.set_num_threads(1)
    torch.manual_seed(0)


def test_output_shapes_and_split():
    model = PoseNet(width=0.125, dropout=0.2).eval()
    x = torch.rand(2, 3, 36, 64)
    f = model.forward_features(x)
    assert f.shape == (2, N_FEATURES)
    out = model(x)
    assert out.shape == (2, 9)
    torch.testing.assert_close(model.forward_head(f), out)
    # the GAP makes the heads independent of the input size
    assert model(torch.rand(1, 3, 90, 160)).shape == (1, 9)


def test_every_activation_is_its_own_non_inplace_module():
    model = PoseNet(width=0.125)
    acts = [m for _, m in model.named_modules(remove_duplicate=False) if isinstance(m, nn.LeakyReLU)]
    convs = [m for m in model.modules() if isinstance(m, nn.Conv2d)]
    assert len(convs) == 19  # Darknet-19's convolution count (5 pools became stride-2 convs + 1000-channel 1x1)
    assert len(acts) == len({id(a) for a in acts}) == len(convs)
    assert not any(a.inplace for a in acts)
    # no max-pools (replaced by stride-2 convolutions); the stem is 7x7
    assert not any(isinstance(m, nn.MaxPool2d) for m in model.modules())
    assert model.backbone[0][0].kernel_size == (7, 7)


def test_initial_output_is_the_bias_scale_and_6d_decodes_to_rotations():
    model = PoseNet(width=0.125).eval()
    out = model(torch.rand(4, 3, 36, 64)).detach().numpy()
    assert np.all(np.abs(out[:, 2] - 35.0) < 5.0)  # starts near the default range, in metres
    R = sixd_to_matrix(out[:, 3:])
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-6)
    np.testing.assert_allclose(R.transpose(0, 2, 1) @ R, np.broadcast_to(np.eye(3), R.shape), atol=1e-6)


def test_dropout_only_in_training():
    model = PoseNet(width=0.125, dropout=0.5)
    f = torch.rand(8, N_FEATURES)
    model.eval()
    torch.testing.assert_close(model.forward_head(f), model.forward_head(f))
    model.train()
    assert not torch.allclose(model.forward_head(f), model.forward_head(f))


def test_loss_weights_receive_gradients_and_parts_are_the_norms():
    loss = PoseLoss("mean")
    pred = torch.zeros(2, 9, requires_grad=True)
    target = torch.zeros(2, 9)
    target[0, :3] = torch.tensor([3.0, 4.0, 0.0])  # position error 5 then 0: mean 2.5
    target[1, 3:] = torch.tensor([0.0, 0.0, 2.0, 0.0, 0.0, 0.0])  # rotation error 0 then 2: mean 1
    pos, rot = loss.parts(pred, target)
    assert pos.item() == pytest.approx(2.5) and rot.item() == pytest.approx(1.0)
    value = loss(pred, target)
    value.backward()
    # dL/ds_p = -2 exp(-2 s_p) pos + 2 at s_p = 0
    assert loss.s_p.grad.item() == pytest.approx(-2 * 2.5 + 2)
    assert loss.s_r.grad.item() == pytest.approx(-2 * 1.0 + 2)
    assert pred.grad is not None and pred.grad.abs().sum() > 0
    assert PoseLoss("sum").parts(pred, target)[0].item() == pytest.approx(5.0)
    with pytest.raises(ValueError):
        loss(pred[:, :6], target[:, :6])


def test_tiny_overfit():
    """Four images, fixed targets: the network memorises them within a few seconds."""
    gen = torch.Generator().manual_seed(1)
    x = torch.rand(4, 3, 36, 64, generator=gen)
    q = np.array([[1, 0, 0, 0], [0.9, 0.1, 0.3, 0.2], [0.7, -0.5, 0.2, 0.4], [0.5, 0.5, -0.5, 0.5]])
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    t = np.array([[0, 0, 20], [3, -2, 40], [-5, 4, 55], [1, 1, 12]])
    y = torch.as_tensor(np.concatenate([t, quat_to_6d(q)], 1), dtype=torch.float32)
    model = PoseNet(width=0.125, dropout=0.0)
    model.set_output_bias(y[:, :3].mean(0), y[:, 3:].mean(0))
    loss = PoseLoss()
    opt = torch.optim.Adam([*model.parameters(), *loss.parameters()], lr=1e-3)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda i: 1 - i / 300)
    start = time.perf_counter()
    initial = (model.eval()(x) - y)[:, :3].norm(dim=1).mean().item()
    model.train()
    for _ in range(300):
        opt.zero_grad()
        loss(model(x), y).backward()
        opt.step()
        sched.step()
        if time.perf_counter() - start > 40:
            break
    model.train()  # BatchNorm batch statistics: the 4 memorised images form the batch
    with torch.no_grad():
        err = model(x) - y
    pos = err[:, :3].norm(dim=1).mean().item()
    rot = err[:, 3:].norm(dim=1).mean().item()
    assert initial > 5.0
    assert pos < 0.1, (initial, pos)
    assert rot < 0.05, rot


def test_augment_changes_pixels_not_shape_and_is_seeded():
    rng_img = np.random.default_rng(0)
    img = np.zeros((36, 64, 3), np.uint8)
    img[10:26, 20:44] = rng_img.integers(100, 200, (16, 24, 3))
    cfg = AugmentConfig(p=1.0)
    a = augment(img, np.random.default_rng(5), cfg)
    b = augment(img, np.random.default_rng(5), cfg)
    c = augment(img, np.random.default_rng(6), cfg)
    assert a.shape == img.shape and a.dtype == np.uint8
    np.testing.assert_array_equal(a, b)
    assert np.abs(a.astype(int) - img).mean() > 1 and np.abs(a.astype(int) - c).mean() > 0.5
    np.testing.assert_array_equal(augment(img, np.random.default_rng(5), AugmentConfig(p=0.0)), img)
    with pytest.raises(ValueError):
        AugmentConfig(brightness=(1.3, 0.7))
    with pytest.raises(ValueError):
        augment(img.astype(np.float32), np.random.default_rng(0), cfg)


def test_place_on_the_cpu_changes_nothing_and_amp_is_cuda_only():
    """`place("cpu", amp=True)`: outputs bit-identical to the unplaced network, no autocast, and the
    outputs stay on the input's device."""
    import copy

    torch.manual_seed(0)
    a = PoseNet(0.125).eval()
    b = copy.deepcopy(a).place("cpu", amp=True)
    assert not b.amp and b.device == torch.device("cpu")
    x = torch.rand(2, 3, 27, 48)
    with torch.no_grad():
        assert torch.equal(a(x), b(x)) and torch.equal(a.forward_features(x), b.forward_features(x))
        f = b.forward_features(x)
        assert torch.equal(a.forward_head(f), b.forward_head(f)) and b(x).device == x.device
