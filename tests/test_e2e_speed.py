"""End to end: a tiny SPEED+-layout folder as the training/test data of `dvc exp run` on the smoke profile
(render imports it; every stage after it, through `rpod report`, runs on it), in a temporary copy of
the repo; then editing one of its images marks `render` changed in `dvc status` (the folder is a DVC
dep through "${render.source}"). About a minute and a half on 2 cores."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pandas as pd
import pytest
import yaml
from test_e2e_smoke import _run, copy_repo
from test_speed import write_folder


@pytest.mark.slow
def test_a_speedplus_folder_runs_through_dvc(tmp_path):
    data = tmp_path / "speedplus"
    write_folder(data, n=(64, 16))
    repo = tmp_path / "repo"
    repo.mkdir()
    env = copy_repo(repo)
    _run(["dvc", "exp", "run", "-S", "profile=smoke", "-S", f"render.source={data}"], repo, env)  # every stage

    assert yaml.safe_load((repo / "params.yaml").read_text())["render"]["source"] == str(data)
    meta = json.loads((repo / "datasets/render/meta.json").read_text())
    assert len(meta["source"].pop("sha256")) == 64  # what it imported, by content (issue 42)
    assert meta["source"] == {
        "folder": str(data),
        "train": "synthetic/train.json",
        "test": "synthetic/test.json",
        "train_images": 64,
        "test_images": 16,
    }
    labels = pd.read_parquet(repo / "datasets/labels.parquet")
    assert (labels.split == "train").sum() == 64 and (labels.split == "test").sum() == 16
    train = json.loads((repo / "reports/metrics/train.json").read_text())
    assert train["profile"] == "smoke" and train["test"]["n"] == 16
    for stage in ("evaluate", "guidance", "robustness", "lab"):
        assert json.loads((repo / f"reports/metrics/{stage}.json").read_text())["profile"] == "smoke", stage
    assert json.loads((repo / "reports/metrics/summary.json").read_text())["pose"]["standard_position_m"] > 0
    assert "## " in (repo / "reports/README.md").read_text()
    lock = yaml.safe_load((repo / "dvc.lock").read_text())["stages"]["render"]
    assert str(data) in [d["path"] for d in lock["deps"]]
    assert "changed" not in _run(["dvc", "status", "dvc.yaml"], repo, env)  # optional/dvc.yaml's stages did not run

    cv2.imwrite(str(data / "synthetic/images/train000.png"), np.zeros((30, 48, 3), np.uint8))
    status = _run(["dvc", "status", "render"], repo, env)
    assert "modified" in status and str(data) in status
