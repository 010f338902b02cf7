"""The README's results block is a copy of reports/README.md's, and `rpod report --check` catches drift."""
from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from pipeline.report import extract_block, replace_block
from stages.cli import app

REPO = Path(__file__).resolve().parent.parent


def test_committed_readme_results_match_the_report_page():
    page, readme = REPO / "reports" / "README.md", REPO / "README.md"
    assert page.exists(), "reports/README.md is missing: run `dvc repro` (its last stage is `rpod report`)"
    ours, theirs = extract_block(page.read_text(), "results"), extract_block(readme.read_text(), "results")
    assert ours, "reports/README.md has no results block"
    assert ours == theirs, "README.md's results differ from reports/README.md: run `rpod report --sync-readme`"


@pytest.mark.parametrize("drift", [False, True])
def test_check_flags_a_drifted_readme(tmp_path, monkeypatch, drift):
    (tmp_path / "reports").mkdir()
    table = "| result | this run |\n|---|---|\n| pose (m) | 0.48 |"
    (tmp_path / "reports" / "README.md").write_text(replace_block("# results\n", "results", table))
    readme = replace_block("# rpodguard\n", "results", table.replace("0.48", "0.50") if drift else table)
    (tmp_path / "README.md").write_text(readme)
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(app, ["report", "--check"])
    if drift:
        assert result.exit_code != 0 and "rpod report --sync-readme" in str(result.exception)
    else:
        assert result.exit_code == 0, result.output


def test_report_names_the_missing_inputs(tmp_path, monkeypatch):
    import shutil

    shutil.copy(REPO / "params.yaml", tmp_path / "params.yaml")
    (tmp_path / "reports" / "metrics").mkdir(parents=True)
    (tmp_path / "reports" / "metrics" / "train.json").write_text("{}")
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(app, ["report"])
    assert result.exit_code != 0
    message = str(result.exception)
    assert "reports/metrics/attack.json (rpod attack)" in message and "reports/pose.md (rpod train)" in message
    assert "train.json" not in message and not (tmp_path / "reports" / "README.md").exists()
