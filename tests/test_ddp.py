"""`rpod train` under torchrun: 2 processes, DistributedDataParallel with gloo on CPU (smoke profile)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import torch
from test_training import H, W, write_dataset

from stages.artifacts import models
from stages.artifacts.paths import POSE
from stages.config import params as params_mod


def test_torchrun_two_processes_gloo(tmp_path, monkeypatch):
    write_dataset(tmp_path, n=80, overrides=["train.epochs=2"])
    rpod = Path(sys.executable).parent / "rpod"
    env = {
        **os.environ,
        "OMP_NUM_THREADS": "1",
        "RPOD_DEBUG": "1",
        "PYTHONPATH": os.pathsep.join(
            filter(None, [str(Path(__file__).resolve().parent.parent), os.environ.get("PYTHONPATH")])
        ),
    }
    env.pop("WORLD_SIZE", None)
    proc = subprocess.run(
        [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2", str(rpod), "train"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "x 2 process(es)" in proc.stdout
    metrics = json.loads((tmp_path / "reports/metrics/train.json").read_text())
    assert metrics["processes"] == 2 and metrics["epochs_run"] == 2
    assert metrics["test"]["n"] == 16 and metrics["train"]["n"] == 58 and metrics["val"]["n"] == 6
    # rank 0 alone wrote: exactly one report and one checkpoint, and the checkpoint matches params
    assert len(list((tmp_path / "reports").glob("*.md"))) == 1
    monkeypatch.chdir(tmp_path)
    model = models.load_pose(params_mod.load(), POSE).model
    assert model(torch.rand(1, 3, H, W)).shape == (1, 9)
