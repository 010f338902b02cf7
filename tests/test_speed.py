"""SPEED / SPEED+ interop: the label and camera formats (pipeline/formats/speed.py), the import as `rpod render`'s
output, `rpod export speed`, and one clear error per kind of bad input."""

import json
from dataclasses import replace

import cv2
import numpy as np
import pandas as pd
import pytest

from pipeline.formats.speed import SPEED_CAMERA, camera_from_json, camera_to_json, from_speed, to_speed
from pipeline.geometry.camera import Intrinsics
from pipeline.geometry.rotations import normalize_quat, quat_to_matrix
from pipeline.io.errors import DataError
from stages.config import params as params_mod
from stages.config.params import load

SIZE = (48, 30)  # source images, Nu x Nv (16:10 like SPEED+)
K_SRC = Intrinsics(*SIZE, 60.0, 60.0, 24.0, 15.0)


def speed_dcm(q):
    """SPEED's direction cosine matrix of q (camera -> target coordinates), written out from its definition."""
    q0, q1, q2, q3 = q / np.linalg.norm(q)
    return np.array(
        [
            [q0**2 + q1**2 - q2**2 - q3**2, 2 * (q1 * q2 + q0 * q3), 2 * (q1 * q3 - q0 * q2)],
            [2 * (q1 * q2 - q0 * q3), q0**2 - q1**2 + q2**2 - q3**2, 2 * (q2 * q3 + q0 * q1)],
            [2 * (q1 * q3 + q0 * q2), 2 * (q2 * q3 - q0 * q1), q0**2 - q1**2 - q2**2 + q3**2],
        ]
    )


