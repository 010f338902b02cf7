"""Stage commands run as subprocesses in a folder of their own: a sub-pipeline with its own params.yaml
(`rpod lab_models`' synthetic-lab retraining, `rpod pose_trial`'s variants of the pose data set)."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import time
from pathlib import Path

from stages.config.params import PARAMS_FILE, ROOT, write_params
from stages.config.schema import Params
from stages.errors import StageError


def run_step(args: list[str], folder: Path) -> None:
    """`rpod <args>` as a subprocess in `folder` (it reads ./params.yaml there); a failure is a StageError
    carrying the command's own one-line error."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))}
    out = subprocess.run(
        [sys.executable, "-m", "stages.cli", *args], cwd=folder, env=env, stderr=subprocess.PIPE, text=True
    )
    sys.stderr.write(out.stderr)
    if out.returncode != 0:
        lines = [ln for ln in out.stderr.strip().splitlines() if ln.strip()]
        raise StageError((lines[-1] if lines else f"exit status {out.returncode}").removeprefix("error: "))


def run_steps(
    sub: Params, steps: dict[str, list[str]], dest: Path, final: Path, what: str, where: str
) -> dict[str, float]:
    """Write `sub` as dest/params.yaml, then run each step's `rpod` command there in order (`steps`: dvc.yaml stage
    name -> its arguments; `dest` a fresh folder that becomes `final`); returns the seconds per step. Progress and
    errors name the sub-pipeline: "`what` (STEP `where` FINAL/): error"."""
    dest.mkdir(parents=True, exist_ok=True)
    write_params(dataclasses.asdict(sub), dest / PARAMS_FILE)
    seconds: dict[str, float] = {}
    for i, (name, args) in enumerate(steps.items(), 1):
        print(f"{what}: {name} ({i}/{len(steps)}) {where} {final}/", flush=True)
        t0 = time.perf_counter()
        try:
            run_step(args, dest)
        except (StageError, ValueError) as e:
            raise StageError(f"{what} ({name} {where} {final}/): {e}") from None
        seconds[name] = time.perf_counter() - t0
    return seconds
