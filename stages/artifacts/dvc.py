"""dvc.yaml as the stages read it: which stage writes a file (for the hint of a missing input) and
the metrics JSON every stage writes."""
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

    return {name: st for path in (DVC_YAML, OPTIONAL_DVC_YAML) if path.is_file()
            for name, st in yaml.safe_load(path.read_text()).get("stages", {}).items()}


def _outputs(stage: dict[str, Any]) -> list[Path]:
    """A dvc.yaml stage's outputs: its outs, metrics and plots."""
    return [Path(next(iter(o)) if isinstance(o, dict) else o) for kind in ("outs", "metrics", "plots")
            for o in stage.get(kind, [])]


def producer(path: Path | str) -> str | None:
    """The dvc.yaml stage whose output is `path` (or a folder holding it), or None."""
    path = Path(path)
    if path.is_absolute():
        path = Path(os.path.relpath(path, DVC_YAML.parent if path.is_relative_to(DVC_YAML.parent) else Path.cwd()))
    return next((name for name, st in dvc_stages().items()
                 if any(path == out or out in path.parents for out in _outputs(st))), None)


def make_hint(path: Path | str) -> str:
    """How to make `path`: "run `dvc repro STAGE` (or `rpod ...`)" for the stage that writes it."""
    stage = producer(path)
    if stage is None:
        return GENERIC_HINT
    return f"run `dvc repro {stage}` (or `{dvc_stages()[stage]['cmd']}`)"


def write_metrics(path: Path | str, metrics: dict[str, Any], profile: str) -> None:
    """Write a stage's metrics JSON stamped with the params profile it ran on (`profile_name`), the CPU
    instruction-set cap torch ran with (stages/config/cpu.py: scripts/variance.py reads it) and the UTC time."""
    from stages.config.cpu import isa_stamp

    stamp = {"profile": profile, "cpu_isa": isa_stamp(),
             "produced": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")}
    write_json(path, {**metrics, **stamp})
