"""SPEED / SPEED+ import faults: file names confined to the dataset folder and normalised before the duplicate
check, no image in both splits, image sizes exact from the header, K checked, every labelled file checked to
exist before the first image is read; each refused with one line naming the file or field."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from test_speed import K_SRC, SIZE, poses, write_folder

from pipeline.formats.speed import camera_from_json, camera_to_json, from_speed, to_speed
from pipeline.io.errors import DataError
from stages.config.params import compose
from stages.config.schema import build
from stages.errors import StageError


def _import(src: Path, out: Path) -> None:
    from stages.artifacts.speed import import_source

    import_source(
        build(compose("smoke", [f"render.source={src}", "render.width=24", "render.height=15", "render.chunk=4"])), out
    )


def _relabel(src: Path, split: str, names: list[str]) -> None:
    """Rewrite synthetic/<split>.json with these file names (poses kept)."""
    path = src / "synthetic" / f"{split}.json"
    records = json.loads(path.read_text())
    for r, name in zip(records, names):
        r["filename"] = name
    path.write_text(json.dumps(records))


def test_names_are_normalised_before_the_duplicate_check():
    t, q = poses(2)
    with pytest.raises(ValueError, match="'img000005.png' is labelled more than once"):
        from_speed(to_speed(["./img000005.png", "img000005.png"], t, q))
    assert from_speed(to_speed(["sub/./a.png", "b.png"], t, q))[0] == ["sub/a.png", "b.png"]


@pytest.mark.parametrize(
    "split, name, error, message",
    [
        *[
            ("train", n, DataError, r"train.json: record 0 .*filename must be a path inside the dataset folder")
            for n in ("../../../../x.png", "/etc/passwd", "a/../../x.png", "C:/data/x.png")
        ],
        ("test", "train002.png", StageError, r"train002.png is labelled in both .*train.json and .*test.json"),
        ("test", "./train002.png", StageError, r"train002.png is labelled in both"),
    ],
)
def test_names_outside_the_folder_or_in_both_splits_are_refused(tmp_path, split, name, error, message):
    src = tmp_path / "src"
    write_folder(src)
    _relabel(src, split, [name])
    with pytest.raises(error, match=message):
        _import(src, tmp_path / "store")
    assert not (tmp_path / "store").exists()


def test_image_size_is_exact(tmp_path):
    """A 47x29 image is not the 48x30 camera.json names, though both decode to 24x15 at 1/2 size."""
    src = tmp_path / "src"
    write_folder(src)
    cv2.imwrite(str(src / "synthetic/images/train003.png"), np.zeros((SIZE[1] - 1, SIZE[0] - 1, 3), np.uint8))
    with pytest.raises(DataError, match=r"train003.png: image is 47x29 pixels but camera.json gives Nu x Nv = 48x30"):
        _import(src, tmp_path / "store")


def test_missing_files_are_found_before_any_image_is_read(tmp_path, monkeypatch):
    from stages.artifacts import speed

    src = tmp_path / "src"
    write_folder(src)
    (src / "synthetic/images/test002.png").unlink()
    monkeypatch.setattr(speed, "read_image", lambda *a: pytest.fail("an image was read before the check"))
    with pytest.raises(StageError, match=r"test002.png: not found, named by its label file \(1 of 9"):
        _import(src, tmp_path / "store")


def test_source_test_outside_the_folder_is_refused(tmp_path):
    from stages.artifacts import speed

    with pytest.raises(StageError, match="render.source_test.*inside the dataset folder"):
        speed.labels_file(tmp_path, ("test.json",), "../other/test.json", "test")


def _cam(**change) -> dict:
    cam = camera_to_json(K_SRC)
    K = np.array(cam["cameraMatrix"])
    for (i, j), v in change.pop("K", {}).items():
        K[i, j] = v
    return {**cam, "cameraMatrix": K.tolist(), **change}


@pytest.mark.parametrize(
    "cam, message",
    [
        (_cam(cameraMatrix=K_SRC.K.T.tolist()), r"no skew; not transposed"),
        (_cam(K={(0, 1): 0.5}), r"no skew"),
        (_cam(K={(0, 2): -5000}), r"principal point \(-5000, 15\) lies outside the 48x30 image"),
        (_cam(K={(1, 2): 31}), r"principal point \(24, 31\) lies outside"),
        (_cam(K={(0, 0): 1e-12}), r"focal lengths must be at least 1 pixel"),
        (_cam(Nu=64.9), r"Nu must be a whole number of pixels, got 64.9"),
        (
            {"Nu": 48, "Nv": 30, "fx": 0.0176, "fy": 0.0176, "ppx": 5.86e-6, "ppy": 5.86e-6, "ccx": 5000},
            r"principal point \(5000, 15\) lies outside",
        ),
    ],
)
def test_bad_cameras_are_refused(cam, message):
    with pytest.raises(ValueError, match=message):
        camera_from_json(cam)
    assert camera_from_json(camera_to_json(K_SRC)) == K_SRC


@pytest.mark.parametrize("how", ["symlink", "copy"])
def test_a_test_image_that_is_a_training_image_is_refused(tmp_path, how):
    """The issue's probe: a test image linked to, or copied byte for byte from, a training image was imported (a
    leak from training into the test split)."""
    src = tmp_path / "src"
    write_folder(src)
    test, train = src / "synthetic/images/test001.png", src / "synthetic/images/train004.png"
    test.unlink()
    if how == "symlink":
        test.symlink_to(train.name)
    else:
        test.write_bytes(train.read_bytes())
    with pytest.raises(
        DataError,
        match=r"test image .*test001.png is the training image .*train004.png \(a link to it "
        r"or a byte-identical copy; 1 such images\)",
    ):
        _import(src, tmp_path / "store")
    assert not (tmp_path / "store").exists()


def test_an_image_linked_from_outside_the_folder_is_refused(tmp_path):
    src = tmp_path / "src"
    write_folder(src)
    outside = tmp_path / "elsewhere.png"
    (src / "synthetic/images/train002.png").rename(outside)
    (src / "synthetic/images/train002.png").symlink_to(outside)
    with pytest.raises(DataError, match=r"train002.png resolves to .*elsewhere.png, outside the dataset folder .*src"):
        _import(src, tmp_path / "store")


@pytest.mark.parametrize(
    "record, message",
    [
        ({"r_Vo2To_vbs_true": [0.0, 0.0, -9.0]}, r"puts the target behind the camera or in its plane"),
        ({"r_Vo2To_vbs_true": [0.0, 0.0, 0.0]}, r"puts the target behind the camera or in its plane"),
        ({"r_Vo2To_vbs_true": [0.0, 0.0, 1e300]}, r"puts the target more than 10000 m away"),
        ({"r_Vo2To_vbs_true": [True, False, True]}, r"r_Vo2To_vbs_true must be a list of 3 numbers, got \[True"),
        ({"q_vbs2tango": [1.0, 0.0, 0.0, 0.0]}, r"has both 'q_vbs2tango_true' \(SPEED\+\) and 'q_vbs2tango' \(SPEED\)"),
        ({"q_vbs2tango_true": [0.0, 0.0, 0.0, 0.0]}, r"has norm 0, not a unit quaternion"),
    ],
)
def test_implausible_records_are_refused(record, message):
    t, q = poses(1)
    good = to_speed(["a.png"], t, q)[0]
    with pytest.raises(ValueError, match=r"record 0 \(a.png\): .*" + message):
        from_speed([{**good, **record}])


def test_export_refuses_a_zero_quaternion():
    t, _ = poses(2)
    q = np.array([[1.0, 0, 0, 0], [0.0, 0, 0, 0]])
    with pytest.raises(ValueError, match=r"b.png: quaternion \[0.0, 0.0, 0.0, 0.0\] is not a unit quaternion"):
        to_speed(["a.png", "b.png"], t, q)
