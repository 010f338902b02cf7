"""scripts/breaking_trial.py: a chain's breaking point is bracketed by the eps it held at and the eps it broke at, and
the shipped / control ratio is only claimed within what the two brackets allow."""

from __future__ import annotations

import json
from pathlib import Path

from script_loader import load_script

REPO = Path(__file__).resolve().parent.parent


def _load():
    return load_script("breaking_trial")


def _summary(failed: dict[str, int], breaking: float | None) -> dict:
    per = {e: {"failed": f, "trajectories": 4, "max_error_al": 0.5 if not f else 3.0} for e, f in failed.items()}
    return {"summary": {"per_eps": per, "breaking_eps": breaking, "eps_flown": list(failed)}}


def test_the_bracket_is_held_at_then_broke_at():
    bt = _load()
    assert bt.bracket({"0.01": {}, "0.05": {}, "0.1": {}}, 0.1) == (0.05, 0.1)
    assert bt.bracket({"0.01": {}, "0.2": {}}, None) == (0.2, None)  # never broke: held at the last eps
    assert bt.bracket({"0.01": {}}, 0.01) == (None, 0.01)  # broke at the first eps


def test_the_ratio_is_bounded_by_both_brackets():
    bt = _load()
    assert bt.ratio_range((0.1, 0.14), (0.05, 0.07)) == "above 1.43, at most 2.80"
    assert bt.ratio_range((0.2, None), (0.1, 0.14)) == "above 1.43, no upper bound"
    assert bt.ratio_range((0.1, 0.14), (None, 0.01)) == "above 10.00, no upper bound"
    assert bt.ratio_range((0.1, 0.14), (0.2, None)).startswith("-")


def test_the_trial_writes_its_section_and_keeps_the_others(tmp_path, monkeypatch):
    bt = _load()
    run = tmp_path / "s0"
    (run / "reports" / "metrics").mkdir(parents=True)
    (run / "params.yaml").write_text("seed: 0\n")
    chains = {
        "robust": _summary({"0.01": 0, "0.05": 0, "0.1": 0, "0.14": 1}, 0.14),
        "control": _summary({"0.01": 0, "0.05": 0, "0.07": 2}, 0.07),
    }
    (run / "reports" / "metrics" / "robustness.json").write_text(json.dumps({"integrity": {"chains": chains}}))
    monkeypatch.setattr(bt, "ROOT", tmp_path)
    (tmp_path / "reports").mkdir()
    (tmp_path / "reports" / "trials.md").write_text("# Trials\n\n## Allocentric attitude\n\nkept\n")
    bt.main([str(run)])
    page = (tmp_path / "reports" / "trials.md").read_text()
    assert "## Allocentric attitude\n\nkept" in page and "## Breaking eps on a finer grid" in page
    assert "| seed 0 | above 1.43, at most 2.80" in page
    assert "0.01: 0/4, 0.05: 0/4, 0.1: 0/4, 0.14: 1/4" in page
