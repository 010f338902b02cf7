"""Fault injection: each probe ends in one clear error (DataError/StageError/ValueError naming the file or
parameter) and leaves every downstream artifact as it was."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import zarr

from pipeline.io.atomic import atomic_dir
from pipeline.io.errors import DataError
from pipeline.io.store import create_array, open_zarr
from stages.config import params as params_mod
from stages.config.params import load
from stages.errors import StageError


def _store(path: Path, n: int = 40) -> np.ndarray:
    """A sealed image store like datasets/render/images.zarr: (n, 9, 16, 3) uint8 in chunks of 8."""
    images = np.random.default_rng(0).integers(1, 255, (n, 9, 16, 3), dtype=np.uint8)
    with atomic_dir(path) as tmp:
        create_array(zarr.open_group(str(tmp), mode="w"), "images", data=images, chunks=(8, 9, 16, 3))
    return images


def test_sealed_store_reads_back(tmp_path):
    images = _store(tmp_path / "images.zarr")
    np.testing.assert_array_equal(open_zarr(tmp_path / "images.zarr")["images"][:], images)


def test_missing_chunk_is_named(tmp_path):
    _store(tmp_path / "images.zarr")
    (tmp_path / "images.zarr/images/c/2/0/0/0").unlink()
    with pytest.raises(DataError, match=r"images.zarr is missing chunk images/c/2/0/0/0"):
        open_zarr(tmp_path / "images.zarr", "image store")


@pytest.mark.parametrize("byte", [0, -5, -2, "middle"])
def test_flipped_bit_is_named(tmp_path, byte):
    _store(tmp_path / "images.zarr")
    chunk = tmp_path / "images.zarr/images/c/1/0/0/0"
    raw = bytearray(chunk.read_bytes())
    raw[len(raw) // 2 if byte == "middle" else byte] ^= 0x10
    chunk.write_bytes(bytes(raw))
    with pytest.raises(DataError, match=r"chunk images/c/1/0/0/0 fails its crc32c checksum"):
        open_zarr(tmp_path / "images.zarr", "image store")


def test_a_chunk_swapped_in_from_elsewhere_is_named(tmp_path):
    """Each chunk's manifest entry is its own payload's checksum, so an intact chunk of other data is refused."""
    _store(tmp_path / "images.zarr")
    chunks = tmp_path / "images.zarr/images/c"
    entries = open_zarr(tmp_path / "images.zarr").attrs["rpodguard_manifest"]["arrays"]["images"]["crc32c"]
    assert len(set(entries.values())) == len(entries)  # no two chunks share a checksum
    (chunks / "1/0/0/0").write_bytes((chunks / "2/0/0/0").read_bytes())
    with pytest.raises(DataError, match=r"chunk images/c/1/0/0/0 fails its crc32c checksum"):
        open_zarr(tmp_path / "images.zarr", "image store")


def test_a_store_of_an_older_manifest_format_is_named(tmp_path):
    import json

    _store(tmp_path / "images.zarr")
    meta = json.loads((tmp_path / "images.zarr/zarr.json").read_text())
    meta["attributes"]["rpodguard_manifest"]["format"] = "rpodguard-zarr-manifest/1"
    (tmp_path / "images.zarr/zarr.json").write_text(json.dumps(meta))
    with pytest.raises(
        DataError, match=r"written by an older rpodguard \(checksum manifest rpodguard-zarr-manifest/1\)"
    ):
        open_zarr(tmp_path / "images.zarr")


def test_unsealed_or_extended_store_is_refused(tmp_path):
    zarr.open_group(str(tmp_path / "raw.zarr"), mode="w").create_array("x", data=np.arange(4))
    with pytest.raises(DataError, match="has no checksum manifest"):
        open_zarr(tmp_path / "raw.zarr")
    _store(tmp_path / "images.zarr")
    create_array(zarr.open_group(str(tmp_path / "images.zarr"), mode="a"), "extra", data=np.arange(4))
    with pytest.raises(DataError, match=r"arrays \['extra'\] differ from its checksum manifest"):
        open_zarr(tmp_path / "images.zarr")


def test_a_failed_write_leaves_the_old_store(tmp_path):
    images = _store(tmp_path / "images.zarr")
    with pytest.raises(RuntimeError, match="never written"):
        with atomic_dir(tmp_path / "images.zarr") as tmp:  # a writer that fills only half the array
            create_array(
                zarr.open_group(str(tmp), mode="w"), "images", shape=(40, 9, 16, 3), chunks=(8, 9, 16, 3), dtype="uint8"
            )[:16] = 0
    np.testing.assert_array_equal(open_zarr(tmp_path / "images.zarr")["images"][:], images)
    assert [p.name for p in tmp_path.iterdir()] == ["images.zarr"]


# --- training: divergence, non-finite labels, killed runs --------------------------------------------------

TRAIN_OUTPUTS = [
    "models/pose.pt",
    "reports/metrics/train.json",
    "reports/pose.md",
    "dvclive/train/plots/metrics/val_pos_m.tsv",
]


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A tiny dataset (tests/test_training.py) and one finished `rpod train` on it."""
    import os

    import torch

    from stages.train import main
    from tests.test_training import write_dataset

    root = tmp_path_factory.mktemp("trained")
    write_dataset(root)
    torch.set_num_threads(1)
    cwd = os.getcwd()
    os.chdir(root)
    try:
        main(load())
    finally:
        os.chdir(cwd)
    return root


