"""`rpod export speed OUT` never deletes what it did not write: a non-empty folder without its marker (or
with files the marker does not list) is refused and left as it was; killed exports' temporary folders are
cleaned up on the next run; the exported files are world-readable."""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import zarr

from pipeline.formats.speed_folder import MARKER, write_speed
from pipeline.geometry.camera import Intrinsics
from pipeline.io.atomic import OWNER
from pipeline.io.errors import DataError

K = Intrinsics(16, 9, 20.0, 20.0, 8.0, 4.5)


def _data(tmp_path: Path, n: int = 6) -> tuple[zarr.Array, pd.DataFrame]:
    """A chunked (n, 9, 16, 3) uint8 image array and labels (index, split, t, q) for it."""
    images = zarr.open_array(
        str(tmp_path / "images.zarr"), mode="w", shape=(n, 9, 16, 3), chunks=(4, 9, 16, 3), dtype="uint8"
    )
    images[:] = np.random.default_rng(0).integers(0, 256, (n, 9, 16, 3), dtype=np.uint8)
    labels = pd.DataFrame(
        {
            "index": np.arange(n),
            "split": ["train"] * (n - 2) + ["test"] * 2,
            "tx": 0.0,
            "ty": 0.0,
            "tz": np.linspace(10, 20, n),
            "qw": 1.0,
            "qx": 0.0,
            "qy": 0.0,
            "qz": 0.0,
        }
    )
    return images, labels


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def _refused_intact(folder: Path, tmp_path: Path, match: str) -> None:
    """write_speed(folder) raises a DataError matching `match` and leaves every file in `folder` as it was."""
    before = _snapshot(folder)
    with pytest.raises(DataError, match=match):
        write_speed(folder, *_data(tmp_path), K)
    assert _snapshot(folder) == before


def test_a_speed_release_is_never_deleted(tmp_path):
    """The issue's probe: a folder with camera.json and other data (a real SPEED+ release) is refused, intact."""
    release = tmp_path / "sp"
    (release / "lightbox/images").mkdir(parents=True)
    (release / "lightbox/images/a.jpg").write_text("x")
    (release / "camera.json").write_text("{}")
    (release / "LICENSE").write_text("CC BY-NC-SA")
    _refused_intact(release, tmp_path, f"not a SPEED folder written before.*no {MARKER}")


def test_rerun_replaces_its_own_export_but_refuses_added_files(tmp_path):
    out = tmp_path / "out"
    write_speed(out, *_data(tmp_path), K)
    listed = json.loads((out / MARKER).read_text())["files"]
    assert "camera.json" in listed and "synthetic/images/img000006.png" in listed
    write_speed(out, *_data(tmp_path, n=5), K)  # an earlier export: replaced whole
    assert not (out / "synthetic/images/img000006.png").exists()
    (out / "synthetic/notes.txt").write_text("mine")
    _refused_intact(out, tmp_path, r"synthetic/notes.txt, which `rpod export speed` did not write")


def test_a_forged_or_broken_marker_is_refused(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "data.bin").write_text("keep")
    (out / MARKER).write_text("not json")
    _refused_intact(out, tmp_path, "not a SPEED folder written before")


def test_an_empty_folder_is_used_and_a_file_refused(tmp_path):
    (tmp_path / "empty").mkdir()
    write_speed(tmp_path / "empty", *_data(tmp_path), K)
    assert (tmp_path / "empty/camera.json").is_file()
    (tmp_path / "file").write_text("x")
    with pytest.raises(DataError, match="exists and is not a folder"):
        write_speed(tmp_path / "file", *_data(tmp_path), K)


def test_exported_files_are_world_readable(tmp_path):
    old = os.umask(0o022)
    try:
        write_speed(tmp_path / "out", *_data(tmp_path), K)
    finally:
        os.umask(old)
    out = tmp_path / "out"
    for p in [out, *out.rglob("*")]:
        mode = stat.S_IMODE(p.stat().st_mode)
        assert mode == (0o755 if p.is_dir() else 0o644), (p, oct(mode))


def _killed_temp(out: Path) -> Path:
    """The temporary folder an export killed mid-write leaves beside `out` (its token inside, its pid gone)."""
    from pipeline.io.atomic import owned_temp

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    made = owned_temp(out)
    stale = made.with_name(made.name.replace(f".{os.getpid()}.", f".{int(dead.stdout)}.", 1))
    made.rename(stale)
    (stale / OWNER).write_text(stale.name)
    (stale / out.name / "synthetic").mkdir(parents=True)
    return stale


