"""The README's results block is a copy of reports/README.md's, and `rpod report --check` catches drift."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from pipeline.report.markdown import extract_block, replace_block
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
    bullets = "- **Scale.** 3,900 images"
    (tmp_path / "reports" / "README.md").write_text(
        replace_block(replace_block("# results\n", "results", table), "differences", bullets)
    )
    readme = replace_block("# rpodguard\n", "results", table.replace("0.48", "0.50") if drift else table)
    (tmp_path / "README.md").write_text(replace_block(readme, "differences", bullets))
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(app, ["report", "--check"])
    if drift:
        assert result.exit_code != 0 and "rpod report --sync-readme" in str(result.exception)
    else:
        assert result.exit_code == 0, result.output


def _page_with(tmp_path, stage_report: str) -> None:
    """reports/README.md holding a one-section stage report as build_page embeds it; README.md in sync."""
    (tmp_path / "reports").mkdir()
    (tmp_path / "reports" / "pose.md").write_text(stage_report)
    page = replace_block(replace_block("# results\n", "results", "table"), "differences", "bullets")
    (tmp_path / "reports" / "README.md").write_text(page + "\n## Pose\n\n_stamp_\n" + stage_report.partition("\n")[2])
    (tmp_path / "README.md").write_text(page)


def test_check_flags_a_stage_report_newer_than_the_page(tmp_path, monkeypatch):
    _page_with(tmp_path, "# Pose\n\n| split | m |\n|---|---|\n| test | 0.48 |\n")
    monkeypatch.chdir(tmp_path)
    assert CliRunner().invoke(app, ["report", "--check"]).exit_code == 0
    (tmp_path / "reports" / "pose.md").write_text("# Pose\n\n| split | m |\n|---|---|\n| test | 0.52 |\n")
    result = CliRunner().invoke(app, ["report", "--check"])
    assert result.exit_code != 0 and "older than reports/pose.md" in str(result.exception)


def test_only_the_default_profile_rewrites_the_readme(tmp_path, monkeypatch):
    """A smoke run (or a sweep) builds its own results page but leaves README.md alone."""
    from stages import report
    from stages.config import params as params_mod
    from stages.config.schema import build

    monkeypatch.chdir(tmp_path)
    (tmp_path / "README.md").write_text("# rpodguard\n")
    monkeypatch.setattr(report, "load", lambda: build(params_mod.compose("smoke")))
    monkeypatch.setattr(report, "_load_metrics", lambda: {})
    monkeypatch.setattr(report, "_write_figures", lambda metrics: [])
    monkeypatch.setattr(report, "build_page", lambda m, p, f: replace_block("# results\n", "results", "smoke table"))
    (tmp_path / "reports").mkdir()
    report.main(sync_readme=True, check=False)
    assert (tmp_path / "README.md").read_text() == "# rpodguard\n"
    assert "smoke table" in (tmp_path / "reports" / "README.md").read_text()


def test_report_names_the_missing_inputs(tmp_path, monkeypatch):
    import shutil

    shutil.copy(REPO / "params.yaml", tmp_path / "params.yaml")
    (tmp_path / "reports" / "metrics").mkdir(parents=True)
    (tmp_path / "reports" / "metrics" / "train.json").write_text("{}")
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(app, ["report"])
    assert result.exit_code != 0
    message = str(result.exception)
    assert "reports/metrics/attack.json: run `dvc repro attack` (or `rpod attack`)" in message
    assert "reports/pose.md: run `dvc repro train` (or `rpod train`)" in message
    assert "train.json" not in message and not (tmp_path / "reports" / "README.md").exists()
