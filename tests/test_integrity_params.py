"""Bad integrity params are one line naming the param: an alert limit that is not positive, an unknown
attacker, goal or AL kind, eps outside (0, 1] or not increasing, a collision range that is not positive, a drift
start that is not a start, a capture bias that is not positive, an execution error out of range, an in-loop start
range off the approach; and the builders hand the library what params say."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from stages.config import params as params_mod
from stages.config.sections import ParamsError


@pytest.mark.parametrize(
    "key, value, message",
    [
        ("alert_limit_m", 0.0, r"^params.yaml integrity.alert_limit_m must be null or > 0 \(metres\), got 0.0$"),
        ("alert_limit_m", -3, r"^params.yaml integrity.alert_limit_m must be null or > 0 \(metres\), got -3$"),
        (
            "attackers",
            ["burst", "jitter"],
            r"^params.yaml integrity.attackers\[1\] must be one of burst, drift/los, "
            r"drift/lateral, capture/los, capture/lateral, got 'jitter'$",
        ),
        (
            "in_loop_goals",
            ["ram"],
            r"^params.yaml integrity.in_loop_goals\[0\] must be one of collide, miss, capture, "
            r"got 'ram'$",
        ),
        (
            "alert_limit_kind",
            "both",
            r"^params.yaml integrity.alert_limit_kind must be one of single_frame, persistent",
        ),
        ("eps", [0.05, 0.01], r"^params.yaml integrity.eps must be increasing \(the breaking point's grid\)"),
        ("in_loop_eps", [0.05, 2.0], r"^params.yaml integrity.in_loop_eps: 2.0 is not in \(0, 1\]"),
        ("capture_initial", [0.0], r"^params.yaml integrity.capture_initial\[0\] must be a positive number"),
        ("drift_start", 40, r"^params.yaml integrity.drift_start must be one of acquisition, after_trusted"),
        ("undefended_drift_rate", 0.0, r"^params.yaml integrity.undefended_drift_rate must be a positive number"),
        ("eps", [0.01, 1.5], r"^params.yaml integrity.eps: 1.5 is not in \(0, 1\]"),
        ("eps", [0.0], r"^params.yaml integrity.eps: 0.0 is not in \(0, 1\]"),
        ("eps", [0.01, 0.01], r"^params.yaml integrity.eps must be a non-empty list without repeats"),
        ("collision_range_m", -1.0, r"^params.yaml integrity.collision_range_m must be > 0 \(metres\), got -1.0$"),
        ("burst_restarts", 0, r"^params.yaml integrity.burst_restarts must be a positive whole number"),
        ("trajectories", 0, r"^params.yaml integrity.trajectories must be a positive whole number in \[1, 100000\]"),
    ],
)
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
    assert _in_loop(p.integrity, settings) == tuple(
        (e, g, 60.0 if g == "capture" else 20.0) for e in (0.01, 0.05, 0.1) for g in ("collide", "miss", "capture")
    )
    bad = dataclasses.replace(p.integrity, in_loop_start_ranges=[30.0, 80.0])
    with pytest.raises(StageError, match=r"^params.yaml integrity.in_loop_start_ranges: attack start range S=80.0 m"):
        _in_loop(bad, settings)


def test_the_builders_follow_the_params():
    from pipeline.attackers.burst import WIDE_LAMBDAS
    from pipeline.defense.integrity import alert_limit
    from stages.config.build import alert_limit_settings, burst_attacker, drift_settings, in_loop_settings
    from stages.config.schema import build

    p = build(params_mod.compose("default"))
    attacker = burst_attacker(p, seed=7)
    assert (attacker.steps, attacker.restarts, attacker.lambdas, attacker.cap, attacker.seed) == (
        50,
        3,
        WIDE_LAMBDAS,
        2.0,
        7,
    )
    assert (attacker.objective, attacker.hinge) == ("error_al", 0.5)
    assert float(attacker.alert_limit(60.0)) == float(alert_limit(60.0, alert_limit_settings(p))) == 51.0  # persistent
    assert float(alert_limit(10.0, alert_limit_settings(p))) == 1.0  # the tolerance
    assert float(alert_limit(10.0, alert_limit_settings(p, "single_frame"))) == 6.0
    fixed = dataclasses.replace(p, integrity=dataclasses.replace(p.integrity, alert_limit_m=2.5))
    assert alert_limit_settings(fixed).fixed == 2.5 and float(burst_attacker(fixed, 0).alert_limit(30.0)) == 2.5
    assert float(alert_limit(60.0, alert_limit_settings(fixed))) == 2.5  # the defense's AL too (PL > AL: unavailable)
    assert drift_settings(p, "lateral").direction == "lateral" and drift_settings(p, "los").gate_fraction == 0.5
    assert in_loop_settings(p, "miss").goal == "miss" and in_loop_settings(p, "collide").steps == 10


def test_the_execution_error_and_the_frame_attack_follow_the_params():
    """guidance.execution reaches the library with its seed; the evaluation's 0.25 m frames keep the closed loop's
    speed (2.5 s); the filter's process noise (defense.position_noise, position_noise_scale) is that error's std for
    any step: a guidance.max_step step and an evaluation frame's 0.25 m; the drift's and the
    capture's per-frame attack lifts the background and passes the clamp."""
    from pipeline.attackers.drift import TargetedPGD
    from stages.config.build import capture_settings, defense_settings, execution_settings, frame_attack
    from stages.config.schema import build

    p = build(params_mod.compose("default"))
    loop, frames = execution_settings(p, 5), execution_settings(p, 6, step=0.25)
    assert (loop.scale_std, loop.noise_std, loop.mean_motion, loop.frame_interval, loop.approach, loop.seed) == (
        0.02,
        0.01,
        0.0011,
        10.0,
        "vbar",
        5,
    )
    assert (frames.frame_interval, frames.seed) == (2.5, 6)
    motion = defense_settings(p.defense, 0.5)[1]
    for step in (p.guidance.max_step, 0.25):
        assert abs(motion.step_variance(step) ** 0.5 - loop.step_std(step)) < 1e-3
    assert frame_attack(p) == TargetedPGD(steps=p.integrity.frame_steps, start="lift", bpda=True)
    c = capture_settings(p, "los", 5.0)
    assert (c.direction, c.initial, c.rate, c.gate_fraction) == ("los", 5.0, 0.0, 0.5)
    with pytest.raises(ValueError, match="unknown execution approach 'hbar'"):  # the section refuses it when built
        dataclasses.replace(p.guidance.execution, approach="hbar")


