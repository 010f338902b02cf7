"""The smaller faults of issue 42 (item 10): a key given twice in params.yaml, duplicated eps entries, values a
report claims but did not use, and late or misleading errors; each refused with one line naming what is wrong."""

from __future__ import annotations

import pytest

from pipeline.io.errors import DataError


def test_a_key_given_twice_in_params_yaml_is_refused(tmp_path):
    """The issue's probe: yaml keeps the last of two equal keys silently, so an edit above a forgotten line was lost."""
    from stages.config import params as params_mod

    params_mod.write_params(params_mod.compose("smoke"), tmp_path / "params.yaml")
    text = (tmp_path / "params.yaml").read_text()
    assert params_mod.load(tmp_path / "params.yaml").seed == 0
    (tmp_path / "params.yaml").write_text(text.replace("seed: 0\n", "seed: 0\nseed: 7\n", 1))
    with pytest.raises(DataError, match=r"params.yaml: key 'seed' is given twice \(line \d+\); keep one"):
        params_mod.load(tmp_path / "params.yaml")


@pytest.mark.parametrize("key", ["evaluate.eps", "shap.eps"])
def test_a_repeated_eps_is_refused(key):
    """The issue's probe: duplicate eps entries duplicated rows and skewed means (exit 0). A validator for the
    schema to call (stages/config/guards.py lists where)."""
    from stages.config.guards import distinct

    distinct([0.5, 0.05, 0.01], key)
    with pytest.raises(ValueError, match=rf"{key} lists 0.05 twice; give each value once"):
        distinct([0.5, 0.05, 0.01, 0.05], key)


@pytest.mark.parametrize(
    "bins, message",
    [
        ([], r"train.range_bins is empty"),
        ([60, float("nan")], r"nan is not a range in metres"),
        ([60, -5], r"-5 is not a range in metres"),
        ([60, 30, 30], r"train.range_bins lists 30 twice"),
    ],
)
def test_range_bins_the_tables_cannot_use_are_refused(bins, message):
    """The issue's probe: train.range_bins=[] crashed after training had finished (8.5 min lost)."""
    from stages.config.guards import range_bins

    range_bins([60, 45, 30, 20, 10])
    with pytest.raises(ValueError, match=message):
        range_bins(bins)


def test_an_even_median_filter_is_refused():
    """The issue's probe: detect.squeeze_median=4 failed only after three baselines had run."""
    from stages.config.guards import odd

    odd(3, "detect.squeeze_median")
    with pytest.raises(ValueError, match=r"detect.squeeze_median=4 must be odd .*e.g. 5"):
        odd(4, "detect.squeeze_median")


def test_the_lid_report_states_the_neighbours_used(monkeypatch):
    """The issue's probe: LID capped detect.lid_k at a minibatch's clean samples but the report claimed the value
    asked for. `neighbours` is the fewest the fit uses, and the report is given that."""
    import numpy as np

    from pipeline.detectors import lid
    from stages.config.params import compose
    from stages.config.schema import build
    from stages.detect import _used

    used = []
    real = lid.lid_mle
    monkeypatch.setattr(
        lid,
        "lid_mle",
        lambda x, ref, k, skip_self=False: (used.append(min(k, len(ref) - int(skip_self))), real(x, ref, k, skip_self))[
            1
        ],
    )
    rng = np.random.default_rng(0)
    labels = np.r_[np.zeros(23, int), np.ones(17, int)]
    lid.LIDDetector(k=20, batch_size=16).fit(rng.normal(size=(40, 5)), labels)
    assert min(used) == lid.neighbours(20, labels, 16) == 10  # 23 clean in 2 minibatches: 11 and 12
    d = build(compose("smoke", ["detect.lid_k=20", "detect.lid_batch=16"])).detect
    assert _used(d, labels).lid_k == 10 and _used(d, np.zeros(400, int)).lid_k == 15  # 25 batches of 16 clean
    few = build(compose("smoke", ["detect.lid_k=5", "detect.lid_batch=16"])).detect
    assert _used(few, labels) == few  # not capped: as asked


def test_a_read_only_models_folder_and_an_empty_test_split_are_found_before_training(tmp_path, monkeypatch):
    """The issue's probes: both were found only after training had finished."""
    import errno
    import os
    import tempfile

    import pandas as pd
    from test_training import write_dataset

    from pipeline.pose import train as fitting
    from stages import train
    from stages.config.params import load
    from stages.errors import StageError

    monkeypatch.chdir(tmp_path)
    write_dataset(tmp_path)
    monkeypatch.setattr(fitting, "fit", lambda *a, **k: pytest.fail("training started"))
    real = tempfile.TemporaryFile

    def read_only(*args, dir=None, **kwargs):  # models/ on a read-only mount (root ignores modes)
        if str(dir).endswith("models"):
            raise OSError(errno.EROFS, os.strerror(errno.EROFS))
        return real(*args, dir=dir, **kwargs)

    monkeypatch.setattr(tempfile, "TemporaryFile", read_only)
    with pytest.raises(DataError, match=r"models is not writable \(Read-only file system\); the outputs go there"):
        train.main(load())
    monkeypatch.setattr(tempfile, "TemporaryFile", real)
    df = pd.read_parquet("datasets/labels.parquet")
    df.assign(split="train").to_parquet("datasets/labels.parquet")
    with pytest.raises(StageError, match=r"the 'test' split is empty"):
        train.main(load())


def test_disk_full_while_saving_a_checkpoint_names_the_output(tmp_path, monkeypatch):
    """The issue's probe: a full disk while saving pose.pt ended in a deep traceback."""
    import builtins

    import torch

    from pipeline.io.atomic import atomic_outputs
    from pipeline.io.checkpoints import save_torch

    real = builtins.open

    def full(path, mode="r", *args, **kwargs):  # every temporary file lands on a full disk
        return (
            real("/dev/full", mode) if str(path).endswith(".tmp") and "w" in mode else real(path, mode, *args, **kwargs)
        )

    monkeypatch.setattr(builtins, "open", full)
    with pytest.raises(
        DataError,
        match=r"could not write .*models/pose.pt \(No space left on device\); the file was "
        r"left as it was",
    ):
        with atomic_outputs(tmp_path / "models/pose.pt") as (pose,):
            save_torch(pose, {"model": torch.zeros(100_000)})
    assert not list((tmp_path / "models").iterdir())
