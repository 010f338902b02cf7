"""Checkpoints (issue 42 item 8 and the crashes of item 10): a flipped byte inside a weight record, learned loss
weights out of range, garbled or extra keys, weights that do not fit the arch, a detector's short background mean
or a threshold that is no probability, and a pose model of the other role (the robust model in the standard
model's place) are each refused on load with one line naming the file."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from pipeline.formats.models import DETECTOR_FORMAT, read_detector, read_pose, save_pose
from pipeline.io.checkpoints import save_torch
from pipeline.io.errors import DataError

H, W = 18, 32


def _pose(path: Path, black_level: float = 0.0, **change) -> Path:
    from pipeline.pose.loss import PoseLoss
    from pipeline.pose.model import PoseNet

    torch.manual_seed(0)
    save_pose(path, PoseNet(width=0.125, black_level=black_level), PoseLoss(), (H, W), {"epoch": 1})
    if change:
        ckpt = torch.load(path, weights_only=True)
        for key, value in change.items():
            if value is None:
                ckpt.pop(key)
            else:
                ckpt[key] = value(ckpt[key]) if callable(value) else value
        save_torch(path, ckpt)
    return path


def _detector(path: Path, **change) -> Path:
    from pipeline.detectors.lstm import LSTMConfig, LSTMDetector, to_checkpoint

    lstm = LSTMDetector(LSTMConfig(n_features=16, hidden=4, dense=[4]))  # threshold 0.5
    ckpt = {
        **to_checkpoint(lstm),
        "format": DETECTOR_FORMAT,
        "pose_model_hash": "0" * 16,
        "shap_method": "exact",
        "background_mean": torch.zeros(16),
        "background_size": 4,
    }
    save_torch(path, {**ckpt, **change})
    return path


def test_a_flipped_byte_inside_a_weight_record_is_refused(tmp_path):
    """torch.load does not check the CRC-32 its zip records carry: the flipped weight loaded as a wrong number."""
    path = _pose(tmp_path / "pose.pt")
    weight = torch.load(path, weights_only=True)["model"]["head_pos.weight"]
    raw = bytearray(path.read_bytes())
    at = raw.find(weight.numpy().tobytes()[:64])
    assert at > 0
    raw[at + 5] ^= 0x40
    path.write_bytes(bytes(raw))
    assert not torch.equal(torch.load(path, weights_only=True)["model"]["head_pos.weight"], weight)  # loads silently
    with pytest.raises(
        DataError,
        match=r"checkpoint .*pose.pt is damaged: record \S+/data/\d+ fails its CRC-32 "
        r"\(changed since it was written\); re-run `rpod train`",
    ):
        read_pose(path)


@pytest.mark.parametrize(
    "change, message",
    [
        ({"loss": lambda loss: {**loss, "s_p": 1e30}}, r"loss s_p = 1e\+30 is no learned log-variance \(\|s\| <= 10"),
        ({"loss": lambda loss: {**loss, "s_r": "0.1"}}, r"loss s_r = '0.1' is no learned log-variance"),
        ({"arch": lambda arch: {**arch, "widht": 0.5}}, r"arch must hold numbers width, dropout"),
        (
            {"arch": lambda arch: {**arch, "width": 0.25}},
            r"its weights do not fit arch .*'width': 0.25.*misshapen, first ",
        ),
        ({"arch": lambda arch: {**arch, "width": -1.0}}, r"arch .*width must be positive"),
        ({"extra": 1}, r"keys missing none, unknown \['extra'\]"),
        ({"loss": None}, r"keys missing \['loss'\]"),
        ({"input_size": [18.5, 32]}, r"input_size must be \[height, width\] in pixels"),
        (
            {"model": lambda m: {**m, "head_pos.extra": torch.zeros(1)}},
            r"its weights do not fit .*first head_pos.extra: \(1,\) for none",
        ),
    ],
)
def test_a_garbled_pose_checkpoint_is_one_line(tmp_path, change, message):
    path = _pose(tmp_path / "pose.pt", **change)
    with pytest.raises(DataError, match=r"pose checkpoint .*pose.pt: " + message) as e:
        read_pose(path)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize(
    "change, message",
    [
        (
            {"background_mean": torch.zeros(10)},
            r"background_mean must hold the 16 features' SHAP background mean, got "
            r"shape \(10,\)",
        ),
        ({"threshold": 1.5}, r"threshold 1.5 is no probability in \(0, 1\)"),
        (
            {"config": {"n_rows": 9, "n_features": 16, "hidden": 4, "dense": [4], "typo": 1}},
            r"does not hold an LSTM detector \(TypeError",
        ),
        ({"state_dict": {}}, r"does not hold an LSTM detector \(RuntimeError"),
    ],
)
def test_a_garbled_detector_checkpoint_is_one_line(tmp_path, change, message):
    """A threshold of 1.5 was reported as "calibrated for another pose model" by the defense's check."""
    path = _detector(tmp_path / "detector.pt", **change)
    with pytest.raises(DataError, match=r"detector checkpoint .*detector.pt" + ".*" + message) as e:
        read_detector(path)
    assert "\n" not in str(e.value)
    read_detector(_detector(tmp_path / "ok.pt"))


def test_the_robust_model_in_the_standard_models_place_is_refused(tmp_path):
    """The issue's probe: models/pose_robust.pt symlinked as models/pose.pt was read as the standard model. The
    chain door checks each pose file's role before it reads the detector (missing here: the next error)."""
    from pipeline.formats.chain import load_chain

    models = tmp_path / "models"
    models.mkdir()
    _pose(models / "pose_robust.pt", black_level=0.07)
    (models / "pose.pt").symlink_to("pose_robust.pt")
    with pytest.raises(DataError, match="detector"):
        load_chain(models, "robust", defended=False)
    with pytest.raises(
        DataError,
        match=r"models/pose.pt holds the robust pose model \(arch .*black_level.*\) where "
        r"the standard one belongs",
    ):
        load_chain(models, "standard", defended=False)
    (models / "pose.pt").unlink()
    _pose(models / "pose.pt")
    with pytest.raises(DataError, match="detector"):
        load_chain(models, "standard", defended=False)
    shutil.copyfile(models / "pose.pt", models / "pose_robust.pt")
    with pytest.raises(
        DataError,
        match=r"pose_robust.pt holds the standard pose model .* where the robust one "
        r"belongs; re-run `rpod train --robust`",
    ):
        load_chain(models, "robust", defended=False)


def test_the_api_refuses_a_standard_model_as_a_runs_shipped_one(tmp_path):
    import rpodguard

    models = tmp_path / "models"
    models.mkdir()
    _pose(models / "pose_robust.pt")
    _detector(models / "detector_robust.pt")
    with pytest.raises(DataError, match=r"pose_robust.pt holds the standard pose model"):
        rpodguard.load_chain(models)


def test_the_shipped_checkpoints_pass_every_check():
    from rpodguard.api import BUNDLE

    ckpt = read_pose(BUNDLE / "pose.pt")
    assert "black_level" in ckpt["arch"] and np.isfinite(ckpt["loss"]["s_p"])
    read_detector(BUNDLE / "detector.pt")
