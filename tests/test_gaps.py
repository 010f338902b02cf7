"""`rpod gaps`: issue 38's "differences from the paper" table. Each row's steps are measured differences that add up to
what is measured together, the share and what is left follow from them, and README's table is reports/gaps.md's."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from pipeline.report.markdown import extract_block, replace_block
from stages.cli import app
from stages.pages.gaps import CHAIN, attitude_gap, detector_gap, gaps_page, sequence_gap
from stages.pages.paper import ATTITUDE_DEG, DETECTOR_ACCURACY, INTEGRATED_EPS

REPO = Path(__file__).resolve().parent.parent


def _row(tp: list[int], fp: list[int], n_att: int = 50, n_clean: int = 40) -> dict:
    """One detector's sequence row at eps 0.01: per-sequence counts (tp, attacked, fp, clean), its re-weighted accuracy."""
    counts = [[t, n_att, f, n_clean] for t, f in zip(tp, fp)]
    f = 0.5
    acc = f * sum(tp) / (n_att * len(tp)) + (1 - f) * (1 - sum(fp) / (n_clean * len(fp)))
    return {"0.01": {"counts": counts, "accuracy_at": {"value": acc, "ci": [acc - 0.05, acc + 0.05]}}}


def _ablation() -> dict:
    rng = np.random.default_rng(0)
    detectors = {
        name: _row(list(rng.integers(lo, lo + 10, 6)), list(rng.integers(0, 4, 6)))
        for name, lo in (
            ("standard/ours", 10),
            ("standard/paper", 15),
            ("paper/strict/paper", 30),
            ("paper/paper/paper", 25),
        )
    }
    seq = {"detectors": detectors, "paper_fraction": 0.5}

    def cell(attack: str, protocol: str, acc: float) -> dict:
        rate = {"value": acc, "ci": [acc - 0.02, acc + 0.02], "n": 800}
        return {"attack": attack, "protocol": protocol, "eps_set": "paper", "rates": {"all": {"accuracy": rate}}}

    cells = [cell("ours", "strict", 0.90), cell("paper", "strict", 0.90), cell("paper", "paper", 0.91)]
    return {"sequences": {"integrated": seq, "lab": seq}, "cells": cells}


def test_the_chains_steps_add_up_to_the_measured_whole_and_the_rest_is_left():
    g = sequence_gap(_ablation(), "integrated")
    assert [s["cause"] for s in g["steps"]] == [c[0] for c in CHAIN]
    assert sum(s["effect"][0] for s in g["steps"]) == pytest.approx(g["together"][0])
    det = _ablation()["sequences"]["integrated"]["detectors"]
    start, end = (100 * det[k]["0.01"]["accuracy_at"]["value"] for k in ("standard/ours", "paper/paper/paper"))
    assert g["ours"][0] == pytest.approx(start) and g["together"][0] == pytest.approx(end - start)
    assert g["gap"] == pytest.approx(INTEGRATED_EPS["0.01"] - start)
    assert g["left"][0] == pytest.approx(INTEGRATED_EPS["0.01"] - end) and g["left"][1] < g["left"][0] < g["left"][2]
    assert g["explained"][0] == pytest.approx((end - start) / g["gap"])
    assert all(s["effect"][1] <= s["effect"][0] <= s["effect"][2] for s in g["steps"])
    assert [s["paper_cause"] for s in g["steps"]] == [True, False, True]  # the refit is ours, not the paper's


def test_the_detector_row_chains_the_cells_from_the_shipped_detector():
    detect = {"detectors": {"lstm": {"all": {"accuracy": 0.92, "accuracy_ci95": [0.90, 0.94], "n": 1000}}}}
    g = detector_gap(detect, _ablation())
    assert [round(s["effect"][0], 6) for s in g["steps"]] == [-2.0, 0.0, 1.0]
    assert g["together"][0] == pytest.approx(-1.0) and g["gap"] == pytest.approx(100 * DETECTOR_ACCURACY - 92.0)
    assert g["explained"][0] < 0  # measured causes that move away from the paper count against it


def _attitude(interactions: dict) -> dict:
    def model(att: float) -> dict:
        return {"test": {"attitude_deg": [att, att - 0.3, att + 0.3]}}

    contribution = {
        v: {"test": {"attitude_deg": [d, d - 0.4, d + 0.4]}} for v, d in (("a", 1.0), ("b", 0.6), ("ab", 1.3))
    }
    return {
        "models": {"standard": model(2.5), "a": model(1.5), "b": model(1.9), "ab": model(1.2)},
        "contributions": contribution,
        "interactions": interactions,
        "changes": {"a": "labels", "b": "size", "ab": "both"},
    }


def test_the_attitude_row_needs_the_combined_trial_and_reports_its_interaction():
    assert attitude_gap(_attitude({})) is None
    x = {"of": ["a", "b"], "test": {"interaction_deg": [-0.3, -0.7, 0.1]}}
    g = attitude_gap(_attitude({"ab": x}))
    assert [s["cause"] for s in g["steps"]] == ["a alone", "b alone", "interaction"]
    assert g["gap"] == pytest.approx(2.5 - ATTITUDE_DEG) and g["together"][0] == pytest.approx(1.3)
    assert g["left"][0] == pytest.approx(1.2 - ATTITUDE_DEG)  # the combined model's error above the paper's
    page = gaps_page([g], "gaps", {"a": "labels"})
    assert "has no row" not in page and "**a alone**: labels." in page
    assert "has no row" in gaps_page([sequence_gap(_ablation(), "lab")], "gaps", {})


def test_committed_readme_gaps_table_matches_reports_gaps():
    page, readme = REPO / "reports" / "gaps.md", REPO / "README.md"
    assert page.exists(), "reports/gaps.md is missing: run `dvc repro optional/dvc.yaml:gaps`"
    ours = extract_block(page.read_text(), "gaps")
    assert ours and ours == extract_block(readme.read_text(), "gaps"), "run `rpod gaps --sync-readme`"
    rows = json.loads((REPO / "reports" / "metrics" / "gaps.json").read_text())["gaps"]
    assert all(f"{r['paper']:.2f}" in ours for r in rows)


def test_report_check_flags_a_drifted_gaps_table(tmp_path, monkeypatch):
    (tmp_path / "reports").mkdir()
    page = replace_block(replace_block("# results\n", "results", "table"), "differences", "bullets")
    (tmp_path / "reports" / "README.md").write_text(page)
    (tmp_path / "reports" / "gaps.md").write_text(replace_block("# gaps\n", "gaps", "| a | 1.0 |"))
    (tmp_path / "README.md").write_text(replace_block(page, "gaps", "| a | 1.0 |"))
    monkeypatch.chdir(tmp_path)
    assert CliRunner().invoke(app, ["report", "--check"]).exit_code == 0
    (tmp_path / "README.md").write_text(replace_block(page, "gaps", "| a | 2.0 |"))
    result = CliRunner().invoke(app, ["report", "--check"])
    assert result.exit_code != 0 and "rpod gaps --sync-readme" in str(result.exception)


def test_a_missing_source_is_one_line_naming_the_stage_that_writes_it(tmp_path, monkeypatch):
    import shutil

    shutil.copy(REPO / "params.yaml", tmp_path / "params.yaml")
    (tmp_path / "reports" / "metrics").mkdir(parents=True)
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(app, ["gaps"])
    assert result.exit_code != 0 and "reports/metrics/attitude.json not found: run `rpod attitude`" in str(
        result.exception
    )
    assert not (tmp_path / "reports" / "gaps.md").exists()
