"""Issue 30, item 2: every artifact pinned to what it was made from. labels.parquet records the render it
labels (train and export refuse labels of another render), pose.pt the labels it was trained on (every stage
loading it checks them); a shared `engine.store` keeps one store per
render fingerprint, which the store itself records and readers check; a refused or failed render leaves
the previous store; a second writer gets one line. Item 6: each array's zarr.json and the root's attributes
are in the checksum manifest."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import tiny
import zarr

from pipeline.io.atomic import OWNER
from pipeline.io.errors import DataError
from pipeline.io.store import create_array, open_zarr, seal_zarr
from stages.config import params as params_mod
from stages.config.params import load
from stages.errors import StageError

TINY = [*tiny.RENDER, "engine.workers=1"]
HOLD = (
    "import sys; from pipeline.io.atomic import exclusive\n"
    "with exclusive(sys.argv[1], 'x'):\n    print('held', flush=True); sys.stdin.read()"
)


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    return tmp_path


def _render(overrides: list[str]) -> dict:
    """`rpod render` in the working folder with the tiny params plus `overrides` -> its meta.json."""
    from stages import render

    params_mod.write_params(params_mod.compose("smoke", TINY + overrides))
    render.main(load())
    return json.loads(Path("datasets/render/meta.json").read_text())


def _images(meta: dict) -> np.ndarray:
    return open_zarr(meta["store"])["images"][:]


# --- labels.parquet names the render it labels ----------------------------------------------------------------


def test_labels_of_another_render_are_refused_by_train_and_export(workdir, capsys):
    """The probe: `rpod render` with another seed, then `rpod train` / `rpod export speed` (before: seed-0 labels
    paired with seed-1 pixels, exit 0)."""
    from typer.testing import CliRunner

    from stages import train
    from stages.cli import app
    from tests.test_training import write_dataset

    write_dataset(workdir)
    seed0 = (workdir / "datasets/labels.parquet").read_bytes()
    write_dataset(workdir, overrides=["seed=1"])  # a render (and labels) of seed 1 ...
    (workdir / "datasets/labels.parquet").write_bytes(seed0)  # ... with the labels of seed 0
    with pytest.raises(
        StageError,
        match=r"labels.parquet labels another render than datasets/render \(render "
        r"fingerprint \w+, datasets/render has \w+\): re-run `rpod label`",
    ):
        train.main(load())
    assert not (workdir / "models/pose.pt").exists()
    result = CliRunner().invoke(app, ["export", "speed", str(workdir / "out")])
    assert result.exit_code == 1 and not (workdir / "out").exists()
    assert "labels another render" in str(result.exception)


def test_a_model_trained_on_other_labels_is_refused(workdir):
    """pose.pt records the label table's hash: relabelling (another test split) after training stops every stage
    that loads the model, instead of attacking or evaluating it on frames it was trained on."""
    import pandas as pd

    from stages import train
    from stages.artifacts.models import load_pose
    from tests.test_training import write_dataset

    write_dataset(workdir)
    train.main(load())
    assert load_pose(load()).meta["epoch"] >= 0
    df = pd.read_parquet("datasets/labels.parquet")
    df.loc[df.index[0], "split"] = "test" if df.loc[df.index[0], "split"] == "train" else "train"
    df.to_parquet("datasets/labels.parquet")
    with pytest.raises(
        StageError,
        match=r"pose checkpoint models/pose.pt was trained on another "
        r"datasets/labels.parquet \(relabelled since\); re-run `rpod train`",
    ):
        load_pose(load())


# --- engine.store: keyed by fingerprint, checked, swapped in whole, locked -------------------------------------


def test_a_shared_store_keeps_one_store_per_render_and_readers_check_it(tmp_path, monkeypatch):
    """Two checkouts sharing engine.store with other params no longer overwrite each other (before: A's poses
    with B's pixels, exit 0); a store holding another render's images is refused."""
    from stages.artifacts.readers import read_render_store

    shared = tmp_path / "shared"
    (tmp_path / "a").mkdir(), (tmp_path / "b").mkdir()
    monkeypatch.chdir(tmp_path / "a")
    a = _render([f"engine.store={shared}"])
    monkeypatch.chdir(tmp_path / "b")
    b = _render([f"engine.store={shared}", "seed=1"])
    assert a["store"] == f"{shared}/render-{a['fingerprint']}.zarr" != b["store"]
    assert sorted(p.name for p in shared.iterdir()) == sorted(  # the stores, their locks gone with the writers
        [f"render-{a['fingerprint']}.zarr", f"render-{b['fingerprint']}.zarr"]
    )
    assert not np.array_equal(_images(a), _images(b))
    monkeypatch.chdir(tmp_path / "a")
    images, _, _ = read_render_store(Path("datasets/render"))
    np.testing.assert_array_equal(images[:], _images(a))  # A still reads its own pixels
    meta = json.loads(Path("datasets/render/meta.json").read_text())
    meta["store"] = b["store"]  # meta.json naming another render's store
    Path("datasets/render/meta.json").write_text(json.dumps(meta))
    with pytest.raises(
        DataError,
        match=r"holds the images of another render \(fingerprint \w+; "
        r"datasets/render/meta.json says \w+\)",
    ):
        read_render_store(Path("datasets/render"))


def test_a_refused_or_failed_render_leaves_the_previous_store(workdir, monkeypatch):
    """Before: a refused render (target covers no pixels) wiped the shared store; now it writes beside it."""
    from stages.engine import chunks

    shared = workdir / "shared"
    before = _render([f"engine.store={shared}"])
    kept = _images(before)
    with pytest.raises(StageError, match="covers no pixels"):
        _render([f"engine.store={shared}", "render.mesh_scale=0.0001"])
    real_run = chunks.RenderWorker.run

    def dies_on_the_second_chunk(self, job):
        if job.lo > 0:
            raise RuntimeError("worker lost")
        return real_run(self, job)

    monkeypatch.setattr(chunks.RenderWorker, "run", dies_on_the_second_chunk)
    with pytest.raises(RuntimeError, match="worker lost"):  # the same params: the same store, half rewritten
        _render([f"engine.store={shared}"])
    np.testing.assert_array_equal(_images(before), kept)
    assert json.loads(Path("datasets/render/meta.json").read_text()) == before
    assert not [p for p in shared.iterdir() if p.name.endswith((".tmp", ".old"))]
    killed = shared / f".render-{before['fingerprint']}.zarr.999999999.abc.tmp"  # a killed render's (no such pid)
    killed.mkdir()
    (killed / OWNER).write_text(killed.name)
    monkeypatch.setattr(chunks.RenderWorker, "run", real_run)
    _render([f"engine.store={shared}"])
    assert not killed.exists()  # removed by the next render


@pytest.mark.parametrize("which", ["checkout", "store"])
def test_a_second_writer_stops_with_one_line(workdir, which):
    """Concurrent renders into one checkout or one shared store: the second gets one line naming the holder."""
    shared = workdir / "shared"
    params_mod.write_params(params_mod.compose("smoke", TINY + [f"engine.store={shared}"]))
    store = f"{shared}/render-{params_mod.render_fingerprint(load())}.zarr"
    lock = workdir / "datasets/.render.lock" if which == "checkout" else Path(f"{store}.lock")
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLD, str(lock)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    try:
        assert holder.stdout.readline().strip() == "held"
        from stages import render

        with pytest.raises(DataError) as err:
            render.main(load())
        what, named = (
            ("datasets/render", "datasets/.render.lock") if which == "checkout" else (f"image store {store}", lock)
        )
        assert str(err.value) == (
            f"{what} is being written by another process (pid {holder.pid}, lock {named}); wait for it to finish"
        )
        assert not (workdir / "datasets/render").exists() and not Path(store).exists()
    finally:
        holder.communicate("")


# --- item 6: the manifest covers zarr.json -----------------------------------------------------------------------


def _sealed(path: Path) -> None:
    group = zarr.open_group(str(path), mode="w")
    group.attrs["eps"] = [0.3]
    create_array(group, "values", data=np.linspace(0, 1, 64, dtype=np.float32).reshape(8, 8), chunks=(4, 8))
    seal_zarr(path)


def test_a_dtype_swapped_in_an_array_zarr_json_is_refused(tmp_path):
    """The probe: float32 -> int32 in shap.zarr's values/zarr.json (before: `rpod detect` exit 0 on garbage)."""
    _sealed(tmp_path / "s.zarr")
    meta_path = tmp_path / "s.zarr/values/zarr.json"
    meta = json.loads(meta_path.read_text())
    meta["data_type"] = "int32"
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(DataError, match=r"values/zarr.json \(dtype, codecs, shape\) changed since it was sealed"):
        open_zarr(tmp_path / "s.zarr")


def test_root_attributes_changed_after_sealing_are_refused(tmp_path):
    """adv.zarr's `eps` (or shap.zarr's model hash) edited in the root zarr.json is named."""
    _sealed(tmp_path / "s.zarr")
    assert open_zarr(tmp_path / "s.zarr").attrs["eps"] == [0.3]
    root = json.loads((tmp_path / "s.zarr/zarr.json").read_text())
    root["attributes"]["eps"] = [0.5]
    (tmp_path / "s.zarr/zarr.json").write_text(json.dumps(root))
    with pytest.raises(DataError, match=r"root group's attributes \(zarr.json\) changed since it was sealed"):
        open_zarr(tmp_path / "s.zarr")
