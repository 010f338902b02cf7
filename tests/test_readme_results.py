"""The README's results block is a copy of reports/README.md's, and `rpod report --check` catches drift."""

from __future__ import annotations

import re
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


# ----------------------------------------------------------------------------- the results' lead: targets met or missed
def _committed_metrics() -> dict:
    import json

    return {p.stem: json.loads(p.read_text()) for p in (REPO / "reports" / "metrics").glob("*.json")}


@pytest.mark.parametrize(
    "value, target, verdict",
    [
        (99.6, ">= 99.5", "met"),
        (99.4, ">= 99.5", "**missed**"),
        (1.0, "<= 1", "met"),
        (1.01, "<= 1", "**missed**"),
        (None, "<= 1", "not shown"),
        (float("nan"), ">= 95", "not shown"),
    ],
)
def test_a_target_is_judged_on_the_point_estimate(value, target, verdict):
    from stages.pages.readme import judge

    assert judge(value, target) == verdict


def test_the_lead_counts_every_target_and_marks_each_in_the_tables():
    """Every target of the shipped chain appears once in the lead's table with its verdict, the counts in the
    sentence add up, and every target cell of the defended table carries a met / missed mark."""
    from stages.pages.readme import headline, shipped_targets, summary_tables

    metrics = _committed_metrics()
    verdicts = shipped_targets(metrics)
    assert len(verdicts) >= 10 and {v for _, v, _ in verdicts} <= {"met", "**missed**", "not shown"}
    met = sum(v == "met" for _, v, _ in verdicts)
    lead = headline(metrics)
    assert lead.startswith(f"**{met} of {len(verdicts)} targets met**")
    for target, verdict, evidence in verdicts:
        assert f"| {target}" in lead and verdict in lead and evidence in lead, target
    text = summary_tables(metrics)
    defended = text[text.index("The defended chains") :]
    lines = [line for line in defended.splitlines() if line.startswith("| ")]
    column = [c.strip() for c in lines[0].split("|")].index("target")
    cells = [line.split("|")[column].strip() for line in lines[1:]]
    assert cells and all(c == "-" or c.endswith(("(met)", "(**missed**)", "(not shown)")) for c in cells), cells
    assert "the interval's upper end is all this run rules out" in text
    assert "issue" not in text.lower()


def test_the_lead_drops_a_target_whose_stage_did_not_run():
    from stages.pages.readme import shipped_targets

    metrics = _committed_metrics()
    full = shipped_targets(metrics)
    del metrics["guidance"]
    partial = shipped_targets(metrics)
    assert len(partial) < len(full) and not any("closed loop" in t or "docking" in t for t, _, _ in partial)


def test_the_rendezvous_target_says_how_the_attacked_runs_ended_by_the_docking_measure():
    """The defended grid's target counts the runs the attack kept from docking (a safe abort counts as kept); its
    evidence says how detect-and-recover's attacked grid runs ended by the docking measure, so a hold is not read as a
    mission failure. Only the variant's grid runs of that dynamics that met the attack count."""
    from stages.pages.readme import _grid_outcomes, shipped_targets

    def run(outcome, failed=False, dynamics="true_state", defense="recover", attack="grid S=60 m K=5", met=True):
        return {
            "dynamics": dynamics,
            "defense": defense,
            "attack": attack,
            "met": met,
            "outcome": outcome,
            "failed": failed,
        }

    runs = [run("docked"), run("held"), run("held"), run("timed out"), run("missed", True)]
    others = [
        run("collision", True, dynamics="paper"),
        run("collision", True, defense="hold"),
        run("collision", True, attack="in-loop capture from 60 m"),
        run("collision", True, met=False),
        run("docked", attack="none"),
    ]
    said = _grid_outcomes({"runs": runs + others}, "true_state")
    assert said == "; by the docking measure 2 held, 1 timed out, 1 failed the mission"
    assert _grid_outcomes(None, "true_state") == "" and _grid_outcomes({"runs": others[:1]}, "true_state") == ""
    rows = [(t, e) for t, _, e in shipped_targets(_committed_metrics()) if "did not keep from docking" in t]
    assert rows and all("by the docking measure" in e for _, e in rows)
    for _, evidence in rows:  # docked + held + timed out + failed = the attacked runs that met the attack
        met = int(re.search(r"of (\d+) kept from docking", evidence).group(1))
        parts = re.search(r"\((\d+) docked; by the docking measure (\d+) held, (\d+) timed out, (\d+) failed", evidence)
        assert parts and sum(int(x) for x in parts.groups()) == met, evidence


def test_the_hmi_rows_give_the_trajectories_with_an_hmi_frame_by_clopper_pearson():
    """Issue 39: the HMI rows stay descriptive, beside the frame rate the count of trajectories with an HMI frame
    and its Clopper-Pearson interval over independent trajectories; the paper dynamics' target says it is the
    paper's reproduction (prediction = truth by construction)."""
    from pipeline.stats import clopper_pearson
    from stages.pages.readme import _hmi_trajectories, shipped_targets, summary_tables

    metrics = _committed_metrics()
    robust = metrics["robustness"]["integrity"]["chains"]["robust"]
    r = robust["summary"]["per_eps"]["0.01"]["hmi_trajectories"]
    k, n = round(r["value"] * r["n"]), r["n"]
    lo, hi = clopper_pearson(k, n).ci()
    said = _hmi_trajectories(robust, "0.01")
    assert said == f"; {k} of {n} trajectories: {100 * r['value']:.1f} [{100 * lo:.1f}, {100 * hi:.1f}]%"
    assert said in summary_tables(metrics)
    assert _hmi_trajectories(robust, "0.3") == ""  # an eps the chain did not fly
    paper = [t for t, _, _ in shipped_targets(metrics) if "paper dynamics" in t]
    assert paper and all("prediction = truth by construction" in t for t in paper)