def test_the_evaluation_and_validation_trajectories_follow_the_seed():
    """Issue 39 item 5: the trajectories' base seeds follow `seed` (hashed with the set's name: pipeline/seeds.py
    run_base), so seed runs fly other trajectories: other starts, other per-trajectory seeds (no run shares one),
    other fingerprints."""
    from pipeline.seeds import run_base, seed_for
    from stages.config.schema import build
    from stages.engine.trajectory_sets import trajectories

    runs = [build(params_mod.compose("default", [f"seed={k}"])) for k in range(6)]
    assert [(params_mod.evaluation_seed(p), params_mod.validation_seed(p)) for p in runs[:2]] == [
        (run_base(k, "evaluate"), run_base(k, "validation")) for k in range(2)
    ]
    bases = [(params_mod.evaluation_seed(p), params_mod.validation_seed(p)) for p in runs]
    drawn = [
        {
            seed_for(b, s, i)
            for b in pair
            for s in ("eval_render.trajectory", "eval_render.execution")
            for i in range(p.defense.val_trajectories)
        }
        for pair, p in zip(bases, runs)
    ]
    assert all(not (a & b) for i, a in enumerate(drawn) for b in drawn[i + 1 :])
    assert len({params_mod.eval_render_fingerprint(p) for p in runs}) == len(runs)
    assert len({params_mod.val_render_fingerprint(p) for p in runs}) == len(runs)
    starts = [tuple(np.round(s.rel[0], 6)) for p, (e, _) in zip(runs[:2], bases) for s in trajectories(p, e, 3)]
    assert len(set(starts)) == len(starts)


def test_the_full_grid_flies_every_attacker_and_the_drifts_from_both_starts():
    """`rpod integrity`'s grid: every attacker of the schema, each drift from acquisition and from the end of the
    trusted start (frame trusted_start + 1), no stop at the breaking point; the default flies one start and keeps the
    plain drift names its committed outputs carry. The page names each drift's start."""
    from stages.config.schema import build
    from stages.engine.campaigns import campaign_for, full_grid
    from stages.pages.integrity import attacker_names

    p = build(params_mod.compose("default"))
    default = campaign_for(p, 0, None, [])
    assert [(c.name, c.start) for c in default.plans] == [("capture/lateral 2 m", 0), ("drift/lateral", 0)]
    full = campaign_for(full_grid(p), 0, None, [])
    after = 1 + p.defense.trusted_start
    assert [(c.name, c.start) for c in full.plans if c.name.startswith("drift/")] == [
        ("drift/los acquisition", 0),
        ("drift/los after_trusted", after),
        ("drift/lateral acquisition", 0),
        ("drift/lateral after_trusted", after),
    ]
    assert {c.name for c in full.plans if c.name.startswith("capture/")} == {"capture/los 2 m", "capture/lateral 2 m"}
    assert full.burst is not None and not full.stop_at_break
    assert attacker_names("drift/lateral after_trusted") == "drift across it, from the end of the trusted start"
    assert attacker_names("drift/los") == "drift along the line of sight"
