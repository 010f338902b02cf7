"""No input hangs: every reader of an input file (JSON, YAML, CSV, parquet, zarr metadata and chunks, images) opens it
through `pipeline.io.files.open_regular`, so a FIFO (or another special file) in its place is one DataError naming
it, at once, instead of a read that waits for ever; and a guidance grid projected to run for days is refused before
its first run, naming guidance.max_steps."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd
import pytest
import torch
import zarr
from test_faults_inputs import _deadline

from pipeline.io.errors import DataError
from pipeline.io.store import create_array, seal_zarr

FIFO = r"is not a regular file \(a FIFO\)"


def _fifo(path: Path) -> Path:
    """Replace `path` (made first, so the reader gets that far) by a FIFO no one writes to."""
    if path.is_dir():
        import shutil

        shutil.rmtree(path)
    else:
        path.unlink(missing_ok=True)
    os.mkfifo(path)
    return path


def _store(path: Path) -> Path:
    group = zarr.open_group(str(path), mode="w")
    create_array(group, "values", shape=(4, 3), chunks=(2, 3), dtype="float32")[:] = np.ones((4, 3), np.float32)
    seal_zarr(path)
    return path


def _params(tmp: Path) -> Callable[[], object]:
    from stages.config import params as params_mod

    params_mod.write_params(params_mod.compose("smoke"), tmp / "params.yaml")
    _fifo(tmp / "params.yaml")
    return lambda: params_mod.load(tmp / "params.yaml")


def _defense(tmp: Path) -> Callable[[], object]:
    from pipeline.formats.defense import read_defense

    _fifo(tmp / "defense.json")
    return lambda: read_defense(tmp / "defense.json", "0" * 16, 0.5)


def _meta(tmp: Path) -> Callable[[], object]:
    from pipeline.formats.renders import read_renders

    (tmp / "render").mkdir()
    _fifo(tmp / "render/meta.json")
    return lambda: read_renders(tmp / "render", "render output", "re-run `rpod render`")


def _labels(tmp: Path) -> Callable[[], object]:
    from pipeline.io.tables import read_parquet

    _fifo(tmp / "labels.parquet")
    return lambda: read_parquet(tmp / "labels.parquet", "label table")


def _camera(tmp: Path) -> Callable[[], object]:
    from rpodguard.camera import read_camera

    _fifo(tmp / "cam.json")
    return lambda: read_camera(tmp / "cam.json")


def _manifest(tmp: Path) -> Callable[[], object]:
    from pipeline.formats.bundle import check_bundle

    _fifo(tmp / "manifest.json")
    return lambda: check_bundle(tmp)


def _speed_camera(tmp: Path) -> Callable[[], object]:
    from pipeline.formats.speed_folder import read_camera

    _fifo(tmp / "camera.json")
    return lambda: read_camera(tmp, speed_layout=True)  # a SPEED folder without camera.json has a default one


def _speed_labels(tmp: Path) -> Callable[[], object]:
    from pipeline.formats.speed_folder import read_labels
    from stages.artifacts.speed import labels_file

    (tmp / "synthetic").mkdir()
    _fifo(tmp / "synthetic/train.json")
    return lambda: read_labels(labels_file(tmp, ("synthetic/train.json",), None, "training"))


def _speed_image(tmp: Path) -> Callable[[], object]:
    from pipeline.formats.speed_folder import image_header

    _fifo(tmp / "img000001.jpg")
    return lambda: image_header(tmp / "img000001.jpg")


def _zarr_json(tmp: Path) -> Callable[[], object]:
    from pipeline.io.store import open_zarr

    _fifo(_store(tmp / "shap.zarr") / "values/zarr.json")
    return lambda: open_zarr(tmp / "shap.zarr", "SHAP store")


def _root_zarr_json(tmp: Path) -> Callable[[], object]:
    from pipeline.io.store import open_zarr

    _fifo(_store(tmp / "shap.zarr") / "zarr.json")
    return lambda: open_zarr(tmp / "shap.zarr", "SHAP store")


def _chunk(tmp: Path) -> Callable[[], object]:
    from pipeline.io.store import open_zarr

    _fifo(_store(tmp / "shap.zarr") / "values/c/1/0")
    return lambda: open_zarr(tmp / "shap.zarr", "SHAP store")


def _motion(tmp: Path) -> Callable[[], object]:
    from rpodguard.sequence import read_motion

    _fifo(tmp / "motion.csv")
    return lambda: read_motion(tmp / "motion.csv", 3)


def _file_hash(tmp: Path) -> Callable[[], object]:
    from pipeline.io.atomic import file_hash

    _fifo(tmp / "pose.pt")
    return lambda: file_hash(tmp / "pose.pt")


READERS = {
    "params.yaml": _params,
    "defense.json": _defense,
    "meta.json": _meta,
    "labels.parquet": _labels,
    "--camera JSON": _camera,
    "bundle manifest.json": _manifest,
    "SPEED camera.json": _speed_camera,
    "SPEED train.json": _speed_labels,
    "SPEED image": _speed_image,
    "an array's zarr.json": _zarr_json,
    "the root zarr.json": _root_zarr_json,
    "a zarr chunk": _chunk,
    "motion CSV": _motion,
    "a hashed model file": _file_hash,
}


@pytest.mark.parametrize("reader", READERS)
def test_a_fifo_in_place_of_an_input_is_refused_at_once(tmp_path, reader):
    read = READERS[reader](tmp_path)
    with _deadline(10):
        with pytest.raises(DataError, match=FIFO) as e:
            read()
    assert "\n" not in str(e.value)


def test_open_regular_names_other_special_files(tmp_path):
    from pipeline.io.files import open_regular, read_bytes

    (tmp_path / "meta.json").mkdir()
    with pytest.raises(DataError, match=r"meta.json is not a regular file \(a folder\)"):
        open_regular(tmp_path / "meta.json")
    with pytest.raises(DataError, match=r"/dev/null is not a regular file \(a character device\)"):
        read_bytes("/dev/null")
    with pytest.raises(DataError, match=r"label table .*x.parquet not found"):
        open_regular(tmp_path / "x.parquet", what="label table")
    (tmp_path / "real.json").write_text("{}")
    (tmp_path / "link.json").symlink_to(tmp_path / "real.json")  # a link to a regular file is read
    assert read_bytes(tmp_path / "link.json") == b"{}"


def test_a_parquet_table_read_through_open_regular_keeps_its_attrs(tmp_path):
    from pipeline.io.tables import read_parquet, write_parquet

    df = pd.DataFrame({"index": np.arange(3), "tz": [10.0, 20.0, 30.0]})
    df.attrs["render_fingerprint"] = "abc"
    write_parquet(df, tmp_path / "t.parquet")
    back = read_parquet(tmp_path / "t.parquet")
    pd.testing.assert_frame_equal(back, df)
    assert back.attrs["render_fingerprint"] == "abc"


class _SlowChain:
    """A chain whose forward takes `seconds` (what check_duration times)."""

    def __init__(self, seconds: float):
        self.model, self.seconds = torch.nn.Linear(1, 1), seconds

    def __call__(self, x):
        time.sleep(self.seconds)
        return type("Out", (), {"prob": torch.zeros(1)})()


@pytest.mark.parametrize("max_steps, refused", [(10_000_000, True), (100, False)])
def test_a_guidance_grid_projected_beyond_the_horizon_is_refused_before_it_starts(max_steps, refused):
    from pipeline.guidance.grid import GridPlan
    from stages import guidance
    from stages.config.build import intrinsics
    from stages.config.params import compose
    from stages.config.schema import build
    from stages.errors import StageError

    p = build(compose("smoke", [f"guidance.max_steps={max_steps}"]))
    settings, grid = guidance._plan(p.guidance)
    plan = GridPlan(
        settings, tuple(grid), p.guidance.slack_steps, tuple(p.guidance.dynamics), tuple(p.guidance.defenses)
    )
    check = lambda: guidance.check_duration(plan, _SlowChain(0.005), intrinsics(p))  # noqa: E731
    if not refused:
        check()
        return
    with pytest.raises(
        StageError,
        match=r"guidance.max_steps=10000000: the no-attack runs alone fly [\d,]+ "
        r"closed-loop steps, about [\d,]+ h at 5\.\d+ ms per step on this machine "
        r"\(more than 24 h\)",
    ):
        check()


def test_read_json_names_invalid_utf8(tmp_path):
    from pipeline.io.atomic import read_json

    (tmp_path / "meta.json").write_bytes(b"\xff\xfe{}")
    with pytest.raises(DataError, match="meta.json is not valid JSON"):
        read_json(tmp_path / "meta.json")
    (tmp_path / "ok.json").write_text(json.dumps({"a": 1}))
    assert read_json(tmp_path / "ok.json") == {"a": 1}
