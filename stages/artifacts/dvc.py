"""dvc.yaml as the stages read it: which stage writes a file (for the hint of a missing input), the metrics JSON
every stage writes, and the git-tracked outputs a failed stage puts back (`restore_tracked_outputs`)."""

from __future__ import annotations

import functools
import os
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from pipeline.io.atomic import write_json
from pipeline.io.errors import GENERIC_HINT
from stages.artifacts.paths import DVC_YAML, OPTIONAL_DVC_YAML


@functools.cache
def dvc_stages() -> dict[str, dict[str, Any]]:
    """The stages of dvc.yaml, then of optional/dvc.yaml (name -> its entry: cmd, deps, params, outs, ...); empty
    without them."""
    import yaml

    return {
        name: st
        for path in (DVC_YAML, OPTIONAL_DVC_YAML)
        if path.is_file()
        for name, st in yaml.safe_load(path.read_text()).get("stages", {}).items()
    }


def _outputs(stage: dict[str, Any]) -> list[Path]:
    """A dvc.yaml stage's outputs: its outs, metrics and plots."""
    return [
        Path(next(iter(o)) if isinstance(o, dict) else o)
        for kind in ("outs", "metrics", "plots")
        for o in stage.get(kind, [])
    ]


def producer(path: Path | str) -> str | None:
    """The dvc.yaml stage whose output is `path` (or a folder holding it), or None."""
    path = Path(path)
    if path.is_absolute():
        path = Path(os.path.relpath(path, DVC_YAML.parent if path.is_relative_to(DVC_YAML.parent) else Path.cwd()))
    return next(
        (name for name, st in dvc_stages().items() if any(path == out or out in path.parents for out in _outputs(st))),
        None,
    )


def make_hint(path: Path | str) -> str:
    """How to make `path`: "run `dvc repro STAGE` (or `rpod ...`)" for the stage that writes it."""
    stage = producer(path)
    if stage is None:
        return GENERIC_HINT
    return f"run `dvc repro {stage}` (or `{dvc_stages()[stage]['cmd']}`)"


def restore_tracked_outputs() -> list[str]:
    """After a stage that DVC ran ($DVC_STAGE, working folder $DVC_ROOT) failed or was interrupted: DVC deletes a
    stage's outputs before it runs it and puts back nothing when it fails, so the outputs git tracks (reports,
    figures, metrics, curves: `cache: false`) are checked out again from git's index (what the last successful run
    left there: `core.autostage`, else the commit), and files the failed run added inside such an output folder are
    removed. The cached outputs (datasets/, models/) come back with `dvc checkout`. Returns the outputs put back;
    nothing outside DVC, or without git."""
    import subprocess

    stage, root = os.environ.get("DVC_STAGE"), os.environ.get("DVC_ROOT")
    if not stage or not root or not Path(root).is_dir() or not Path(root).samefile(Path.cwd()):
        return []
    entry = dvc_stages().get(stage.rsplit(":", 1)[-1])
    if entry is None:
        return []

    def git(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(["git", *args], capture_output=True, text=True, timeout=60)

    restored = []
    for out in map(str, _outputs(entry)):
        try:
            listed = git("ls-files", "--", out)
        except (OSError, subprocess.SubprocessError):  # no git here
            return restored
        if listed.returncode != 0 or not listed.stdout.strip():
            continue
        changed = git("status", "--porcelain", "--untracked-files=all", "--", out).stdout.strip()
        if changed and git("checkout", "--", out).returncode == 0:
            if Path(out).is_dir():
                git("clean", "-fdq", "--", out)
            restored.append(out)
    return restored


def write_metrics(path: Path | str, metrics: dict[str, Any], profile: str) -> None:
    """Write a stage's metrics JSON stamped with the params profile it ran on (`profile_name`), the CPU
    instruction-set cap torch ran with (stages/config/cpu.py: scripts/variance.py reads it) and the UTC time."""
    from stages.config.cpu import isa_stamp

    stamp = {
        "profile": profile,
        "cpu_isa": isa_stamp(),
        "produced": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
    }
    write_json(path, {**metrics, **stamp})
