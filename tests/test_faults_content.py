"""Data pinned by content and degenerate data refused (issue 42, items 4, 5 and 7): a SPEED import records the sha256
of what it read, so labels of an earlier import of an edited folder are refused and `rpod label` finds the folder
changed since; labels are cross-checked against the render's poses and their own values (6-D = q, unit q, splits,
integer index, no image in both splits); a SHAP store names the detector split it explains; a render, an
evaluation render, a SPEED import and a label split mostly without the target in view are refused, naming how
many frames and what to check."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pandas as pd
import pytest
from test_speed import SIZE, project, render_and_label, write_folder  # noqa: F401  (project: a fixture)
from test_training import dataset  # noqa: F401  (a fixture)

from pipeline.io.errors import DataError
from stages.artifacts import data
from stages.config import params as params_mod
from stages.config.params import load
from stages.errors import StageError


def _dark(path, k: int) -> None:
    """A black image (no target in view) whose bytes differ from the other dark ones (a faint pixel of value k)."""
    img = np.zeros((SIZE[1], SIZE[0], 3), np.uint8)
    img[0, 0] = k
    cv2.imwrite(str(path), img)


def _move(path, metres: float) -> None:
    """Every target of a SPEED label file `metres` farther along the boresight (the issue's 5 m probe)."""
    records = json.loads(path.read_text())
    for r in records:
        r["r_Vo2To_vbs_true"][2] += metres
    path.write_text(json.dumps(records))


def test_a_speed_import_is_pinned_by_its_content(project):  # noqa: F811
    from stages import label, render

    root, use = project
    write_folder(root / "src")
    use(root / "src")
    labelled = render_and_label()
    sha = json.loads(open("datasets/render/meta.json").read())["source"]["sha256"]
    assert len(sha) == 64 and labelled.attrs[data.RENDER_KEY].endswith(":" + sha[:16])
    _move(root / "src/synthetic/train.json", 5.0)
    with pytest.raises(
        StageError,
        match=r"render.source .*src changed since `rpod render` imported it \(sha256 of its "
        r"label files, camera.json and images \w+, imported \w+\); re-run `rpod render`",
    ):
        label.main(load())
    render.main(load())  # the same params, the edited folder: another render
    with pytest.raises(StageError, match=r"labels.parquet labels another render than datasets/render"):
        data.load_labels()  # what `rpod train` reads: the stale labels refused
    label.main(load())
    train = (labelled["split"] == "train").to_numpy()
    assert np.allclose(data.load_labels()["tz"], labelled["tz"] + 5 * train)


def test_a_speed_folder_moved_elsewhere_keeps_its_content_hash(project):  # noqa: F811
    from stages.artifacts import speed as speed_io

    root, use = project
    write_folder(root / "src")
    use(root / "src")
    speed_io.import_source(params_mod.load(), root / "a")
    (root / "src").rename(root / "moved")
    use(root / "moved")
    speed_io.import_source(params_mod.load(), root / "b")
    sha = [json.loads((root / f / "meta.json").read_text())["source"]["sha256"] for f in ("a", "b")]
    assert sha[0] == sha[1]


def test_labels_of_a_render_with_a_wrong_range_are_refused_at_label_time(project):  # noqa: F811
    from pipeline.io.tables import write_parquet
    from stages import label, render

    root, use = project
    write_folder(root / "src")
    use(root / "src")
    render.main(load())
    poses = pd.read_parquet("datasets/render/poses.parquet")
    write_parquet(poses.assign(range=poses["range"] + 1.0), "datasets/render/poses.parquet")
    with pytest.raises(
        StageError,
        match=r"datasets/render: row 0 \(index 0\): range is not the distance \|t\| of its "
        r"position \(9 such rows\)",
    ):
        label.main(load())


@pytest.mark.parametrize(
    "edit, message",
    [
        (
            lambda df: df.assign(tx=np.where(df["index"] == 5, -df["tx"], df["tx"])),
            r"row 5 \(index 5\): its position differs from the render's pose",
        ),
        (
            lambda df: df.assign(**{c: df[c].sample(frac=1, random_state=0).to_numpy() for c in ("tx", "ty", "tz")}),
            r"range is not the distance \|t\| of its position",
        ),
        (lambda df: df.assign(range=df["range"] * 1.5), r"range is not the distance \|t\| of its position \(40 such"),
        (lambda df: df.assign(qx=-df["qx"]), r"\['r0', .*'r5'\] are not the 6-D rotation of its quaternion"),
        (
            lambda df: df.assign(
                qw=np.where(df["index"] == 3, 0.0, df["qw"]),
                qx=np.where(df["index"] == 3, 0.0, df["qx"]),
                qy=np.where(df["index"] == 3, 0.0, df["qy"]),
                qz=np.where(df["index"] == 3, 0.0, df["qz"]),
            ),
            r"row 3 \(index 3\): \['qw', 'qx', 'qy', 'qz'\] is not a unit quaternion",
        ),
        (
            lambda df: df.assign(split=np.where(df["index"] == 7, "validation", df["split"])),
            r"row 7 \(index 7\): split is not one of train, test",
        ),
        (
            lambda df: df.assign(image=np.where(df["index"] == 5, "images/1", df["image"])),
            r"image 'images/1' is in both splits",
        ),
        (
            lambda df: df.assign(index=np.where(df["index"] == 2, 2.5, df["index"])),
            r"\(index 2.5\): index is not a whole",
        ),
        (
            lambda df: df.assign(index=np.where(df["index"] == 2, -1, df["index"])),
            r"\(index -1\): index is not a whole",
        ),
        (
            lambda df: df.assign(tz=np.where(df["index"] == 4, -df["tz"], df["tz"]), range=df["range"]),
            r"row 4 \(index 4\): the target is behind the camera",
        ),
    ],
)
def test_bad_or_stale_labels_are_refused_by_every_reader(dataset, edit, message):  # noqa: F811
    """The issue's probes: each was trained on (or exported) with exit 0."""
    df = pd.read_parquet("datasets/labels.parquet")
    edit(df).to_parquet("datasets/labels.parquet")
    with pytest.raises(StageError, match=r"datasets/labels.parquet: .*" + message):
        data.load_split(dataset, "train")


def test_a_shap_store_of_another_detector_split_is_refused():
    from stages.artifacts.readers import SPLIT_KEY, check_shap_split
    from stages.config.params import compose, detect_render_fingerprint
    from stages.config.schema import build

    made, now = build(compose("smoke")), build(compose("smoke", ["shap.seed=5"]))
    attrs = {"model": "robust", SPLIT_KEY: detect_render_fingerprint(made)}
    check_shap_split(attrs, made, "datasets/shap_robust.zarr")
    with pytest.raises(
        StageError,
        match=r"shap_robust.zarr explains another detector split than datasets/"
        r"detect_render of params.yaml \(fingerprint \w+, params give \w+\); re-run "
        r"`rpod shap --model robust`",
    ):
        check_shap_split(attrs, now, "datasets/shap_robust.zarr")
    with pytest.raises(StageError, match=r"fingerprint not recorded"):
        check_shap_split({"model": "standard"}, now, "datasets/shap.zarr")


# --- degenerate data --------------------------------------------------------------------------------------------


def test_a_render_mostly_out_of_view_is_refused(tmp_path):
    """The issue's probe: evaluate.lateral_range=[0, 100000] rendered 18 of 20 black frames, evaluated as 100%."""
    from pipeline.geometry.camera import reference_intrinsics
    from stages.config.build import scene_settings
    from stages.config.schema import build
    from stages.engine.chunks import render_to_store
    from stages.engine.pool import engine_settings

    p = build(params_mod.compose("smoke", ["render.samples=1", "engine.workers=1"]))
    K = reference_intrinsics().scaled(32, 18)
    n = 8
    t = np.tile([0.0, 0.0, 20.0], (n, 1))
    t[2:, 0] = 1e5  # frames 2..7 far to the side: black
    R = np.tile(np.eye(3), (n, 1, 1))
    hint = "check params.yaml evaluate.lateral_range=[0, 100000] (lateral start offsets, m)"
    with pytest.raises(
        StageError,
        match=r"6 of 8 frames of eval_render x have no target in view \(under 0.37% of "
        r"their pixels lit; at most 25% may be\); check params.yaml "
        r"evaluate.lateral_range=\[0, 100000\]",
    ):
        render_to_store(
            str(tmp_path / "a.zarr"),
            K,
            scene_settings(p.render),
            R,
            t,
            2,
            engine_settings(p),
            "eval_render x",
            empty_hint=hint,
        )
    t[1:, 0] = 0.0  # one black frame of eight: kept
    render_to_store(
        str(tmp_path / "b.zarr"),
        K,
        scene_settings(p.render),
        R,
        t,
        2,
        engine_settings(p),
        "eval_render x",
        empty_hint=hint,
    )


def test_a_speed_import_that_is_mostly_black_is_refused(project):  # noqa: F811
    from stages.artifacts import speed as speed_io

    root, use = project
    write_folder(root / "src")
    for k, path in enumerate(sorted((root / "src/synthetic/images").iterdir())[:5]):
        _dark(path, k + 1)
    use(root / "src")
    with pytest.raises(
        StageError,
        match=r"params.yaml render.source: 5 of 9 images imported from .*src have no "
        r"target in view .*check its images and camera.json's distCoeffs",
    ):
        speed_io.import_source(params_mod.load(), root / "store")
    assert not (root / "store").exists()


def test_a_label_split_mostly_out_of_view_is_refused(project):  # noqa: F811
    """Two black test images of three: the import (2 of 9) passes, its test split does not."""
    from stages import label, render

    root, use = project
    write_folder(root / "src")
    for k, name in enumerate(("test000.png", "test001.png")):
        _dark(root / "src/synthetic/images" / name, k + 1)
    use(root / "src")
    render.main(load())
    with pytest.raises(
        StageError,
        match=r"datasets/render: 2 of 3 test frames have no target in view .*the render is "
        r"degenerate",
    ):
        label.main(load())


def test_previews_are_not_repeated():
    from pipeline.geometry.trajectories import preview_picks

    assert preview_picks(np.arange(9), np.arange(9), 1000) == [0, 5, 6, 7, 8]  # an import: one frame each
    seq = np.repeat(np.arange(13), 300)
    assert len(preview_picks(seq, np.arange(len(seq)), 4)) == 4


def test_an_error_names_the_index_that_is_outside(tmp_path):
    """The issue's probe: index -1 was reported as "image index 77"."""
    import zarr

    from pipeline.formats.speed_folder import write_speed
    from pipeline.geometry.camera import Intrinsics

    images = zarr.open_array(
        str(tmp_path / "i.zarr"), mode="w", shape=(78, 9, 16, 3), chunks=(8, 9, 16, 3), dtype="uint8"
    )
    labels = pd.DataFrame(
        {
            "index": [-1, 77],
            "split": ["train", "test"],
            "tx": 0.0,
            "ty": 0.0,
            "tz": 10.0,
            "qw": 1.0,
            "qx": 0.0,
            "qy": 0.0,
            "qz": 0.0,
        }
    )
    with pytest.raises(DataError, match=r"the labels name image -1 but the render store holds 78 \(0..77\)"):
        write_speed(tmp_path / "out", images, labels, Intrinsics(16, 9, 20.0, 20.0, 8.0, 4.5))
