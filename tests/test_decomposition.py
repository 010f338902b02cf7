"""Issue 38's attitude decomposition: errors split by target-attitude group with bootstrap intervals over sequences,
and the paper-like labels option (one target attitude per rotating sequence)."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.geometry.rotations import matrix_to_6d
from pipeline.geometry.trajectories import approach_sequences, attitude_groups, flatten
from pipeline.pose.decomposition import (
    bootstrap_contrast,
    bootstrap_difference,
    bootstrap_mean,
    bootstrap_model_difference,
    group_errors,
)


def test_the_default_sequences_are_unchanged_and_paper_like_ones_hold_one_attitude_per_sequence():
    default, explicit = approach_sequences(20, seed=3), approach_sequences(20, seed=3, attitude="per_frame")
    assert all(np.array_equal(a.R, b.R) and np.array_equal(a.t, b.t) for a, b in zip(default, explicit))
    paper = approach_sequences(20, seed=3, attitude="per_sequence")
    for s in paper:
        same = np.allclose(s.R_target, s.R_target[0])
        assert same  # one attitude for the whole sequence
        assert np.allclose(s.R_target[0], np.eye(3)) == (s.sequence < 5)  # 0 on the fixed, drawn on the rotating
    assert not np.allclose(default[7].R_target, default[7].R_target[0])  # today's: afresh every frame
    angle = np.rad2deg(np.arccos((np.trace(paper[7].R_target[0]) - 1) / 2))
    assert 0 < angle <= np.sqrt(3) * 10 + 1e-6
    with pytest.raises(ValueError, match="per_frame, per_sequence"):
        approach_sequences(20, attitude="per_run")


def test_attitude_groups_name_the_fixed_and_the_rotating_sequences():
    seq, _, _, _ = flatten(approach_sequences(4))
    groups = attitude_groups(seq)
    assert (groups == "fixed").sum() == 5 * 4 and (groups == "rotating").sum() == 8 * 4


def test_bootstrap_over_sequences_is_wider_when_sequences_differ():
    rng = np.random.default_rng(0)
    seq = np.repeat(np.arange(8), 100)
    alike = rng.normal(2.0, 0.5, 800)
    unlike = alike + np.repeat(rng.normal(0, 1.0, 8), 100)  # a per-sequence offset: correlated frames
    m, lo, hi = bootstrap_mean(alike, seq)
    m2, lo2, hi2 = bootstrap_mean(unlike, seq)
    assert lo < m < hi and lo2 < m2 < hi2
    assert hi2 - lo2 > 3 * (hi - lo)
    assert bootstrap_mean(np.ones(5), np.zeros(5)) == (1.0, 1.0, 1.0)


def test_the_difference_between_groups_and_its_interval():
    rng = np.random.default_rng(1)
    seq = np.repeat(np.arange(13), 50)
    a = seq < 5
    values = np.where(a, 1.5, 3.0) + rng.normal(0, 0.3, seq.size)
    d, lo, hi = bootstrap_difference(values, seq, a)
    assert d == pytest.approx(-1.5, abs=0.1) and lo < d < hi < 0
    with pytest.raises(ValueError, match="both sides"):
        bootstrap_difference(values, seq % 2, a)


def test_the_interaction_of_two_changes_is_zero_when_they_add_and_found_when_they_do_not():
    """ab - a - b + s: the combined change's contribution minus the two alone (paired by sequence)."""
    rng = np.random.default_rng(2)
    seq = np.repeat(np.arange(13), 40)
    offset = np.repeat(rng.normal(0, 0.5, 13), 40)  # per-sequence difficulty: shared, so it cancels when paired
    s = 3.0 + offset + rng.normal(0, 0.1, seq.size)
    a, b = s - 1.0, s - 0.5
    sides = [(a - 0.5, seq), (a, seq), (b, seq), (s, seq)]
    weights = [1.0, -1.0, -1.0, 1.0]
    d, lo, hi = bootstrap_contrast(sides, weights)  # additive: ab = s - 1.5
    assert d == pytest.approx(0.0, abs=1e-9) and lo <= d <= hi and hi - lo < 1e-9
    d, lo, hi = bootstrap_contrast([(a - 0.2, seq), *sides[1:]], weights)  # they overlap: ab = s - 1.2
    assert d == pytest.approx(0.3) and 0 < lo < d < hi
    assert bootstrap_contrast(sides[1:3], [1.0, -1.0]) == bootstrap_model_difference(a, seq, b, seq)
    with pytest.raises(ValueError, match="same sequences"):
        bootstrap_contrast([(a, seq), (b, seq % 5)], [1.0, -1.0])
    with pytest.raises(ValueError, match="one weight per side"):
        bootstrap_contrast(sides, [1.0])


def test_group_errors_split_the_errors_by_group():
    seq, _, R, t = flatten(approach_sequences(6, seed=0))
    target = np.column_stack([t, matrix_to_6d(R)])
    pred = target.copy()
    pred[:, 2] += np.where(seq < 5, 0.1, 0.4)  # range errors 0.1 m (fixed) and 0.4 m (rotating)
    out = group_errors(pred, target, seq, attitude_groups(seq))
    assert out["fixed"]["frames"] == 30 and out["rotating"]["sequences"] == 8
    assert out["fixed"]["position_m"][0] == pytest.approx(0.1) and out["rotating"]["position_m"][0] == pytest.approx(
        0.4
    )
    assert out["fixed"]["attitude_deg"][0] == pytest.approx(0.0, abs=1e-5)


def test_the_default_target_attitude_leaves_the_render_fingerprint_as_it_was():
    """Renders made before `render.target_attitude` existed stay valid; paper-like labels are another render."""
    from stages.config import params as params_mod
    from stages.config.schema import build

    p = build(params_mod.compose("default", []))
    paper = build(params_mod.compose("default", ["render.target_attitude=per_sequence"]))
    assert p.render.target_attitude == "per_frame"
    assert "target_attitude" not in params_mod.render_key(p)
    assert params_mod.render_key(paper)["target_attitude"] == "per_sequence"
    assert params_mod.render_fingerprint(paper) != params_mod.render_fingerprint(p)
