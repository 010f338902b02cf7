"""pipeline/evaluation/sequences.py: per-eps summaries, the report tables and the JSON-safe NaN helper."""

from __future__ import annotations

import json
import math

import pytest

from pipeline.evaluation.sequences import accuracy_table, detail_table, nan_to_none, per_eps_summary


def _row(eps, seq, acc, und, und_pos, delay):
    return {
        "eps": eps,
        "sequence": seq,
        "accuracy": acc,
        "tpr": acc,
        "fpr": 1 - acc,
        "mean_delay": delay,
        "missed_bursts": 1,
        "bursts": 4,
        "undetected_frames": und,
        "undetected_position_m": und_pos,
        "attacked_position_m": 2.0,
        "frames": 100,
        "correct": round(100 * acc),
        "attacked_frames": 20,
        "flagged_attacked": round(20 * acc),
        "clean_frames": 80,
        "flagged_clean": round(80 * (1 - acc)),
    }


def test_per_eps_summary_averages_sequences_and_weights_undetected_errors():
    rows = [
        _row(0.5, "T1", 1.0, 0, float("nan"), float("nan")),
        _row(0.5, "T2", 0.8, 3, 4.0, 2.0),
        _row(0.05, "T1", 0.6, 1, 1.0, 1.0),
        _row(0.05, "T2", 0.4, 3, 3.0, 3.0),
    ]
    s = {r["eps"]: r for r in per_eps_summary(rows)}
    assert list(s) == [0.5, 0.05]  # the rows' eps order
    assert s[0.5]["accuracy"] == pytest.approx(0.9) and s[0.5]["mean_delay"] == 2.0
    assert s[0.5]["undetected_position_m"] == pytest.approx(4.0)  # the NaN of 0 frames weighs nothing
    assert s[0.05]["undetected_position_m"] == pytest.approx((1 * 1.0 + 3 * 3.0) / 4)
    assert s[0.05]["missed_bursts"] == 2 and s[0.05]["bursts"] == 8

    table = accuracy_table(rows, list(s.values()), ["T1", "T2"], {0.5: 100.0})
    assert [r["eps"] for r in table] == ["0.5", "0.05", "average"]
    assert table[0]["T2"] == pytest.approx(80.0) and table[1]["paper (average)"] == "-"
    assert table[2]["T1"] == pytest.approx(80.0) and table[2]["average"] == pytest.approx(70.0)
    assert detail_table([{**s[0.5], "mean_delay": float("nan")}])[0]["mean delay (frames)"] == "-"
    # intervals: a bootstrap over the two sequences, around the pooled rate
    lo, hi = s[0.05]["accuracy_ci95"]
    assert lo <= 0.5 <= hi and lo >= 0.4 - 1e-9 and hi <= 0.6 + 1e-9
    assert s[0.5]["fpr_ci95"][0] <= 0.1 <= s[0.5]["fpr_ci95"][1]
    assert table[1]["95% interval"] == f"[{100 * lo:.1f}, {100 * hi:.1f}]"


def test_nan_to_none_makes_results_json_safe():
    out = nan_to_none({"a": float("nan"), "b": [1.0, float("nan"), {"c": math.nan}], "d": "x"})
    assert out == {"a": None, "b": [1.0, None, {"c": None}], "d": "x"}
    json.dumps(out, allow_nan=False)


def _approach(n=60, seed=0, offset=(4.0, 0.0, 3.0), attacked=None):
    """A straight approach rel (world, m) with a still camera looking along +z, seeded estimate noise
    and `offset` (camera frame, m) on the attacked frames, which the detector does not see (prob 0)."""
    import numpy as np

    from pipeline.geometry.rotations import matrix_to_6d

    rng = np.random.default_rng(seed)
    rel = np.column_stack([np.full(n, 2.0), np.full(n, -1.0), np.linspace(40.0, 25.25, n)])
    R_cam = np.repeat(np.eye(3)[None], n, axis=0)
    u = np.zeros((n, 3))
    u[1:] = np.diff(rel, axis=0)
    att = np.zeros(n, bool) if attacked is None else attacked
    est = rel + rng.normal(0, 0.03, (n, 3)) + np.where(att[:, None], np.asarray(offset), 0.0)
    pose = np.column_stack([est, np.repeat(matrix_to_6d(np.eye(3))[None], n, axis=0)])
    err = np.linalg.norm(est - rel, axis=1)
    return rel, R_cam, u, att, pose, err


def test_defended_summary_flags_what_the_detector_misses_with_intervals():
    import numpy as np

    from pipeline.defense.gate import MotionSettings
    from pipeline.defense.noise import NoiseModel
    from pipeline.defense.settings import DefenseSettings
    from pipeline.evaluation.sequences import Sequence, Trace, defended_summary, defense_table, rates_json

    noise = NoiseModel((0.05, 0.05, 0.1), (0.0, 0.0, 0.0), 1.0, 0.0)
    traces, seqs = {}, []
    for g in range(3):
        att = np.zeros(60, bool)
        att[20 + g : 30 + g] = True
        rel, R_cam, u, att, pose, err = _approach(seed=g, attacked=att)
        _, _, _, _, clean_pose, clean_err = _approach(seed=10 + g)
        name = f"T{g + 1}"
        seqs.append(
            Sequence(
                name=name,
                images=np.zeros((60, 1, 1, 3), np.uint8),
                targets=pose.astype(np.float32),
                attacked=att,
                rel=rel,
                R_cam=R_cam,
                u=u,
            )
        )
        traces[(0.5, name)] = Trace(
            prob=np.zeros(60), flag=np.zeros(60, bool), position_error=err, estimate_z=pose[:, 2], pose=pose
        )
        traces[(0.0, name)] = Trace(
            prob=np.zeros(60),
            flag=np.zeros(60, bool),
            position_error=clean_err,
            estimate_z=clean_pose[:, 2],
            pose=clean_pose,
        )
    chains = {
        f: defended_summary(traces, seqs, [0.5], DefenseSettings(fusion=f), MotionSettings(), noise, 10, 1.0)
        for f in ("paper", "or")
    }
    paper, fused = chains["paper"][0], chains["or"][0]
    assert paper["tpr"].value == 0.0 and paper["harmful_undetected"].value == 1.0  # the detector sees nothing
    assert fused["tpr"].value == 1.0 and fused["harmful_flagged"].value == 1.0 and fused["harmful_frames"] == 30
    assert fused["fpr_clean"].value == 0.0 and fused["fpr"].value <= 0.02 and fused["mean_delay"] == 0.0
    assert fused["accuracy"].n == 180 and fused["accuracy"].lo <= fused["accuracy"].value <= fused["accuracy"].hi
    assert fused["trusted_error_attacked_m"] < 0.5  # coasting through the attack, not trusting it
    rows = defense_table({"paper": chains["paper"], "fused": chains["or"]})
    assert [(r["eps"], r["chain"]) for r in rows] == [("0.5", "paper"), ("0.5", "fused")]
    assert rows[1]["TPR %"].startswith("100.0 [") and rates_json(chains["or"])[0]["tpr"]["n"] == 30
