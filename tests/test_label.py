"""The render and label stages end to end on a tiny dataset, plus their failure modes."""

import json

import numpy as np
import pandas as pd
import pytest

from pipeline.geometry.rotations import quat_to_6d
from pipeline.io.errors import DataError
from stages.config import params as params_mod
from stages.config.params import load
from stages.errors import StageError
from stages.label import build_labels

CONTRACT = [
    "index",
    "image",
    "sequence",
    "frame",
    "tx",
    "ty",
    "tz",
    "qw",
    "qx",
    "qy",
    "qz",
    "r0",
    "r1",
    "r2",
    "r3",
    "r4",
    "r5",
    "range",
    "split",
]


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    """A project folder with a tiny params.yaml (13 x 2 frames at 32x18)."""
    monkeypatch.chdir(tmp_path)
    p = params_mod.compose(
        "smoke",
        [
            "render.width=32",
            "render.height=18",
            "render.frames_per_sequence=2",
            "render.samples=1",
            "render.chunk=4",
            "render.previews=3",
        ],
    )
    params_mod.write_params(p)
    return tmp_path


def test_build_labels_contract_and_split():
    rng = np.random.default_rng(0)
    q = rng.normal(size=(100, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    poses = pd.DataFrame(
        {
            "index": np.arange(100)[::-1],
            "sequence": 0,
            "frame": np.arange(100)[::-1],
            "tx": 0.0,
            "ty": 0.0,
            "tz": rng.uniform(10, 60, 100),
            "qw": q[:, 0],
            "qx": q[:, 1],
            "qy": q[:, 2],
            "qz": q[:, 3],
        }
    )
    poses["range"] = poses.tz
    a = build_labels(poses, 0.2, seed=3)
    assert list(a.columns) == CONTRACT
    assert np.array_equal(a["index"], np.arange(100))  # sorted by row of the zarr array
    assert a.image.iloc[7] == "datasets/render/images.zarr:7"
    assert (a.split == "test").sum() == 20 and set(a.split) == {"train", "test"}
    r6 = a[[f"r{k}" for k in range(6)]].to_numpy()
    assert np.allclose(r6, quat_to_6d(a[["qw", "qx", "qy", "qz"]].to_numpy()))
    assert a.split.equals(build_labels(poses, 0.2, seed=3).split)
    assert not a.split.equals(build_labels(poses, 0.2, seed=4).split)
    with pytest.raises(StageError, match="test_fraction"):
        build_labels(poses, 1.5, seed=0)


@pytest.mark.slow
def test_render_and_label_stages(workdir):
    import zarr

    from stages import label, render

    render.main(load())
    g = zarr.open_group("datasets/render/images.zarr", mode="r")
    images = g["images"]
    assert images.shape == (26, 18, 32, 3) and images.dtype == np.uint8 and images.chunks[0] == 4
    assert np.asarray(images[0]).max() > 0  # something was rendered
    meta = json.loads(open("datasets/render/meta.json").read())
    assert meta["complete"] and meta["frames"] == 26
    assert not {"seconds", "seconds_per_image", "workers"} & set(meta)  # timings: the metrics JSON (stable hash)
    assert json.loads(open("reports/metrics/render.json").read())["seconds_per_image"] > 0
    previews = sorted(p.name for p in (workdir / "reports/figures/previews").glob("*.png"))
    assert len(previews) == 3 and "60m" in previews[0] and "10m" in previews[1]

    label.main(load())
    labels = pd.read_parquet("datasets/labels.parquet")
    # the default share of frames over the Earth or stars: the render's background column carried over
    assert list(labels.columns) == [*CONTRACT, "background"] and len(labels) == 26
    assert set(labels.background) <= {"black", "space", "earth"} and (labels.background == "black").any()
    assert labels.tz.max() > 59 and abs(labels.tz.min() - 10) < 0.01
    assert set(labels.sequence) == set(range(13))
    assert not (workdir / "datasets/speed_labels.json").exists()  # `rpod export speed` writes SPEED+ folders
    card = open("reports/dataset.md").read()
    assert "| 26 " in card and "figures/previews/" in card
    assert "Rendering took" not in card and "seconds_per_image" in card  # no wall-clock time in a report
    assert "Pixel aspect fy/fx = 1 (`camera.fy`)" in card  # the default camera has square pixels


@pytest.mark.slow
def test_interrupted_render_leaves_no_dataset(workdir, monkeypatch):
    from pipeline.render import scene
    from stages import render

    calls = {"n": 0}
    original = scene.Renderer.render_with_alpha

    def flaky(self, R, t, background=None):
        calls["n"] += 1
        if calls["n"] > 5:
            raise KeyboardInterrupt
        return original(self, R, t, background)

    monkeypatch.setattr(scene.Renderer, "render_with_alpha", flaky)
    with pytest.raises(KeyboardInterrupt):
        render.main(load())
    assert not (workdir / "datasets/render").exists()
    # the temporary folder and the writers' lock file (datasets/.render.lock) are gone too
    assert not list((workdir / "datasets").glob(".render*"))

    # A hard kill (no clean-up) leaves a temporary folder (its token inside, its pid gone): never trusted, and
    # removed by the next run; a folder named alike without the token is not a run's and stays.
    from pipeline.io.atomic import OWNER

    leftover, foreign = workdir / "datasets" / ".render.999999999.abc.tmp", workdir / "datasets" / ".render.killed.tmp"
    for d in (leftover, foreign):
        (d / "render" / "images.zarr").mkdir(parents=True)
    (leftover / OWNER).write_text(leftover.name)
    monkeypatch.setattr(scene.Renderer, "render_with_alpha", original)
    render.main(load())
    assert not leftover.exists() and foreign.exists() and (workdir / "datasets/render/meta.json").exists()


@pytest.mark.slow
def test_corrupt_or_missing_store_is_refused(workdir):
    import shutil

    from stages import label, render

    with pytest.raises(DataError, match="not found"):
        label.main(load())
    render.main(load())
    shutil.rmtree("datasets/render/images.zarr/images")
    with pytest.raises(DataError, match="incomplete|corrupt|inconsistent|missing"):
        label.main(load())
    render.main(load())
    meta = json.loads(open("datasets/render/meta.json").read())
    meta["frames"] = 999
    open("datasets/render/meta.json", "w").write(json.dumps(meta))
    with pytest.raises(DataError, match="inconsistent"):
        label.main(load())


def test_bad_params(workdir):
    from stages import render

    for override, msg in [
        ("render.width=0", "positive"),
        ("render.pointing_jitter_deg=30", "out of view"),
        ("render.mesh=/nope/sat.obj", "not found"),
    ]:
        params_mod.write_params(params_mod.compose("smoke", [override]))
        with pytest.raises((StageError, ValueError), match=msg):
            render.main(load())
        assert not (workdir / "datasets/render").exists()
    with pytest.raises(params_mod.ParamsError, match="unknown profile"):
        params_mod.compose("nosuchprofile")