def test_a_killed_exports_temporary_folder_is_removed_next_run(tmp_path):
    """A temporary folder of a process that is gone (SIGKILL mid-export) is deleted by the next export."""
    stale = _killed_temp(tmp_path / "out")
    live = tmp_path / f".out.{os.getpid()}.def.tmp"  # a live run's folder is kept
    live.mkdir()
    (live / OWNER).write_text(live.name)
    write_speed(tmp_path / "out", *_data(tmp_path), K)
    assert not stale.exists() and live.exists()


def test_the_users_folders_beside_out_are_never_deleted(tmp_path):
    """The issue's probe: `.OUT.backup.tmp` (no live pid in its name) and `.OUT.old` are the user's, never the
    export's: an export, and a rerun replacing it, leave them as they were; so is a folder named like a killed
    run's temporary one but without its token."""
    mine = [tmp_path / ".out.backup.tmp", tmp_path / ".out.old", tmp_path / ".out.999999999.abc.tmp"]
    for d in mine:
        d.mkdir()
        (d / "keep.txt").write_text("mine")
    write_speed(tmp_path / "out", *_data(tmp_path), K)
    write_speed(tmp_path / "out", *_data(tmp_path, n=5), K)
    assert all((d / "keep.txt").read_text() == "mine" for d in mine)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        [".out.999999999.abc.tmp", ".out.backup.tmp", ".out.old", "images.zarr", "out"]
    )


def test_an_edited_export_is_refused_unless_overwritten(tmp_path):
    out = tmp_path / "out"
    write_speed(out, *_data(tmp_path), K)
    files = json.loads((out / MARKER).read_text())["files"]
    assert len(files["camera.json"]) == 64  # each file's sha256
    (out / "synthetic/train.json").write_text("[]")  # the user's edit
    _refused_intact(
        out,
        tmp_path,
        r"synthetic/train.json was changed since `rpod export speed` wrote it "
        r"\(1 such files.*pass --overwrite",
    )
    write_speed(out, *_data(tmp_path), K, overwrite=True)
    assert len(json.loads((out / "synthetic/train.json").read_text())) == 4


def test_an_older_marker_without_hashes_needs_overwrite(tmp_path):
    out = tmp_path / "out"
    write_speed(out, *_data(tmp_path), K)
    marker = json.loads((out / MARKER).read_text())
    (out / MARKER).write_text(json.dumps({"written_by": "rpod export speed", "files": sorted(marker["files"])}))
    _refused_intact(out, tmp_path, "lists no sha256 of the files.*pass --overwrite")
    write_speed(out, *_data(tmp_path), K, overwrite=True)


def test_a_symlinked_out_is_followed_not_replaced(tmp_path):
    target, link = tmp_path / "disk/export", tmp_path / "out"
    target.mkdir(parents=True)
    link.symlink_to(target)
    for n in (6, 5):  # a first export, then a rerun replacing it
        write_speed(link, *_data(tmp_path, n=n), K)
        assert link.is_symlink() and os.readlink(link) == str(target)
        assert (target / "camera.json").is_file() and len(list((target / "synthetic/images").iterdir())) == n
    assert not [p for p in [*tmp_path.iterdir(), *target.parent.iterdir()] if p.name.startswith(".")]
    dangling = tmp_path / "gone"
    dangling.symlink_to(tmp_path / "nowhere")
    with pytest.raises(DataError, match=r"gone is a symbolic link to .*nowhere, which does not exist"):
        write_speed(dangling, *_data(tmp_path), K)
    assert not (tmp_path / "nowhere").exists()


def test_a_previous_output_is_put_back_after_a_kill_between_the_renames(tmp_path):
    """Killed after moving the old export into its temporary folder, before the new one was renamed in: the next
    run puts the old one back before it deletes that folder."""
    from pipeline.io.atomic import OLD, remove_stale_temps

    out = tmp_path / "out"
    write_speed(out, *_data(tmp_path), K)
    before = _snapshot(out)
    stale = _killed_temp(out)
    out.rename(stale / OLD)
    assert remove_stale_temps(out) == [stale]
    assert _snapshot(out) == before and not stale.exists()