@pytest.fixture
def run_dir(trained, tmp_path, monkeypatch):
    """A copy of `trained` as the working directory; returns the bytes of the train outputs."""
    import shutil

    shutil.copytree(trained, tmp_path / "run")
    monkeypatch.chdir(tmp_path / "run")
    return {p: Path(p).read_bytes() for p in TRAIN_OUTPUTS}


def _unchanged(before: dict[str, bytes]) -> None:
    assert {p: Path(p).read_bytes() for p in before} == before
    assert not [p for p in Path(".").rglob("*.tmp")], "temporary files left behind"


def _set_params(**overrides: object) -> None:
    from stages.config import params as params_mod

    p = dataclasses.asdict(params_mod.load())
    for key, value in overrides.items():
        section, name = key.split("__")
        p[section][name] = value
    params_mod.write_params(p)


def test_diverging_learning_rate_is_refused_and_keeps_the_old_model(run_dir):
    from stages.train import main

    _set_params(train__lr_base=10.0, train__lr_max=10.0)  # the largest learning rate params accept
    with pytest.raises(
        StageError, match=r"(training diverged: loss (nan|inf)|no epoch of \d+ improved).*lower train.lr_base"
    ):
        main(load())
    _unchanged(run_dir)


@pytest.mark.parametrize("value", [np.inf, np.nan])
def test_non_finite_label_is_refused(run_dir, value):
    import pandas as pd

    from stages.train import main

    df = pd.read_parquet("datasets/labels.parquet")
    df.loc[5, "tz"] = value
    df.to_parquet("datasets/labels.parquet")
    with pytest.raises(StageError, match=r"NaN or infinite labels in columns \{'tz': 1\}"):
        main(load())
    _unchanged(run_dir)


def test_pose_dataset_refuses_non_finite_targets():
    from pipeline.pose.train import PoseDataset

    targets = np.zeros((4, 9), np.float32)
    targets[2, 4] = np.inf
    with pytest.raises(ValueError, match=r"1 targets are NaN or infinite \(first: row 2\)"):
        PoseDataset(np.zeros((4, 2, 2, 3), np.uint8), targets)


def test_killed_train_leaves_old_model_and_metrics(run_dir):
    import os
    import signal
    import subprocess
    import sys

    _set_params(train__epochs=50, train__max_minutes=None)
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parent.parent), "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-c", "from stages.config.params import load; from stages.train import main; main(load())"],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    for line in proc.stdout:  # wait for the second finished epoch (the first was a new best)
        if line.startswith("epoch   2"):
            break
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL
    assert {p: Path(p).read_bytes() for p in run_dir} == run_dir


def test_checkpoint_with_nan_weights_is_refused(run_dir):
    import torch

    from pipeline.formats.models import read_pose

    ckpt = torch.load("models/pose.pt", weights_only=True)
    next(v for v in ckpt["model"].values() if v.is_floating_point()).view(-1)[0] = float("nan")
    torch.save(ckpt, "models/pose.pt")
    with pytest.raises(DataError, match="holds non-finite weights"):
        read_pose("models/pose.pt")