def poses(n, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform([-2, -2, 10], [2, 2, 40], size=(n, 3)), normalize_quat(rng.normal(size=(n, 4)))


def test_speed_quaternion_is_our_q():
    """SPEED projects target points as dcm(q).T @ x + r: the rotation our q gives (target -> camera)."""
    t, q = poses(20)
    x_target = np.random.default_rng(1).normal(size=(20, 3))
    for qi, xi in zip(q, x_target):
        assert np.allclose(quat_to_matrix(qi), speed_dcm(qi).T, atol=1e-12)
        assert np.allclose(speed_dcm(qi) @ (quat_to_matrix(qi) @ xi), xi)  # vbs -> tango undoes it
    names, t2, q2 = from_speed(json.loads(json.dumps(to_speed([f"img{i}.jpg" for i in range(20)], t, q))))
    assert names[3] == "img3.jpg" and np.abs(t2 - t).max() < 1e-12 and np.abs(q2 - q).max() < 1e-12


def test_both_key_sets_and_bad_records():
    t, q = poses(2)
    speed = [{"filename": "a.jpg", "q_vbs2tango": list(-q[0]), "r_Vo2To_vbs_true": list(t[0])}]
    names, t2, q2 = from_speed(speed)  # SPEED's key; -q is the same attitude, stored qw >= 0
    assert names == ["a.jpg"] and np.allclose(q2[0], q[0]) and np.allclose(t2[0], t[0])
    bad = [
        ({"filename": "b.jpg", "q_vbs2tango_true": [1, 0, 0, 0]}, "record 0 \\(b.jpg\\).*r_Vo2To_vbs_true"),
        ({"filename": "b.jpg", "r_Vo2To_vbs_true": [0, 0, 9]}, "missing key 'q_vbs2tango_true'"),
        (
            {"filename": "b.jpg", "q_vbs2tango_true": [0.5, 0, 0, 0], "r_Vo2To_vbs_true": [0, 0, 9]},
            "q_vbs2tango_true has norm 0.5, not a unit",
        ),
        ({"filename": "b.jpg", "q_vbs2tango_true": [1, 0, 0], "r_Vo2To_vbs_true": [0, 0, 9]}, "4 finite"),
        ({"q_vbs2tango_true": [1, 0, 0, 0], "r_Vo2To_vbs_true": [0, 0, 9]}, "'filename'"),
    ]
    for record, message in bad:
        with pytest.raises(ValueError, match=message):
            from_speed([record])
    with pytest.raises(ValueError, match="labelled more than once"):
        from_speed(speed * 2)


def test_camera_json():
    K = camera_from_json(camera_to_json(K_SRC))
    assert K == K_SRC
    speed = camera_from_json(SPEED_CAMERA)  # SPEED's published camera: f / pixel pitch
    assert speed.width == 1920 and speed.fx == pytest.approx(0.0176 / 5.86e-6) and speed.cx == 960
    assert camera_from_json({"cameraMatrix": K_SRC.K.tolist()}, size=SIZE) == K_SRC
    for cam, message in [
        ({"Nu": 48, "Nv": 30}, "no camera matrix.*cameraMatrix"),
        ({"Nu": 48, "Nv": 30, "cameraMatrix": [[1, 0], [0, 1]]}, "cameraMatrix must be a 3x3"),
        ({"cameraMatrix": K_SRC.K.tolist()}, "missing key 'Nu'"),
    ]:
        with pytest.raises(ValueError, match=message):
            camera_from_json(cam)


def write_folder(root, layout="plus", n=(6, 3), seed=0):
    """A tiny SPEED+ (camera.json, synthetic/{train,test}.json, synthetic/images/) or SPEED (train.json,
    test.json, images/<split>/) folder of random images; returns {filename: (image RGB, t, q)}."""
    rng = np.random.default_rng(seed)
    truth = {}
    for split, count in zip(("train", "test"), n):
        t, q = poses(count, seed + len(split))
        names = [f"{split}{i:03d}.png" for i in range(count)]
        base = root / "synthetic" if layout == "plus" else root
        img_dir = base / "images" if layout == "plus" else root / "images" / split
        img_dir.mkdir(parents=True, exist_ok=True)
        for name, ti, qi in zip(names, t, q):
            img = rng.integers(0, 256, size=(SIZE[1], SIZE[0], 3), dtype=np.uint8)
            cv2.imwrite(str(img_dir / name), img[..., ::-1])
            truth[name] = (img, ti, qi)
        (base / f"{split}.json").write_text(json.dumps(to_speed(names, t, q)))
    (root / "camera.json").write_text(json.dumps(camera_to_json(K_SRC)))
    return truth


@pytest.fixture
def project(tmp_path, monkeypatch):
    """A working folder whose params import `src/` at the source size (so pixels can be compared)."""
    monkeypatch.chdir(tmp_path)

    def use(source, *extra):
        params_mod.write_params(
            params_mod.compose(
                "smoke",
                [
                    f"render.source={source}",
                    f"render.width={SIZE[0]}",
                    f"render.height={SIZE[1]}",
                    "render.chunk=4",
                    *extra,
                ],
            )
        )

    return tmp_path, use


def render_and_label():
    from stages import label, render

    render.main(load())
    label.main(load())
    return pd.read_parquet("datasets/labels.parquet")


def test_import_export_round_trip(project):
    import zarr

    from stages.export import speed as export_speed

    root, use = project
    truth = write_folder(root / "src")
    use(root / "src")
    labels = render_and_label()
    assert list(labels.split) == ["train"] * 6 + ["test"] * 3 and labels.sequence.nunique() == 9
    assert labels.image.iloc[0] == "synthetic/images/train000.png"
    stored = zarr.open_group("datasets/render/images.zarr", mode="r")["images"]
    meta = json.loads(open("datasets/render/meta.json").read())
    assert np.allclose(meta["K"], K_SRC.K) and meta["source"]["test"] == "synthetic/test.json"
    assert "imported SPEED/SPEED+ set" in open("reports/dataset.md").read()

    export_speed(root / "out")
    assert json.loads((root / "out/camera.json").read_text())["Nu"] == SIZE[0]
    use(root / "out")
    again = render_and_label()
    stored2 = zarr.open_group("datasets/render/images.zarr", mode="r")["images"]
    for row, row2 in zip(labels.itertuples(), again.itertuples()):
        img, t, q = truth[row.image.split("/")[-1]]
        assert np.array_equal(np.asarray(stored[row.index]), img)
        assert np.array_equal(np.asarray(stored2[row2.index]), img)
        assert np.abs(np.array([row2.tx, row2.ty, row2.tz]) - t).max() < 1e-6
        assert np.abs(np.array([row2.qw, row2.qx, row2.qy, row2.qz]) - q).max() < 1e-6
    assert list(again.split) == list(labels.split)

    with pytest.raises(DataError, match="not a SPEED folder"):  # never replaces an unrelated folder
        (root / "keep").mkdir()
        (root / "keep/notes.txt").write_text("mine")
        export_speed(root / "keep")


def test_speed_layout_resized_with_scaled_k(project):
    from stages.artifacts import speed as speed_io

    root, use = project
    write_folder(root / "speed", layout="speed", n=(4, 2))
    use(root / "speed", "render.width=24", "render.height=15")
    p = params_mod.load()
    speed_io.import_source(p, root / "store")
    meta = json.loads((root / "store/meta.json").read_text())
    assert np.allclose(meta["K"], K_SRC.scaled(24, 15).K) and meta["frames"] == 6 and meta["width"] == 24
    assert meta["source"]["train"] == "train.json"
    assert pd.read_parquet(root / "store/poses.parquet")["filename"].iloc[-1] == "images/test/test001.png"
    speed_io.import_source(replace(p, render=replace(p.render, width=64, height=36)), root / "store")  # upscaled
    assert json.loads((root / "store/meta.json").read_text())["width"] == 64


@pytest.mark.parametrize(
    "damage, message",
    [
        (
            lambda r: (r / "synthetic/images/train001.png").write_bytes(b"not an image"),
            "train001.png: not a readable image",
        ),
        (lambda r: (r / "synthetic/images/test002.png").unlink(), "test002.png: not found"),
        (
            lambda r: cv2.imwrite(str(r / "synthetic/images/train000.png"), np.zeros((10, 10, 3), np.uint8)),
            "train000.png: image is 10x10 pixels but camera.json gives Nu x Nv = 48x30",
        ),
        (
            lambda r: (r / "synthetic/train.json").write_text(
                json.dumps([{"filename": "train000.png", "q_vbs2tango_true": [1, 0, 0, 0]}])
            ),
            "synthetic/train.json: record 0 \\(train000.png\\): missing key 'r_Vo2To_vbs_true'",
        ),
        (
            lambda r: (r / "synthetic/test.json").write_text(
                json.dumps(
                    [{"filename": "test000.png", "r_Vo2To_vbs_true": [0, 0, 9], "q_vbs2tango_true": [0.9, 0.1, 0, 0]}]
                )
            ),
            "synthetic/test.json: record 0 \\(test000.png\\): q_vbs2tango_true has norm 0.905539, not a unit",
        ),
        (
            lambda r: (r / "camera.json").write_text(json.dumps({"Nu": 48, "Nv": 30, "distCoeffs": [0] * 5})),
            "camera.json: no camera matrix: needs 'cameraMatrix'",
        ),
        (lambda r: (r / "synthetic/test.json").unlink(), "no test labels"),
    ],
)
def test_bad_input_stops_with_one_message(project, damage, message):
    from stages.artifacts import speed as speed_io

    root, use = project
    write_folder(root / "src")
    damage(root / "src")
    use(root / "src")
    with pytest.raises(DataError, match=message) as err:
        speed_io.import_source(params_mod.load(), root / "store")
    assert "\n" not in str(err.value) and not (root / "store").exists()
