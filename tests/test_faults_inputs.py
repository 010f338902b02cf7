"""Smaller input faults: a non-finite number in a checkpoint (a detector's threshold) is refused on load, a FIFO
named as a checkpoint is refused instead of blocking for ever, and the lab loader refuses a mocap quaternion
that is not unit length (as the SPEED importer does) instead of normalising it."""

from __future__ import annotations

import contextlib
import os
import signal
from typing import Iterator

import numpy as np
import pytest
import torch
from test_lab import _hand_made

from pipeline.evaluation.lab import LabDataError, match_frames
from pipeline.formats.models import DETECTOR_FORMAT
from pipeline.io.atomic import file_hash
from pipeline.io.checkpoints import load_torch, save_torch
from pipeline.io.errors import DataError


@contextlib.contextmanager
def _deadline(seconds: int) -> Iterator[None]:
    """Fail instead of hanging: SIGALRM interrupts a blocking open() after `seconds`."""

    def stop(*_: object) -> None:
        raise TimeoutError(f"still blocked after {seconds} s")

    old = signal.signal(signal.SIGALRM, stop)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


@pytest.mark.parametrize("threshold", [float("nan"), float("inf")])
def test_a_non_finite_threshold_is_refused_on_load(tmp_path, threshold):
    path = tmp_path / "detector.pt"
    save_torch(
        path, {"format": DETECTOR_FORMAT, "threshold": threshold, "weights": torch.zeros(3), "sizes": [1.0, 2.0]}
    )
    with pytest.raises(DataError, match=r"detector.pt holds non-finite weights or values \(threshold\); re-run"):
        load_torch(path, DETECTOR_FORMAT, "re-run `rpod detect`")
    save_torch(
        path, {"format": DETECTOR_FORMAT, "threshold": 0.5, "weights": torch.zeros(3), "sizes": [1.0, float("nan")]}
    )
    with pytest.raises(DataError, match=r"\(sizes.1\)"):
        load_torch(path, DETECTOR_FORMAT, "re-run `rpod detect`")


def test_a_fifo_as_checkpoint_is_refused_not_waited_on(tmp_path):
    fifo = tmp_path / "pose.pt"
    os.mkfifo(fifo)
    with _deadline(10):
        with pytest.raises(DataError, match=r"checkpoint .*pose.pt is not a regular file; re-run"):
            load_torch(fifo, "rpodguard-pose", "re-run `rpod train`")
        with pytest.raises(DataError, match=r"pose.pt is not a regular file"):
            file_hash(fifo)


@pytest.mark.parametrize("scale, ok", [(3.0, False), (0.5, False), (1.0 + 5e-4, True)])
def test_the_lab_loader_refuses_non_unit_quaternions(scale, ok):
    camera, mocap = _hand_made()
    quat = ["qw", "qx", "qy", "qz"]
    mocap.loc[5, quat] = mocap.loc[5, quat].to_numpy(dtype=float) * scale  # body 'tgt', data row 5
    if ok:  # rounding noise: normalised
        match_frames(camera, mocap, "cam", "tgt", "nearest", max_gap=0.005)
        return
    with pytest.raises(
        LabDataError,
        match=rf"mocap.csv line 7: body 'tgt' has a quaternion of norm "
        rf"{np.float64(scale):g}, not a unit quaternion",
    ):
        match_frames(camera, mocap, "cam", "tgt", "nearest", max_gap=0.005)


def _motion_csv(path, first_row: str | None = None, bom: bool = False, n: int = 3):
    from rpodguard.sequence import MOTION_COLUMNS

    rows = [",".join(MOTION_COLUMNS)] + ["0,0,-0.1," + ",".join(map(str, np.eye(3).ravel()))] * n
    if first_row is not None:
        rows[2] = first_row
    path.write_text(("\ufeff" if bom else "") + "\n".join(rows) + "\n", encoding="utf-8")
    return path


def test_a_motion_csv_with_a_byte_order_mark_is_read():
    """The issue's probe: a UTF-8 BOM (as spreadsheet programs write) was read as part of the first column's name."""
    import tempfile
    from pathlib import Path

    from rpodguard.sequence import read_motion

    with tempfile.TemporaryDirectory() as tmp:
        commands, attitudes = read_motion(_motion_csv(Path(tmp) / "m.csv", bom=True), 3)
    assert commands.shape == (3, 3) and np.allclose(attitudes, np.eye(3))


@pytest.mark.parametrize(
    "row, message",
    [
        (
            "0,0,-0.1," + ",".join(map(str, np.diag([1.0, 1.0, -1.0]).ravel())),
            r"m.csv: c0..c8 of data row 2 is a mirror \(determinant -1\), not a rotation \(1 such rows\)",
        ),
        (
            "1e300,0,0," + ",".join(map(str, np.eye(3).ravel())),
            r"m.csv: data row 2 commands a displacement of 1e\+300, 0, 0 m between two frames \(more than 1000 m",
        ),
    ],
)
def test_a_motion_csv_with_a_mirror_or_an_absurd_displacement_is_refused(tmp_path, row, message):
    from rpodguard.sequence import read_motion

    with pytest.raises(DataError, match=message):
        read_motion(_motion_csv(tmp_path / "m.csv", row), 3)
