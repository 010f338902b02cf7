"""The train stage on a tiny synthetic dataset: data checks, checkpoints, the loop, the report."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
import yaml
import zarr

from pipeline.formats.models import read_pose, save_pose
from pipeline.geometry.camera import reference_intrinsics
from pipeline.geometry.labels import pose_columns
from pipeline.geometry.rotations import euler_to_matrix, matrix_to_6d, matrix_to_quat
from pipeline.geometry.trajectories import poses_table
from pipeline.io.atomic import file_hash, write_json
from pipeline.io.errors import DataError
from pipeline.io.store import create_array, seal_zarr
from pipeline.io.tables import write_parquet
from stages.artifacts import data, models
from stages.artifacts.paths import POSE
from stages.config import params as params_mod
from stages.config.params import load
from stages.config.schema import build
from stages.errors import StageError

W, H = 48, 27


def write_dataset(
    root: Path, n: int = 40, width: int = W, height: int = H, seed: int = 0, overrides: list[str] | None = None
) -> dict:
    """A tiny stand-in for render + label under `root`: a bright rectangle at the projected target
    position, sized by 1/range, shaded by the attitude; params.yaml = the smoke profile at this size."""
    rng = np.random.default_rng(seed)
    K = reference_intrinsics().scaled(width, height)
    tz = rng.uniform(10, 60, n)
    t = np.stack([rng.uniform(-0.2, 0.2, n) * tz, rng.uniform(-0.2, 0.2, n) * tz, tz], 1)
    R = euler_to_matrix(rng.uniform(-10, 10, (n, 3)))
    images = np.zeros((n, height, width, 3), np.uint8)
    for i in range(n):
        u, v = K.fx * t[i, 0] / t[i, 2] + K.cx, K.fy * t[i, 1] / t[i, 2] + K.cy
        half = max(1, int(round(K.fx * 1.5 / t[i, 2])))
        shade = (128 + 100 * R[i, :, 0]).clip(0, 255)
        images[i, max(0, int(v) - half) : int(v) + half + 1, max(0, int(u) - half) : int(u) + half + 1] = shade
    group = zarr.open_group(str(root / "datasets/render/images.zarr"), mode="w")
    create_array(group, "images", shape=images.shape, chunks=(16, height, width, 3), dtype="uint8")[:] = images
    seal_zarr(root / "datasets/render/images.zarr")
    r6 = matrix_to_6d(R)
    labels = pd.DataFrame(
        {
            "index": np.arange(n),
            "image": [f"images/{i}" for i in range(n)],
            "sequence": np.arange(n) % 13,
            "frame": np.arange(n) // 13,
            **pose_columns(t, matrix_to_quat(R), r6),
            "range": np.linalg.norm(t, axis=1),
            "split": np.where(np.arange(n) % 5 == 0, "test", "train"),
        }
    )
    params = params_mod.compose("smoke", [f"render.width={width}", f"render.height={height}", *(overrides or [])])
    params_mod.write_params(params, root / "params.yaml")
    typed = build(params)
    write_json(
        root / "datasets/render/meta.json",
        {"complete": True, "frames": n, "K": K.K, "fingerprint": params_mod.render_fingerprint(typed)},
    )
    labels.attrs[data.RENDER_KEY] = params_mod.render_fingerprint(typed)  # as `rpod label` records it
    write_parquet(
        poses_table(np.arange(n), labels["sequence"].to_numpy(), labels["frame"].to_numpy(), R, t),
        root / "datasets/render/poses.parquet",
    )  # as `rpod render` writes them
    labels.to_parquet(root / "datasets/labels.parquet")
    return typed


@pytest.fixture
def dataset(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    torch.set_num_threads(1)
    return write_dataset(tmp_path)


def test_load_split_reads_rows_and_images(dataset):
    train, test = data.load_split(dataset, "train"), data.load_split(dataset, "test")
    assert len(train) == 32 and len(test) == 8
    assert train.images.shape == (32, H, W, 3) and train.images.dtype == np.uint8
    assert train.targets.shape == (32, 9)
    store = zarr.open_group("datasets/render/images.zarr", mode="r")["images"]
    np.testing.assert_array_equal(test.images[3], store[int(test.labels["index"][3])])
    lazy = data.load_split(dataset, "test", preload=False)
    np.testing.assert_array_equal(lazy.images[3], test.images[3])


def _edit_labels(fn) -> None:
    df = pd.read_parquet("datasets/labels.parquet")
    fn(df).to_parquet("datasets/labels.parquet")


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda df: df.assign(tx=df["tx"].where(df.index != 3)), "NaN or infinite labels"),
        (lambda df: df.drop(columns=["r5"]), "r0..r5"),
        (lambda df: df.assign(r6=0.0), "r0..r5"),
        (lambda df: df.assign(r0=df["r0"] * 2), r"r5'\] are not the 6-D rotation of its quaternion"),
        (lambda df: df.assign(split="train"), "'test' split is empty"),
        (lambda df: df.assign(index=df["index"] + 100), r"index is no row of the render's poses \(0..39\)"),
    ],
)
def test_bad_labels_are_refused_clearly(dataset, edit, message):
    _edit_labels(edit)
    with pytest.raises(StageError, match=message):
        data.load_split(dataset, "test")


def test_image_size_mismatch_is_refused(dataset):
    dataset = replace(dataset, render=replace(dataset.render, width=64))
    with pytest.raises(StageError, match="48x27 pixels but params.yaml has render.width x render.height = 64x27"):
        data.load_split(dataset, "train")


def test_checkpoint_round_trip_and_mismatch_refusal(dataset, tmp_path):
    from pipeline.pose.loss import PoseLoss
    from pipeline.pose.model import PoseNet

    model, loss = PoseNet(dataset.train.width, dataset.train.dropout).eval(), PoseLoss()
    with torch.no_grad():
        loss.s_p.fill_(0.7)
    path = tmp_path / "models/pose.pt"
    save_pose(path, model, loss, (H, W), {"epoch": 1})
    pose = models.load_pose(dataset, path)
    loaded = pose.model
    assert not loaded.training
    x = torch.rand(2, 3, H, W)
    torch.testing.assert_close(loaded(x), model(x))
    assert pose.loss.s_p.item() == pytest.approx(0.7)
    wider = replace(dataset, train=replace(dataset.train, width=0.5))
    with pytest.raises(StageError, match=r"does not match params.yaml: width=0.125 \(params: 0.5\)"):
        models.load_pose(wider, path)
    bigger = replace(dataset, render=replace(dataset.render, height=54, width=96))
    with pytest.raises(StageError, match=r"input_size HxW=\[27, 48\] \(params: \[54, 96\]\)"):
        models.check_pose(bigger, path, read_pose(path))
    path.write_bytes(b"not a checkpoint")
    with pytest.raises(DataError, match="unreadable"):
        read_pose(path)


def test_fit_improves_and_tracks_the_best_epoch(dataset):
    from pipeline.pose.loss import PoseLoss
    from pipeline.pose.model import PoseNet
    from pipeline.pose.train import TrainConfig, fit

    train, test = data.load_split(dataset, "train"), data.load_split(dataset, "test")
    model = PoseNet(0.125, 0.0)
    model.set_output_bias(train.targets[:, :3].mean(0), train.targets[:, 3:].mean(0))
    seen = []
    cfg = TrainConfig(epochs=4, batch_size=8, lr_base=1e-4, lr_max=2e-3, cycle_epochs=2)
    result = fit(
        model,
        PoseLoss(),
        data.pose_dataset(train, dataset.train.augment),
        data.pose_dataset(test),
        cfg,
        on_epoch=lambda stats, best, net: seen.append((stats.epoch, best)),
        progress=False,
    )
    assert [e for e, _ in seen] == [1, 2, 3, 4] and len(result.history) == 4
    scores = [h.val_score for h in result.history]
    assert result.best_epoch == int(np.argmin(scores)) + 1 and result.best_score == min(scores)
    assert result.history[-1].loss < result.history[0].loss
    assert all(h.images_per_s > 0 for h in result.history)
    model.load_state_dict(result.best_state)  # the kept state loads back


def test_time_limit_stops_between_epochs(dataset):
    from pipeline.pose.loss import PoseLoss
    from pipeline.pose.model import PoseNet
    from pipeline.pose.train import TrainConfig, fit

    train, test = data.load_split(dataset, "train"), data.load_split(dataset, "test")
    cfg = TrainConfig(epochs=50, batch_size=16, max_minutes=1e-4)
    result = fit(PoseNet(0.125), PoseLoss(), data.pose_dataset(train), data.pose_dataset(test), cfg, progress=False)
    assert result.stopped_early and len(result.history) == 1


def test_train_stage_writes_checkpoint_report_and_metrics(dataset):
    from stages.train import main

    main(load())
    metrics = json.loads(Path("reports/metrics/train.json").read_text())
    assert metrics["epochs_run"] == dataset.train.epochs and metrics["processes"] == 1
    assert metrics["test"]["n"] == 8 and metrics["train"]["n"] + metrics["val"]["n"] == 32 and metrics["val"]["n"] == 3
    assert sum(b["n"] for b in metrics["test"]["bins"]) == 8
    report = Path("reports/pose.md").read_text()
    assert "0.490" in report and "Guidance requirements" in report and "60-45" in report
    model = models.load_pose(params_mod.load(), POSE).model
    assert model(torch.rand(1, 3, H, W)).shape == (1, 9)
    assert read_pose(POSE)["K"] == reference_intrinsics().scaled(W, H).K.tolist()  # the training images' camera
    assert read_pose(POSE)["labels_hash"] == file_hash("datasets/labels.parquet")  # and their labels
    assert Path("dvclive/train/plots/metrics/val_pos_m.tsv").exists()
    logged = yaml.safe_load(Path("dvclive/train/params.yaml").read_text())  # DVCLive's log_params
    assert logged["train"]["epochs"] == dataset.train.epochs and logged["render"] == {"width": W, "height": H}


def test_test_split_is_read_only_after_training(dataset, monkeypatch):
    """The checkpoint is chosen on validation frames carved from the training split: no test frame
    reaches `fit`, and the test split is first loaded after `fit` returns."""
    import pipeline.pose.train
    from stages import train

    events: list[tuple[str, object]] = []
    load_split, real_fit = data.load_split, pipeline.pose.train.fit
    test_targets = {tuple(t) for t in load_split(dataset, "test").targets}

    def recording_load(params, split, **kw):
        events.append(("load", split))
        return load_split(params, split, **kw)

    def recording_fit(model, loss, train_set, val_set, *args, **kw):
        events.append(("fit", (len(train_set), len(val_set))))
        seen = {tuple(t) for ds in (train_set, val_set) for t in ds.targets.numpy()}
        assert len(seen) == 32 and not seen & test_targets
        out = real_fit(model, loss, train_set, val_set, *args, **kw)
        events.append(("fit done", None))
        return out

    monkeypatch.setattr(data, "load_split", recording_load)
    monkeypatch.setattr(pipeline.pose.train, "fit", recording_fit)
    train.main(load())
    assert events[:2] == [("load", "train"), ("fit", (29, 3))]
    assert events.index(("load", "test")) > events.index(("fit done", None))


def test_training_is_reproducible_bit_for_bit(dataset):
    """Two runs of the train stage on one machine give identical weights (seeded before the network
    is built, deterministic algorithms)."""
    from stages import train

    weights = []
    for _ in range(2):
        train.main(load())
        weights.append(torch.load(POSE, weights_only=False))
    a, b = (w["model"] for w in weights)
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k


def test_holdout_keeps_groups_whole():
    from pipeline.evaluation.splits import holdout

    groups = np.repeat(np.arange(20), 3)
    kept, out = holdout(groups, 0.25, seed=1)
    assert len(out) == 15 and len(kept) == 45
    assert not set(groups[kept]) & set(groups[out])
    np.testing.assert_array_equal(holdout(groups, 0.25, seed=1)[1], out)
    assert not np.array_equal(holdout(groups, 0.25, seed=2)[1], out)
    with pytest.raises(ValueError, match="fraction must be in"):
        holdout(groups, 1.0, seed=0)
    with pytest.raises(ValueError, match="both sides non-empty"):
        holdout(np.arange(3), 0.1, seed=0)


def test_checkpoint_bytes_do_not_depend_on_the_temporary_name(tmp_path):
    """The same weights saved twice give the same file hash (models/pose.pt's hash is in the reports)."""
    from pipeline.io.atomic import file_hash
    from pipeline.pose.loss import PoseLoss
    from pipeline.pose.model import PoseNet

    torch.manual_seed(0)
    model, loss = PoseNet(0.125), PoseLoss()
    hashes = []
    for name in ("a.pt", "b.pt"):
        save_pose(tmp_path / name, model, loss, (H, W), {"epoch": 1})
        hashes.append(file_hash(tmp_path / name))
    assert hashes[0] == hashes[1]


def test_train_stage_on_the_cpu_device_and_a_missing_gpu_in_one_line(tmp_path, monkeypatch, capsys):
    """device: cpu trains as before (the metrics name the device); device: cuda on a machine without a
    GPU stops `rpod train` and `rpod attack` with one line before any work."""
    import sys

    from stages import cli, train

    monkeypatch.chdir(tmp_path)
    torch.set_num_threads(1)
    write_dataset(tmp_path, overrides=["device=cpu"])
    train.main(load())
    assert json.loads(Path("reports/metrics/train.json").read_text())["device"] == "cpu"
    capsys.readouterr()  # the training run's own output
    params_mod.write_params({**dataclasses.asdict(params_mod.load()), "device": "cuda"})
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setitem(cli._DEBUG, "on", False)
    for stage in ("train", "attack"):
        monkeypatch.setattr(sys, "argv", ["rpod", stage])
        with pytest.raises(SystemExit) as exit_info:
            cli.main()
        err = capsys.readouterr().err
        assert exit_info.value.code == 1 and err.count("\n") == 1
        assert (
            err.startswith("error: params.yaml device: 'cuda' asks for a CUDA GPU but torch ") and "auto or cpu" in err
        )
    assert not Path("reports/metrics/attack.json").exists()
