"""The attack detectors in pipeline/detectors/ on small synthetic data with a known answer."""

from __future__ import annotations

import io

import numpy as np
import pytest
import torch

from pipeline.detectors.lid import LIDDetector, lid_mle
from pipeline.detectors.lstm import LSTMConfig, LSTMDetector, ReLULSTMCell, from_checkpoint, to_checkpoint, train_lstm
from pipeline.detectors.mahalanobis import MahalanobisDetector
from pipeline.detectors.metrics import choose_threshold, detection_metrics, metrics_by_eps
from pipeline.detectors.mlp import MLPDetector
from pipeline.detectors.squeeze import SqueezeDetector, median_filter, reduce_bit_depth

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


def _shap_like(n: int, n_features: int, seed: int, shift: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Half clean, half "attacked" SHAP-shaped samples (n, 9, n_features): attacks shift 10 features."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, 9, n_features)).astype(np.float32)
    y = (np.arange(n) % 2).astype(np.int64)
    x[y == 1, :, :10] += shift
    return x, y


def test_relu_lstm_cell_matches_the_equations():
    torch.manual_seed(0)
    cell = ReLULSTMCell(5, 3)
    x = torch.randn(2, 4, 5)
    h = torch.zeros(2, 3)
    c = torch.zeros(2, 3)
    for t in range(4):
        z = cell.input_proj(x[:, t]) + cell.hidden_proj(h)
        i, f, g, o = z[:, :3], z[:, 3:6], z[:, 6:9], z[:, 9:]
        c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.relu(g)
        h = torch.sigmoid(o) * torch.relu(c)
    torch.testing.assert_close(cell(x), h)
    assert float(cell.input_proj.bias[3:6].min()) == 1.0  # forget-gate bias


def test_lstm_detector_learns_and_round_trips_a_checkpoint():
    x, y = _shap_like(400, 40, seed=0)
    xv, yv = _shap_like(100, 40, seed=1)
    xt, yt = _shap_like(200, 40, seed=2)
    config = LSTMConfig(n_features=40, hidden=16, dense=[8])
    result = train_lstm(x, y, xv, yv, config, epochs=30, patience=5, batch_size=32, seed=0)
    model = result.model
    assert 0.0 < float(model.threshold) < 1.0
    assert 1 <= result.best_epoch <= len(result.history)
    acc = (model.predict(xt) == yt).mean()
    assert acc > 0.95
    buf = io.BytesIO()
    torch.save(to_checkpoint(model, {"model_hash": "abc"}), buf)
    buf.seek(0)
    ckpt = torch.load(buf, weights_only=True)
    assert ckpt["model_hash"] == "abc"
    loaded = from_checkpoint(ckpt)
    np.testing.assert_allclose(loaded.predict_proba(xt), model.predict_proba(xt), rtol=1e-6, atol=1e-7)
    assert float(loaded.threshold) == pytest.approx(float(model.threshold))


def test_lstm_early_stopping_stops_on_noise():
    rng = np.random.default_rng(3)
    x = rng.normal(size=(64, 9, 12)).astype(np.float32)
    y = rng.integers(0, 2, 64)
    xv = rng.normal(size=(32, 9, 12)).astype(np.float32)
    yv = rng.integers(0, 2, 32)
    result = train_lstm(
        x,
        y,
        xv,
        yv,
        LSTMConfig(n_features=12, hidden=8, dense=[4]),
        epochs=200,
        patience=3,
        batch_size=16,
        lr=1.0,
        seed=0,
    )
    assert len(result.history) < 200
    assert len(result.history) - result.best_epoch == 3


def test_lstm_takes_the_paper_shape():
    model = LSTMDetector(LSTMConfig())
    out = model(torch.randn(5, 9, 1000))
    assert out.shape == (5,)
    assert model.lstm.hidden_size == 100


def test_threshold_and_metrics_by_hand():
    scores = np.array([0.1, 0.2, 0.3, 0.6, 0.7, 0.9])
    labels = np.array([0, 0, 0, 1, 1, 1])
    thr = choose_threshold(scores, labels)
    assert 0.3 < thr < 0.6
    m = detection_metrics(labels, scores, 0.65)  # misses the 0.6 attack
    assert m["accuracy"] == pytest.approx(5 / 6)
    assert m["recall"] == pytest.approx(2 / 3)
    assert m["precision"] == 1.0 and m["fpr"] == 0.0
    assert m["roc_auc"] == 1.0 and m["tpr_at_1pct_fpr"] == 1.0
    eps = np.array([0, 0, 0, 0.5, 0.05, 0.05])
    by_eps = metrics_by_eps(labels, scores, eps, 0.65)
    assert set(by_eps) == {"all", "0.5", "0.05"}
    assert by_eps["0.5"]["recall"] == 0.0 and by_eps["0.05"]["recall"] == 1.0  # the 0.6 attack is at eps 0.5
    assert by_eps["0.05"]["n"] == 5
    single = detection_metrics(np.zeros(3), np.array([0.1, 0.2, 0.3]), 0.5)
    assert np.isnan(single["roc_auc"]) and single["fpr"] == 0.0


def test_mlp_separates_shifted_shap():
    x, y = _shap_like(300, 30, seed=4)
    xt, yt = _shap_like(100, 30, seed=5)
    scores = MLPDetector(hidden=(32,), seed=0).fit(x, y).score(xt)
    assert detection_metrics(yt, scores, 0.5)["roc_auc"] > 0.95


def test_mahalanobis_flags_off_distribution_features():
    rng = np.random.default_rng(6)
    means = rng.normal(scale=5.0, size=(3, 20))
    groups = rng.integers(0, 3, 600)
    clean = means[groups] + rng.normal(size=(600, 20))
    det = MahalanobisDetector().fit(clean[:400], groups[:400])
    test_clean = clean[400:]
    test_adv = means[groups[400:]] + rng.normal(scale=2.0, size=(200, 20))  # same centres, wider spread
    scores = det.score(np.concatenate([test_clean, test_adv]))
    labels = np.r_[np.zeros(200), np.ones(200)]
    assert detection_metrics(labels, scores, 0.0)["roc_auc"] > 0.9
    # a sample at a group mean is at distance 0 from it
    assert det.score(det.means_[:1])[0] == pytest.approx(0.0, abs=1e-9)


def test_lid_estimate_and_detector():
    rng = np.random.default_rng(7)
    # clean data on a 2-D plane inside 30-D space has LID about 2; isotropic noise raises it
    basis = rng.normal(size=(2, 30))
    plane = rng.normal(size=(1000, 2)) @ basis
    lid = lid_mle(plane[:200], plane, k=20, skip_self=True)
    assert 1.0 < np.median(lid) < 3.5
    clean = rng.normal(size=(400, 2)) @ basis
    adv = rng.normal(size=(400, 2)) @ basis + rng.normal(scale=1.0, size=(400, 30))
    feats = np.concatenate([clean[:300], adv[:300]])
    labels = np.r_[np.zeros(300), np.ones(300)]
    det = LIDDetector(k=10, batch_size=100, seed=0).fit(feats, labels)
    scores = det.score(np.concatenate([clean[300:], adv[300:]]))
    assert detection_metrics(np.r_[np.zeros(100), np.ones(100)], scores, 0.5)["roc_auc"] > 0.9


def test_squeezers():
    img = np.array([[[0, 17, 255]]], dtype=np.uint8)[None]  # (1, 1, 1, 3)
    np.testing.assert_array_equal(reduce_bit_depth(img, 1)[0, 0, 0], [0, 0, 255])
    np.testing.assert_array_equal(reduce_bit_depth(img, 8), img)
    speck = np.zeros((1, 5, 5, 3), dtype=np.uint8)
    speck[0, 2, 2] = 255
    assert median_filter(speck, 3).max() == 0  # an isolated pixel is removed
    with pytest.raises(ValueError, match="odd"):
        SqueezeDetector(lambda x: x, median_size=2)


def test_squeeze_detector_flags_high_frequency_perturbations():
    rng = np.random.default_rng(8)
    # smooth images (vertical gradients of random brightness) and the same with +-40 sign noise
    base = (
        np.linspace(0, 1, 16)[None, :, None, None] * rng.uniform(60, 200, (40, 1, 1, 1)) * np.ones((1, 1, 16, 3))
    ).astype(np.uint8)
    noise = rng.choice([-40, 40], size=base.shape)
    adv = np.clip(base.astype(int) + noise, 0, 255).astype(np.uint8)

    def predict(images: np.ndarray) -> np.ndarray:  # a "pose net" that reacts to local contrast
        x = images.astype(np.float64) / 255.0
        grad = np.abs(np.diff(x, axis=2)).mean(axis=(1, 2))  # (N, 3)
        return np.concatenate([grad, x.mean(axis=(1, 2)), x.std(axis=(1, 2))], axis=1)  # (N, 9)

    det = SqueezeDetector(predict, bits=4, median_size=3).fit(base[:20])
    s_clean, s_adv = det.score(base[20:]), det.score(adv[20:])
    assert s_clean.shape == (20,)
    assert s_adv.min() > s_clean.max()


def _store(path, n: int = 20, eps=None, model_hash: str = "h1", values=None):
    import zarr

    from pipeline.io.store import create_array, seal_zarr

    eps = np.r_[np.zeros(n // 2), np.full(n - n // 2, 0.5)] if eps is None else np.asarray(eps)
    root = zarr.open_group(str(path), mode="w")
    create_array(root, "values", data=np.zeros((len(eps), 9, 16), np.float32) if values is None else values)
    create_array(root, "features", data=np.zeros((len(eps), 16), np.float32))
    create_array(root, "is_adversarial", data=eps > 0)
    create_array(root, "eps", data=eps.astype(np.float32))
    create_array(root, "source_index", data=np.arange(len(eps)))
    create_array(root, "split", data=np.ones(len(eps), np.int8))
    root.attrs.update({"model_hash": model_hash, "background_size": 4, "background_mean": [0.0] * 16})
    seal_zarr(path)
    return path


def test_detect_stage_refuses_bad_shap_stores(tmp_path):
    from pipeline.io.errors import DataError
    from stages.artifacts.readers import read_shap_store as read_store
    from stages.errors import StageError

    good = read_store(_store(tmp_path / "ok.zarr"), "h1")
    assert good["values"].shape == (20, 9, 16) and good["is_adversarial"].sum() == 10
    with pytest.raises(StageError, match="another pose checkpoint"):
        read_store(_store(tmp_path / "hash.zarr"), "h2")
    nan = np.zeros((20, 9, 16), np.float32)
    nan[3, 2, 1] = np.nan
    with pytest.raises(StageError, match="NaN"):
        read_store(_store(tmp_path / "nan.zarr", values=nan), "h1")
    with pytest.raises(StageError, match="only clean"):
        read_store(_store(tmp_path / "one.zarr", eps=np.zeros(10)), "h1")
    with pytest.raises(StageError, match=r"\(N, 9, n_features\)"):
        read_store(_store(tmp_path / "shape.zarr", values=np.zeros((20, 8, 16), np.float32)), "h1")
    with pytest.raises(DataError, match="not found"):
        read_store(tmp_path / "missing.zarr", "h1")


def test_detect_split_groups_source_images_and_stratifies_eps():
    """All versions of a source image (clean and every eps) fall on one side; eps shares stay close."""
    from stages.detect import split_indices

    rng = np.random.default_rng(0)
    # 100 clean samples, then 50 at eps 0.5 and 50 at 0.01 drawn independently from 120 source images,
    # so most attacked images have a clean or other-eps twin (as rpod shap draws them)
    source = np.r_[rng.permutation(120)[:100], rng.permutation(120)[:50], rng.permutation(120)[:50]]
    eps = np.r_[np.zeros(100), np.full(50, 0.5), np.full(50, 0.01)].astype(np.float32)
    tr, va, te = split_indices(eps, source, 0.2, 0.2, seed=0)
    assert np.array_equal(np.sort(np.r_[tr, va, te]), np.arange(200))
    for a, b in ((tr, te), (tr, va), (va, te)):
        assert not set(source[a]) & set(source[b])
    assert 30 <= len(te) <= 50 and 24 <= len(va) <= 40
    assert 5 <= (eps[te] == 0.01).sum() <= 15 and 12 <= (eps[te] == 0).sum() <= 28
    again = split_indices(eps, source, 0.2, 0.2, seed=0)
    assert all(np.array_equal(a, b) for a, b in zip((tr, va, te), again))
    from stages.errors import StageError

    with pytest.raises(StageError, match="detect.test_fraction=0.2"):
        split_indices(eps[:4], source[:4] * 0, 0.2, 0.2, seed=0)