@pytest.mark.parametrize(
    "setting, message",
    [
        ({"epochs": 0}, "epochs=0"),
        ({"hidden": 0}, "hidden=0"),
        ({"dense": [0]}, r"dense\[0\]=0"),
        ({"lr": 1e30}, "training diverged|improved"),
    ],
)
def test_lstm_detector_refuses_zero_sizes_and_divergence(setting, message):
    from pipeline.detectors.lstm import LSTMConfig, train_lstm

    rng = np.random.default_rng(0)
    x, y = rng.normal(size=(40, 9, 8)).astype(np.float32), np.arange(40) % 2
    cfg = LSTMConfig(n_rows=9, n_features=8, hidden=setting.get("hidden", 4), dense=setting.get("dense", [4]))
    with pytest.raises(ValueError, match=message):
        train_lstm(
            x[:30],
            y[:30],
            x[30:],
            y[30:],
            cfg,
            epochs=setting.get("epochs", 3),
            patience=2,
            batch_size=8,
            lr=setting.get("lr", 1.0),
        )


# --- the CLI: one line, exit status 1; --debug for the traceback --------------------------------------------


def _rpod(monkeypatch, capsys, *args: str) -> tuple[int, str]:
    import sys

    from stages import cli

    monkeypatch.setattr(sys, "argv", ["rpod", *args])
    monkeypatch.setitem(cli._DEBUG, "on", False)
    with pytest.raises(SystemExit) as exit_info:
        cli.main()
    return exit_info.value.code, capsys.readouterr().err


