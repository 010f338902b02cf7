"""Bad integrity params are one line naming the param: an alert limit that is not positive, an unknown
attacker or goal, eps outside (0, 1], a collision range that is not positive, a drift longer than a
trajectory, an in-loop start range off the approach; and the builders hand the library what params say."""
from __future__ import annotations

import dataclasses

import pytest

from stages.config import params as params_mod
from stages.config.sections import ParamsError


@pytest.mark.parametrize("key, value, message", [
    ("alert_limit_m", 0.0, r"^params.yaml integrity.alert_limit_m must be null or > 0 \(metres\), got 0.0$"),
    ("alert_limit_m", -3, r"^params.yaml integrity.alert_limit_m must be null or > 0 \(metres\), got -3$"),
    ("attackers", ["burst", "jitter"], r"^params.yaml integrity.attackers\[1\] must be one of burst, drift/los, "
                                        r"drift/lateral, got 'jitter'$"),
    ("in_loop_goals", ["ram"], r"^params.yaml integrity.in_loop_goals\[0\] must be one of collide, miss, got 'ram'$"),
    ("eps", [0.01, 1.5], r"^params.yaml integrity.eps: 1.5 is not in \(0, 1\]"),
    ("eps", [0.0], r"^params.yaml integrity.eps: 0.0 is not in \(0, 1\]"),
    ("eps", [0.01, 0.01], r"^params.yaml integrity.eps must be a non-empty list without repeats"),
    ("collision_range_m", -1.0, r"^params.yaml integrity.collision_range_m must be > 0 \(metres\), got -1.0$"),
    ("drift_frames", 200, r"^params.yaml integrity.drift_start \+ integrity.drift_frames \(40 \+ 200\) must be at "
                          r"most evaluate.frames = 200"),
    ("burst_restarts", 0, r"^params.yaml integrity.burst_restarts must be a positive whole number"),
])
def test_bad_integrity_params_are_one_line_naming_the_param(tmp_path, monkeypatch, key, value, message):
    monkeypatch.chdir(tmp_path)
    p = params_mod.compose("default")
    p["integrity"][key] = value
    params_mod.write_params(p)
    with pytest.raises(ParamsError, match=message) as e:
        params_mod.load()
    assert "\n" not in str(e.value)


def test_an_in_loop_start_range_off_the_approach_is_one_line():
    from stages.config.schema import build
    from stages.errors import StageError
    from stages.guidance import _in_loop, _plan

    p = build(params_mod.compose("default"))
    settings, _ = _plan(p.guidance)
    assert _in_loop(p.integrity, settings) == tuple((e, g, s) for e in (0.01, 0.05) for g in ("collide", "miss")
                                                    for s in (20.0,))
    bad = dataclasses.replace(p.integrity, in_loop_start_ranges=[30.0, 80.0])
    with pytest.raises(StageError, match=r"^params.yaml integrity.in_loop_start_ranges: attack start range S=80.0 m"):
        _in_loop(bad, settings)


def test_the_builders_follow_the_params():
    from pipeline.defense.integrity import alert_limit
    from stages.config.build import alert_limit_settings, burst_attacker, drift_settings, in_loop_settings
    from stages.config.schema import build

    p = build(params_mod.compose("default"))
    attacker = burst_attacker(p, seed=7)
    assert (attacker.steps, attacker.restarts, attacker.lambdas, attacker.cap, attacker.seed) == (50, 3, (0.0, 10.0),
                                                                                                  2.0, 7)
    assert float(attacker.alert_limit(60.0)) == float(alert_limit(60.0, alert_limit_settings(p))) == 11.0
    fixed = dataclasses.replace(p, integrity=dataclasses.replace(p.integrity, alert_limit_m=2.5))
    assert alert_limit_settings(fixed).fixed == 2.5 and float(burst_attacker(fixed, 0).alert_limit(30.0)) == 2.5
    assert float(alert_limit(60.0, alert_limit_settings(fixed))) == 2.5   # the defense's AL too (PL > AL: unavailable)
    assert drift_settings(p, "lateral").direction == "lateral" and drift_settings(p, "los").gate_fraction == 0.5
    assert in_loop_settings(p, "miss").goal == "miss" and in_loop_settings(p, "collide").steps == 10
