"""pipeline/evaluation.py: per-eps summaries, the report tables and the JSON-safe NaN helper."""
from __future__ import annotations

import json
import math

import pytest

from pipeline.evaluation import accuracy_table, detail_table, nan_to_none, per_eps_summary


def _row(eps, seq, acc, und, und_pos, delay):
    return {"eps": eps, "sequence": seq, "accuracy": acc, "tpr": acc, "fpr": 1 - acc, "mean_delay": delay,
            "missed_bursts": 1, "bursts": 4, "undetected_frames": und, "undetected_position_m": und_pos,
            "attacked_position_m": 2.0}


def test_per_eps_summary_averages_sequences_and_weights_undetected_errors():
    rows = [_row(0.5, "T1", 1.0, 0, float("nan"), float("nan")), _row(0.5, "T2", 0.8, 3, 4.0, 2.0),
            _row(0.05, "T1", 0.6, 1, 1.0, 1.0), _row(0.05, "T2", 0.4, 3, 3.0, 3.0)]
    s = {r["eps"]: r for r in per_eps_summary(rows)}
    assert list(s) == [0.5, 0.05]                                     # the rows' eps order
    assert s[0.5]["accuracy"] == pytest.approx(0.9) and s[0.5]["mean_delay"] == 2.0
    assert s[0.5]["undetected_position_m"] == pytest.approx(4.0)      # the NaN of 0 frames weighs nothing
    assert s[0.05]["undetected_position_m"] == pytest.approx((1 * 1.0 + 3 * 3.0) / 4)
    assert s[0.05]["missed_bursts"] == 2 and s[0.05]["bursts"] == 8

    table = accuracy_table(rows, list(s.values()), ["T1", "T2"], {0.5: 100.0})
    assert [r["eps"] for r in table] == ["0.5", "0.05", "average"]
    assert table[0]["T2"] == pytest.approx(80.0) and table[1]["paper (average)"] == "-"
    assert table[2]["T1"] == pytest.approx(80.0) and table[2]["average"] == pytest.approx(70.0)
    assert detail_table([{**s[0.5], "mean_delay": float("nan")}])[0]["mean delay (frames)"] == "-"


def test_nan_to_none_makes_results_json_safe():
    out = nan_to_none({"a": float("nan"), "b": [1.0, float("nan"), {"c": math.nan}], "d": "x"})
    assert out == {"a": None, "b": [1.0, None, {"c": None}], "d": "x"}
    json.dumps(out, allow_nan=False)