def test_cli_prints_one_line_for_known_errors(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    code, err = _rpod(monkeypatch, capsys, "params", "smoke", "-S", "nosuchkey=1")  # refused before Hydra
    assert code == 1 and err.count("\n") == 1 and err.startswith("error: ") and "nosuchkey" in err
    code, err = _rpod(monkeypatch, capsys, "train")  # no params.yaml
    assert code == 1 and err == "error: params.yaml not found: run `rpod params default` (or another profile) first\n"
    code, err = _rpod(monkeypatch, capsys, "params", "smoke", "-S", "train=1")  # refused when composed
    assert code == 1 and err == "error: params.yaml: 'train' must be a section of parameters, got 1\n"
    assert not Path("params.yaml").exists()
    params_mod.write_params({**params_mod.compose("smoke"), "train": 1})  # e.g. edited by hand
    code, err = _rpod(monkeypatch, capsys, "label")  # params.yaml with a section replaced by a number
    assert code == 1 and err == "error: params.yaml: 'train' must be a section of parameters, got 1\n"
    assert not Path("datasets").exists()


def test_cli_debug_shows_the_traceback(tmp_path, monkeypatch):
    import sys

    from stages import cli

    monkeypatch.chdir(tmp_path)
    monkeypatch.setitem(cli._DEBUG, "on", False)  # restored after the test: --debug sets it for the process
    monkeypatch.setattr(sys, "argv", ["rpod", "--debug", "train"])
    with pytest.raises(ValueError, match="params.yaml not found"):
        cli.main()


def test_cli_reports_a_corrupt_chunk_in_one_line(trained, tmp_path, monkeypatch, capsys):
    import shutil

    shutil.copytree(trained, tmp_path / "run")
    monkeypatch.chdir(tmp_path / "run")
    Path("datasets/render/images.zarr/images/c/1/0/0/0").unlink()
    before = {p: Path(p).read_bytes() for p in TRAIN_OUTPUTS}
    code, err = _rpod(monkeypatch, capsys, "train")
    assert code == 1 and err == (
        "error: image store datasets/render/images.zarr is missing chunk images/c/1/0/0/0; "
        "delete it and re-run the stage that writes it\n"
    )
    _unchanged(before)


# --- the lab loader ---------------------------------------------------------------------------------------

BODIES = {"camera": "camera", "target": "target"}


@pytest.fixture
def recording(tmp_path) -> Path:
    """A 6-frame lab recording (pipeline.formats.recordings.write_recording layout) with a bright target on black."""
    from pipeline.evaluation.lab import synthetic_recording
    from pipeline.formats.recordings import write_recording

    rec = synthetic_recording(1.6, 1.0, 6, 30.0, 120.0, np.array([1.0, 0, 0, 0]))
    images = np.zeros((6, 36, 64, 3), np.uint8)
    images[:, 10:26, 20:44] = 200
    write_recording(tmp_path / "seq", rec.camera, rec.mocap, images, None)
    return tmp_path / "seq"


def _read(folder: Path, **kwargs):
    from pipeline.formats.recordings import read_recording

    return read_recording(folder, 32, 18, BODIES, "nearest", 0.01, 0.08, **kwargs)


def _edit_csv(path: Path, fn) -> None:
    import pandas as pd

    fn(pd.read_csv(path)).to_csv(path, index=False)


def test_lab_recording_reads(recording):
    assert _read(recording)["images"].shape == (6, 18, 32, 3)


@pytest.mark.parametrize("name", ["../../secret.png", "/etc/hostname", "sub/../../camera.csv"])
def test_lab_image_path_escape_is_refused(recording, name):
    import shutil

    shutil.copy(recording / "images/000000.png", recording.parent / "secret.png")
    _edit_csv(recording / "camera.csv", lambda df: df.assign(image=[name] + [f"{i:06d}.png" for i in range(1, 6)]))
    with pytest.raises(DataError, match=r"camera.csv line 2: image .* lies outside the recording folder"):
        _read(recording)


def test_lab_fifo_is_refused_without_hanging(recording):
    import os

    (recording / "images/000002.png").unlink()
    os.mkfifo(recording / "images/000002.png")
    with pytest.raises(DataError, match=r"camera.csv line 4: .*000002.png is not a regular file"):
        _read(recording)
    os.rename(recording / "images/000002.png", recording / "camera.csv.fifo")
    os.replace(recording / "camera.csv.fifo", recording / "camera.csv")
    with pytest.raises(DataError, match=r"camera.csv is not a regular file"):
        _read(recording)


def test_lab_oversized_image_is_refused_from_its_header(recording):
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    # a 16000x9000 PNG header with no pixel data: decoding it would allocate 432 MB
    ihdr = struct.pack(">IIBBBBB", 16000, 9000, 8, 2, 0, 0, 0)
    (recording / "images/000001.png").write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IEND", b""))
    with pytest.raises(DataError, match=r"000001.png is 16000x9000 = 144000000 pixels, above lab.max_image_pixels"):
        _read(recording)


@pytest.mark.parametrize(
    "edit, message",
    [
        (
            lambda df: df.assign(x=df["x"].where(df.index != 3, np.inf)),
            r"mocap.csv line 5: column 'x' is not finite \(inf\)",
        ),
        (lambda df: df.assign(z=df["z"].where(df.index != 4, "nan")), r"mocap.csv line 6: column 'z' is not a number"),
    ],
)
def test_lab_non_finite_mocap_is_refused(recording, edit, message):
    _edit_csv(recording / "mocap.csv", edit)
    with pytest.raises(DataError, match=message):
        _read(recording)


def test_lab_duplicate_frame_is_refused(recording):
    _edit_csv(recording / "camera.csv", lambda df: df.assign(frame=[0, 1, 2, 2, 4, 5]))
    with pytest.raises(DataError, match=r"camera.csv line 5: frame 2 already appears on line 4"):
        _read(recording)


def test_lab_target_behind_the_camera_is_refused(recording):
    def mirror(df):  # the target body moved to the other side of the camera, along the viewing axis
        cam = df[df.body == "camera"].iloc[0]
        tgt = df.body == "target"
        df.loc[tgt, "x"] = 2 * cam["x"] - df.loc[tgt, "x"]
        return df

    _edit_csv(recording / "mocap.csv", mirror)
    with pytest.raises(DataError, match=r"camera.csv line 2: the target is behind the camera"):
        _read(recording)


def test_lab_frames_without_target_are_refused(recording):
    import cv2

    cv2.imwrite(str(recording / "images/000003.png"), np.zeros((36, 64, 3), np.uint8))
    with pytest.raises(DataError, match=r"1 of 6 frames have no target pixels .*first: frame index 3"):
        _read(recording)
    assert _read(recording, empty_tolerance=0.2)["images"][3].max() == 0  # within a tolerance of 20%


def test_lab_nan_image_name_is_refused(recording):
    _edit_csv(recording / "camera.csv", lambda df: df.assign(image=[f"{i:06d}.png" for i in range(5)] + [np.nan]))
    with pytest.raises(DataError, match=r"camera.csv line 7: column 'image' is empty or not a file name \(nan\)"):
        _read(recording)


# --- stale inputs: render fingerprints, wrong mesh scale ------------------------------------------------------


def test_train_refuses_a_stale_render(run_dir):
    from stages.train import main

    _set_params(render__frames_per_sequence=7)
    with pytest.raises(
        ValueError, match=r"datasets/render/meta.json was rendered with other seed/camera/render params"
    ):
        main(load())
    _unchanged(run_dir)


@pytest.mark.slow
def test_label_refuses_a_stale_render_and_render_refuses_an_invisible_target(tmp_path, monkeypatch):
    from stages import label, render
    from stages.config import params as params_mod

    monkeypatch.chdir(tmp_path)
    tiny = ["render.width=32", "render.height=18", "render.frames_per_sequence=2", "render.samples=1", "render.chunk=4"]
    params_mod.write_params(params_mod.compose("smoke", tiny))
    render.main(load())
    rendered = {p: p.read_bytes() for p in Path("datasets/render").rglob("*") if p.is_file()}

    params_mod.write_params(params_mod.compose("smoke", [*tiny, "render.frames_per_sequence=3"]))
    with pytest.raises(ValueError, match="rendered with other seed/camera/render params"):
        label.main(load())
    assert not Path("datasets/labels.parquet").exists()

    # a mesh in millimetres declared as metres: 1000x too small, nothing visible at 60 m
    Path("cube.obj").write_text(
        "".join(f"v {x} {y} {z}\n" for x in (-1, 1) for y in (-1, 1) for z in (-1, 1))
        + "f 1 2 4 3\nf 5 6 8 7\nf 1 2 6 5\nf 3 4 8 7\nf 1 3 7 5\nf 2 4 8 6\n"
    )
    params_mod.write_params(params_mod.compose("smoke", [*tiny, "render.mesh=cube.obj", "render.mesh_scale=0.001"]))
    with pytest.raises(StageError, match="the target covers no pixels in the first 4 frames"):
        render.main(load())
    assert {p: p.read_bytes() for p in Path("datasets/render").rglob("*") if p.is_file()} == rendered
    assert sorted(p.name for p in Path("datasets").iterdir()) == ["render"]  # no temporary, no lock left


def test_temporary_folders_of_live_runs_are_kept(tmp_path):
    import os

    from pipeline.io.atomic import OWNER, remove_stale_temps

    live = tmp_path / f".render.{os.getpid()}.abc.tmp"
    dead = tmp_path / ".render.999999999.def.tmp"
    foreign = tmp_path / ".render.999999999.ghi.tmp"  # no token inside: not a run's, never deleted
    for d in (live, dead, foreign):
        d.mkdir()
    for d in (live, dead):
        (d / OWNER).write_text(d.name)
    assert remove_stale_temps(tmp_path / "render") == [dead]
    assert live.is_dir() and foreign.is_dir() and not dead.exists()


def test_flipped_bit_in_a_parquet_table_is_refused(tmp_path):
    import pandas as pd

    from pipeline.io.tables import read_parquet, write_parquet

    df = pd.DataFrame({"tz": np.random.default_rng(0).uniform(10, 60, 2000), "index": np.arange(2000)})
    write_parquet(df, tmp_path / "labels.parquet")
    pd.testing.assert_frame_equal(read_parquet(tmp_path / "labels.parquet"), df)
    raw = bytearray((tmp_path / "labels.parquet").read_bytes())
    raw[len(raw) // 4] ^= 0x10  # inside the first column's data page
    (tmp_path / "labels.parquet").write_bytes(bytes(raw))
    with pytest.raises(DataError, match=r"labels.parquet is unreadable .*(checksum|CRC)"):
        read_parquet(tmp_path / "labels.parquet", "label table")
