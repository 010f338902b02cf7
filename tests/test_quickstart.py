"""The README's quick start runs as written: its sample image and example sequence are committed, the motion file
fits the sequence, and the commands give a pose and a verdict on the shipped weights (issue 41)."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parent.parent
README = REPO / "README.md"
SECTION = "## Quick start"


def _section() -> str:
    text = README.read_text()
    start = text.index(SECTION)
    assert start < 3000, "the quick start is on the README's first screen"
    return text[start : text.index("\n<!-- ", start)]


def _commands() -> list[list[str]]:
    block = re.findall(r"```bash\n(.*?)```", _section(), flags=re.S)[0]
    return [shlex.split(line.split("#")[0]) for line in block.splitlines() if line.startswith("rpod ")]


def test_the_quick_start_names_committed_files_and_a_matching_motion_file():
    from rpodguard.sequence import read_motion

    single, sequence = _commands()
    assert single[:2] == ["rpod", "predict"] and (REPO / single[2]).is_file()
    frames = sorted((REPO / "examples/approach").glob("*.png"))
    assert sequence[2] == "examples/approach/*.png" and len(frames) == 8
    commands, attitudes = read_motion(REPO / sequence[sequence.index("--motion") + 1], len(frames))
    assert np.allclose(commands[0], 0) and (commands[1:, 2] < 0).all()  # closing in, every step
    assert "source .venv/bin/activate" in _section()


@pytest.mark.slow
def test_the_quick_start_commands_give_a_pose_and_a_verdict(monkeypatch, capsys):
    from typer.testing import CliRunner

    from stages.cli import app

    monkeypatch.chdir(REPO)
    single, sequence = _commands()
    frames = [str(p.relative_to(REPO)) for p in sorted((REPO / "examples/approach").glob("*.png"))]
    runner = CliRunner()
    one = runner.invoke(app, single[1:])
    assert one.exit_code == 0, one.output
    assert one.output.splitlines()[-1].split()[-1] in ("clean", "doubt", "attack")
    args = [a for a in sequence[1:] if "*" not in a]
    many = runner.invoke(app, [*args[:1], *frames, *args[1:]])
    assert many.exit_code == 0, many.output
    rows = [line for line in many.output.splitlines() if line.startswith("examples/approach/")]
    assert len(rows) == 8
    assert abs(float(rows[-1].split()[3]) - 12.0) < 2.0  # the last frame's trusted range: the approach ends at 12 m
