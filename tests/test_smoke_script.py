"""scripts/smoke.py (`make smoke`) works in a copy and leaves the checkout as it was. Kept cheap: the
copy switches to the smoke profile and runs `dvc repro --dry` (nothing executes); tests/test_e2e_smoke.py
runs the whole `make smoke` (this script, every stage) and checks the checkout is left as it was."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parent.parent
SCRIPT = REPO / "scripts" / "smoke.py"
pytestmark = pytest.mark.skipif(
    shutil.which("git") is None or not (Path(sys.executable).parent / "dvc").exists(),
    reason="git and dvc (beside python) are needed",
)


def _porcelain() -> str:
    return subprocess.run(["git", "status", "--porcelain"], cwd=REPO, check=True, capture_output=True, text=True).stdout


def test_a_dry_smoke_run_works_in_a_copy_and_leaves_the_checkout_alone(tmp_path):
    before = _porcelain()
    dst = tmp_path / "copy"
    out = subprocess.run(
        [sys.executable, str(SCRIPT), "--dir", str(dst), "--dry", "--stages", "render"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert _porcelain() == before
    assert yaml.safe_load((dst / "params.yaml").read_text())["profile_name"] == "smoke"
    assert "profile: smoke" in (dst / "conf" / "config.yaml").read_text()
    assert "'render'" in out.stdout and "'label'" not in out.stdout and "'train'" not in out.stdout, out.stdout
    assert f"smoke results: {dst.resolve()}" in out.stdout
    tracked = subprocess.run(["git", "ls-files"], cwd=REPO, check=True, capture_output=True, text=True).stdout
    assert set(tracked.split()) <= set(
        subprocess.run(["git", "ls-files"], cwd=dst, check=True, capture_output=True, text=True).stdout.split()
    )


def test_a_dry_run_of_every_stage_lists_them_all(tmp_path):
    """Unforced, `dvc repro --dry` stopped at label in the copy (no datasets/render there): issue 41."""
    out = subprocess.run(
        [sys.executable, str(SCRIPT), "--dir", str(tmp_path / "c"), "--dry"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    stages = yaml.safe_load((REPO / "dvc.yaml").read_text())["stages"]
    assert set(re.findall(r"Running stage '(\w+)'", out.stdout)) == set(stages), out.stdout


def test_a_folder_that_is_not_empty_is_refused(tmp_path):
    (tmp_path / "keep.txt").write_text("mine")
    out = subprocess.run(
        [sys.executable, str(SCRIPT), "--dir", str(tmp_path), "--dry"], capture_output=True, text=True, timeout=60
    )
    assert out.returncode != 0 and out.stderr.strip().splitlines() == [f"smoke: --dir {tmp_path} is not empty"]
    assert (tmp_path / "keep.txt").read_text() == "mine"


def test_an_unknown_stage_stops_with_one_line(tmp_path):
    out = subprocess.run(
        [sys.executable, str(SCRIPT), "--dir", str(tmp_path / "c"), "--dry", "--stages", "nosuch"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert out.returncode != 0
    last = out.stderr.strip().splitlines()[-1]
    where = re.escape(str(tmp_path.resolve()))
    assert re.fullmatch(rf"smoke: `dvc repro --dry --force nosuch` failed in {where}/c \(exit \d+\)", last), last
