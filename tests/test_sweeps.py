"""Profiles and sweeps (issue 29): `rpod params NAME` makes NAME the profile DVC's Hydra composition starts
from, so `dvc exp run -S key=value` changes one value of it; both entry points refuse an unknown name or a
bad value at once with the schema's one-line message. No stage runs here."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from stages.config import compose as compose_mod
from stages.config.sections import ParamsError

REPO = Path(__file__).resolve().parent.parent
DVC = Path(sys.executable).with_name("dvc")
# DVC's own code path for `dvc exp run -S` (BaseStashQueue._update_params), without stashing or running stages
UPDATE_PARAMS = (
    "import sys, types; from dvc.repo import Repo; from dvc.repo.experiments.queue.base import "
    "BaseStashQueue as Q; r = Repo('.'); Q._update_params(types.SimpleNamespace(repo=r, scm=r.scm), "
    "{'params.yaml': sys.argv[1:]})"
)
pytestmark = pytest.mark.skipif(not DVC.exists(), reason="dvc not installed beside python")


@pytest.fixture
def repo(tmp_path) -> tuple[Path, dict[str, str]]:
    """A git + DVC repository with what composition reads: conf/, .dvc/config and the schema plugin."""
    for name in ("conf", "stages/config/hydra_plugins"):
        shutil.copytree(REPO / name, tmp_path / name, ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("dvc.yaml", "params.yaml", ".dvc/config"):
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(REPO / name, tmp_path / name)
    env = {
        **os.environ,
        "PYTHONPATH": str(REPO),
        "GIT_AUTHOR_NAME": "t",
        "GIT_AUTHOR_EMAIL": "t@example.org",
        "GIT_COMMITTER_NAME": "t",
        "GIT_COMMITTER_EMAIL": "t@example.org",
    }
    for cmd in (["git", "init", "-q"], ["git", "add", "-A"], ["git", "commit", "-qm", "copy"]):
        subprocess.run(cmd, cwd=tmp_path, env=env, check=True)
    return tmp_path, env


def _run(args: list[str], cwd: Path, env: dict[str, str]) -> subprocess.CompletedProcess:
    return subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=120)


def _rpod_params(cwd: Path, env: dict[str, str], *args: str) -> subprocess.CompletedProcess:
    return _run([sys.executable, "-m", "stages.cli", "params", *args], cwd, env)


def test_a_sweep_keeps_the_profile_rpod_params_chose(repo):
    cwd, env = repo
    assert _rpod_params(cwd, env, "smoke").returncode == 0
    assert "  - profile: smoke" in (cwd / "conf/config.yaml").read_text()
    smoke = yaml.safe_load((cwd / "params.yaml").read_text())
    done = _run([sys.executable, "-c", UPDATE_PARAMS, "train.epochs=2"], cwd, env)
    assert done.returncode == 0, done.stderr
    swept = yaml.safe_load((cwd / "params.yaml").read_text())
    assert swept["profile_name"] == "smoke" and swept["train"]["epochs"] == 2
    assert swept["render"] == smoke["render"] and swept["render"]["width"] < 100  # smoke-sized stages
    swept["train"]["epochs"] = smoke["train"]["epochs"]
    assert swept == smoke  # one value changed
    assert _rpod_params(cwd, env, "default").returncode == 0
    assert "  - profile: default" in (cwd / "conf/config.yaml").read_text()


def test_a_dry_sweep_says_it_keeps_the_profile(repo):
    """`rpod params smoke && dvc exp run -S train.epochs=2 --dry` shows the smoke profile it composes (issue 29).
    `-f`: DVC runs a dry experiment in a temporary copy without the outputs, where its dry run stops at the first
    stage whose input is missing (treeverse/dvc#9818); forced, it lists every stage."""
    cwd, env = repo
    assert _rpod_params(cwd, env, "smoke").returncode == 0
    dvc = _run([str(DVC), "exp", "run", "--dry", "-f", "-S", "train.epochs=2"], cwd, env)
    assert dvc.returncode == 0, dvc.stderr
    assert "params.yaml <- profile 'smoke' with train.epochs=2" in dvc.stderr.splitlines()
    assert "> rpod train" in dvc.stdout
    assert yaml.safe_load((cwd / "params.yaml").read_text())["profile_name"] == "smoke"


@pytest.mark.parametrize(
    "override, message",
    [
        ("trian.epochs=3", "params.yaml: unknown parameter 'trian' (did you mean 'train'?)"),
        ("+trian.epochs=3", "params.yaml: unknown parameter 'trian' (did you mean 'train'?)"),
        ("train.epoch=3", "params.yaml: unknown parameter 'train.epoch' (did you mean 'train.epochs'?)"),
        ("train.epochs=abc", "params.yaml train.epochs must be a whole number, got 'abc'"),
    ],
)
def test_both_entry_points_refuse_a_typo_in_one_line(repo, override, message):
    cwd, env = repo
    before = {p: (cwd / p).read_text() for p in ("params.yaml", "conf/config.yaml")}
    rpod = _rpod_params(cwd, env, "smoke", "-S", override)
    assert rpod.returncode == 1 and rpod.stderr == f"error: {message}\n"
    dvc = _run([str(DVC), "exp", "run", "--dry", "-S", override], cwd, env)
    assert dvc.returncode != 0 and dvc.stderr.strip() == f"ERROR: {message}", dvc.stderr
    assert {p: (cwd / p).read_text() for p in before} == before


def test_compose_checked_refuses_what_the_stages_refuse():
    with pytest.raises(ParamsError, match=r"unknown parameter 'trian' \(did you mean 'train'\?\)"):
        compose_mod.compose_checked("smoke", ["trian.epochs=3"])
    assert compose_mod.compose_checked("smoke", ["train.epochs=2"])["train"]["epochs"] == 2


def test_record_profile_needs_the_defaults_line(tmp_path):
    config = tmp_path / "config.yaml"
    assert not compose_mod.record_profile("smoke", config)
    config.write_text("defaults:\n  - _self_\nseed: 0\n")
    with pytest.raises(ParamsError, match="one `  - profile: NAME` line"):
        compose_mod.record_profile("smoke", config)


def test_the_committed_params_are_the_profile_conf_picks():
    """params.yaml and conf/config.yaml's defaults list are committed together (`rpod params NAME` writes both)."""
    picked = next(
        line.split(":")[1].split()[0]
        for line in (REPO / "conf/config.yaml").read_text().splitlines()
        if line.startswith("  - profile:")
    )
    assert yaml.safe_load((REPO / "params.yaml").read_text())["profile_name"] == picked
