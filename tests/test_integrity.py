"""Integrity metrics (pipeline/defense/integrity.py): the alert limit against the guidance law flown in
the loop, HMI / MI / availability and attack-caused harm on hand-made traces, the params that feed them."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pipeline.defense.fusion import COAST, HOLD, TRACK, DefenseTrace
from pipeline.defense.integrity import (
    AlertLimitSettings,
    IntegrityFrames,
    alert_limit,
    attack_hmi,
    attack_mi,
    clean_rates,
    concat,
    defense_frames,
    integrity_rates,
)
from pipeline.geometry.camera import reference_intrinsics
from pipeline.guidance.law import GuidanceSettings, run_rendezvous
from pipeline.stats import bootstrap_rate
from stages.config import params as params_mod
from stages.config.sections import ParamsError

K = reference_intrinsics().scaled(160, 90)
DEFAULT = AlertLimitSettings()
OTHER = AlertLimitSettings(tolerance=0.5, max_step=0.5, slack_steps=6, collision_range=4.0)


# ----------------------------------------------------------------------------- alert limit
def _fly(settings: AlertLimitSettings, start_range: float, error: np.ndarray) -> tuple[float, float]:
    """The paper guidance law from 60 m to the 10 m goal with the budget the guidance stage gives (nominal
    steps + slack); the one frame at `start_range` carries `error` (world frame, m), every other estimate is
    exact -> (final miss (m), smallest true range (m))."""
    nominal = int(np.ceil((60.0 - 10.0) / settings.max_step))
    g = GuidanceSettings(
        tolerance=settings.tolerance, max_step=settings.max_step, max_steps=nominal + settings.slack_steps
    )

    def estimate(image, attacked, pose):  # pose = (R target -> camera, t camera); R_c = R^T (target attitude I)
        return pose[1] + (pose[0] @ error if attacked else 0.0)

    run = run_rendezvous(lambda R, t: None, estimate, K, g, g.window(start_range, 1))
    assert run.attack_start is not None and np.isclose(np.linalg.norm(run.positions[run.attack_start]), start_range)
    return run.miss, float(np.linalg.norm(run.positions, axis=1).min())


def _directions(seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    axes = [np.array(v, float) for v in ((0, 0, 1), (0, 0, -1), (1, 0, 0), (0, -1, 0), (0.6, 0, 0.8), (0, 0.6, -0.8))]
    return axes + [v / np.linalg.norm(v) for v in rng.normal(size=(12, 3))]


@pytest.mark.parametrize("settings", [DEFAULT, OTHER], ids=["default", "other"])
@pytest.mark.parametrize("start_range", [60.0, 30.0, 12.0, 10.0])
def test_an_error_within_the_alert_limit_docks_and_one_above_it_does_not(settings, start_range):
    al = float(alert_limit(start_range, settings))
    for d in _directions():  # within AL, any direction: docks within tolerance, never inside the collision range
        miss, closest = _fly(settings, start_range, 0.98 * al * d)
        assert miss <= settings.tolerance + 1e-9 and closest >= settings.collision_range, (d, miss, closest)
    # just above AL, along the line of sight (outward: too late to dock; inward: a collision) one of them fails
    failed = []
    for d in (np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, -1.0])):
        miss, closest = _fly(settings, start_range, 1.02 * al * d)
        failed.append(miss > settings.tolerance or closest < settings.collision_range)
    assert any(failed)


def test_alert_limit_closed_form_floor_and_constants():
    """max(tol, min(tol + slack s, r + s - collision range)): the docking term far out, the collision
    term near the target, the tolerance below that; every constant moves it."""
    r = np.array([60.0, 30.0, 15.0, 10.0, 6.0, 5.0, 2.0])
    al = alert_limit(r, DEFAULT)
    docking = DEFAULT.tolerance + DEFAULT.slack_steps * DEFAULT.max_step
    assert np.all(al[r >= DEFAULT.collision_range + docking - DEFAULT.max_step] == docking)
    assert np.allclose(al[3:5], r[3:5] + DEFAULT.max_step - DEFAULT.collision_range)
    assert np.all(al[5:] == DEFAULT.tolerance) and np.all(np.diff(al) <= 0)
    for change in ({"tolerance": 2.0}, {"max_step": 2.0}, {"slack_steps": 3}, {"collision_range": 8.0}):
        assert not np.array_equal(alert_limit(r, dataclasses.replace(DEFAULT, **change)), al), change


@pytest.mark.parametrize(
    "change, message",
    [
        ({"tolerance": 0.0}, "tolerance must be > 0"),
        ({"max_step": -1.0}, "max_step must be > 0"),
        ({"collision_range": 0.0}, "collision_range must be > 0"),
        ({"slack_steps": -1}, "slack_steps must be"),
    ],
)
def test_alert_limit_settings_refuse_bad_constants(change, message):
    with pytest.raises(ValueError, match=message):
        AlertLimitSettings(**change)


# ----------------------------------------------------------------------------- records and rates
RANGES = np.array([60.0, 30.0, 10.0, 6.0])  # AL 11, 11, 6, 2 m with the default constants


def _run(name: str, errors: list[float], modes: list[str], pl: list[float] | None = None) -> IntegrityFrames:
    """A hand-made run: truth on the line of sight at RANGES, trusted = truth + error along z (NaN: none)."""
    truth = np.c_[np.zeros((4, 2)), RANGES]
    trusted = truth + np.c_[np.zeros((4, 2)), errors]
    n = len(modes)
    trace = DefenseTrace(
        np.zeros(n, bool),
        np.zeros(n, bool),
        np.zeros(n, bool),
        trusted,
        np.array(modes),
        np.full(n, np.nan),
        np.full(n, np.nan),
    )
    return defense_frames(trace, truth, name, DEFAULT, None if pl is None else np.array(pl))


T, C, H, NAN = TRACK, COAST, HOLD, float("nan")
CLEAN = concat(
    [
        _run("A", [0, 12, 0, 0], [T, T, T, T]),  # HMI at 1 (12 > 11)
        _run("B", [NAN, 0.5, 7, 3], [H, T, C, H]),  # HMI at 2 (coasting, 7 > 6); 3 is held
        _run("C", [0, 0, 0, 0], [T, T, T, T]),
    ]
)
ATTACKED = concat(
    [
        _run("A", [20, 12, 0, 0], [T, T, T, T]),  # HMI at 0 (caused) and 1 (also clean)
        _run("B", [NAN, 12, 7, 3], [H, T, C, T]),  # HMI at 1 and 3 (caused), 2 (also clean)
        _run("C", [0, 0, 50, 0], [T, T, H, T]),
    ]
)  # 50 m, but held: not HMI
GROUPS = np.repeat(["A", "B", "C"], 4)


def test_hmi_and_availability_on_a_hand_made_trace():
    assert np.allclose(CLEAN.alert, np.tile([11.0, 11.0, 6.0, 2.0], 3))
    assert np.flatnonzero(CLEAN.hmi).tolist() == [1, 6]
    assert np.flatnonzero(~CLEAN.available).tolist() == [4, 7]  # B's held frames
    assert np.flatnonzero(ATTACKED.hmi).tolist() == [0, 1, 5, 6, 7]
    assert np.isnan(CLEAN.error[4]) and not ATTACKED.mi.any()  # no PL: no MI
    rates = clean_rates(CLEAN)
    assert rates["availability"].value == pytest.approx(10 / 12) and rates["hmi"].value == pytest.approx(2 / 12)
    assert rates["availability"] == bootstrap_rate(CLEAN.available, GROUPS)  # intervals over trajectories
    assert rates["mi"].n == 0 and rates["frames"] == 12
    assert rates["trusted_error_max_m"] == 12.0


def test_attack_harm_counts_only_what_the_attack_caused():
    caused = attack_hmi(ATTACKED, CLEAN)
    assert np.flatnonzero(caused).tolist() == [0, 5, 7]  # 1 and 6 are HMI without the attack too
    r = integrity_rates(ATTACKED, CLEAN)
    assert r["hmi"].value == pytest.approx(3 / 12) and r["hmi_attacked"].value == pytest.approx(5 / 12)
    assert r["hmi_clean"].value == pytest.approx(2 / 12) and r["availability"].value == pytest.approx(10 / 12)
    assert r["hmi"] == bootstrap_rate(caused, GROUPS) and r["hmi"].lo <= r["hmi"].value <= r["hmi"].hi
    assert r["trusted_error_max_m"] == 50.0 and r["frames"] == 12
    first = np.tile([True, True, False, False], 3)  # count only the first two frames
    r = integrity_rates(ATTACKED, CLEAN, mask=first)
    assert r["frames"] == 6 and r["hmi"].value == pytest.approx(2 / 6) and r["hmi_clean"].value == pytest.approx(1 / 6)


def test_attacked_and_clean_runs_must_hold_the_same_frames():
    other = concat([_run("A", [0] * 4, [T] * 4), _run("C", [0] * 4, [T] * 4), _run("B", [0] * 4, [T] * 4)])
    with pytest.raises(ValueError, match="same frames of the same trajectories"):
        attack_hmi(ATTACKED, other)
    with pytest.raises(ValueError, match="unknown defense modes"):
        _run("A", [0] * 4, [T, T, "lost", T])


def test_protection_level_gates_availability_and_defines_mi():
    """PL > AL: not available, so a large error is not HMI; error > PL: MI; NaN PL: no MI, not available."""
    clean = concat(
        [
            _run("A", [0.2, 15, 0.2, 0.1], [T] * 4, pl=[0.5, 20, 1.0, NAN]),
            _run("B", [1.0, 0, 0, 0], [T] * 4, pl=[0.5, 0.5, 0.5, 0.5]),
        ]
    )
    assert np.flatnonzero(clean.available).tolist() == [0, 2, 4, 5, 6, 7]
    assert not clean.hmi.any()  # 15 m > AL, but PL 20 m > AL: unavailable
    assert np.flatnonzero(clean.mi).tolist() == [4]  # 1.0 m > PL 0.5 m
    assert clean_rates(clean)["mi"].value == pytest.approx(1 / 7)  # over the 7 frames with a PL
    attacked = concat(
        [
            _run("A", [0.9, 15, 0.2, 0.1], [T] * 4, pl=[0.5, 20, 1.0, NAN]),
            _run("B", [1.0, 0.8, 0, 0], [T] * 4, pl=[0.5, 0.5, 0.5, 0.5]),
        ]
    )
    assert np.flatnonzero(attack_mi(attacked, clean)).tolist() == [0, 5]  # 4 is MI without the attack too
    assert integrity_rates(attacked, clean)["mi"].value == pytest.approx(2 / 7)


# ----------------------------------------------------------------------------- params
@pytest.mark.parametrize(
    "value, message",
    [
        (0.0, r"^params.yaml integrity.collision_range_m must be > 0 \(metres\), got 0.0$"),
        (-5, r"^params.yaml integrity.collision_range_m must be > 0 \(metres\), got -5$"),
        (10.0, r"^params.yaml integrity.collision_range_m must be below the goal range \|guidance.target\| = 10 m"),
        ("near", r"^params.yaml integrity.collision_range_m must be a number, got 'near'$"),
    ],
)
def test_bad_integrity_params_give_one_line_naming_the_param(tmp_path, monkeypatch, value, message):
    monkeypatch.chdir(tmp_path)
    p = params_mod.compose("smoke")
    p["integrity"]["collision_range_m"] = value
    params_mod.write_params(p)
    with pytest.raises(ParamsError, match=message) as e:
        params_mod.load()
    assert "\n" not in str(e.value)


@pytest.mark.parametrize(
    "key, value, name",
    [
        ("tolerance", 0.0, "guidance.tolerance"),
        ("max_step", -1.0, "guidance.max_step"),
        ("slack_steps", -2, "guidance.slack_steps"),
    ],
)
def test_alert_limit_builder_names_the_guidance_param(key, value, name):
    from stages.config.build import alert_limit_settings
    from stages.config.schema import build
    from stages.errors import StageError

    p = build(params_mod.compose("default"))
    assert alert_limit_settings(p) == AlertLimitSettings(
        float(p.guidance.tolerance),
        float(p.guidance.max_step),
        p.guidance.slack_steps,
        float(p.integrity.collision_range_m),
        None,
        float(np.linalg.norm(p.guidance.target)),  # the goal range, metres
        p.integrity.alert_limit_kind,
    )
    bad = dataclasses.replace(p, guidance=dataclasses.replace(p.guidance, **{key: value}))
    with pytest.raises(StageError, match=rf"^params.yaml {name}: alert limit: {key} must be"):
        alert_limit_settings(bad)
