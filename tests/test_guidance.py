"""Closed-loop guidance with stand-in renderers and estimators (no Blender, no torch)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pipeline.geometry.camera import reference_intrinsics
from pipeline.guidance.law import (
    DOCKED,
    LOST,
    MISSED,
    SUCCEEDED,
    GuidanceSettings,
    RendezvousResult,
    guidance_step,
    run_rendezvous,
)
from stages.config.sections import Execution, Guidance

K = reference_intrinsics().scaled(160, 90)


def blank(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    return np.zeros((K.height, K.width, 3), np.uint8)


def perfect(image, attacked, pose):
    return pose[1]


def biased(offset):
    """Perfect estimator, except `offset` (camera frame, m) added on attacked frames."""
    return lambda image, attacked, pose: pose[1] + (np.asarray(offset) if attacked else 0.0)


@pytest.mark.parametrize("variant", ["paper", "true_state"])
@pytest.mark.parametrize("start", [(0.0, 0.0, 60.0), (-15.0, 25.0, 60.0)])
def test_perfect_estimator_reaches_goal_with_bounded_steps(variant, start):
    s = GuidanceSettings(start=start, variant=variant, max_steps=60)
    r = run_rendezvous(blank, perfect, K, s)
    assert r.outcome == DOCKED and r.miss < 1e-9
    assert len(r.positions) == 61 and not r.attacked.any()
    steps = np.abs(np.diff(r.positions, axis=0))
    assert steps.max() <= 1.0 + 1e-9
    assert np.isclose(steps[0], np.minimum(np.abs(np.subtract(start, (0, 0, 10))), 1.0)).all()
    assert np.allclose(r.estimates, r.positions[:-1])


def test_law_moves_at_most_max_step_from_the_estimate():
    rng = np.random.default_rng(0)
    goal = np.array([0.0, 0.0, 10.0])
    for _ in range(200):
        est, rel = rng.normal(0, 30, 3), rng.normal(0, 30, 3)
        nxt_paper, believed = guidance_step(est, rel, goal, 1.0, "paper")
        nxt_true, _ = guidance_step(est, rel, goal, 1.0, "true_state")
        assert np.abs(believed - est).max() <= 1.0 + 1e-12
        assert np.allclose(nxt_paper, believed)
        assert np.abs(nxt_true - rel).max() <= 1.0 + 1e-12
        assert np.allclose(nxt_true - rel, believed - est)


@pytest.mark.parametrize("variant", ["paper", "true_state"])
def test_five_metres_off_for_20_frames_near_the_end_fails(variant):
    s = GuidanceSettings(variant=variant, max_steps=60)
    r = run_rendezvous(blank, biased([5.0, 0.0, 0.0]), K, s, s.window(20, 20))
    assert r.outcome in (SUCCEEDED, LOST)
    assert r.miss > s.tolerance
    assert r.attack_start == 40  # range 20 m after 40 one-metre steps
    assert r.attacked[40:].all() and not r.attacked[:40].any()


def test_early_attack_is_recovered_and_window_is_counted():
    s = GuidanceSettings(max_steps=60)
    r = run_rendezvous(blank, biased([5.0, 0.0, 0.0]), K, s, s.window(60, 5))
    assert r.attack_start == 0 and r.attacked_frames == 5
    assert r.outcome == DOCKED and r.miss < 1e-9


def test_true_state_variant_loses_the_target_when_the_camera_follows_a_bad_estimate():
    s = GuidanceSettings(variant="true_state", max_steps=60)
    r = run_rendezvous(blank, biased([12.0, 0.0, 0.0]), K, s, s.window(30, 15))
    assert r.outcome == LOST
    assert len(r.positions) < 61


def test_a_miss_without_attack_is_not_called_an_attack_success():
    s = GuidanceSettings(max_steps=30)  # too few steps to cover 50 m
    r = run_rendezvous(blank, perfect, K, s)
    assert r.outcome == MISSED and r.miss == pytest.approx(20.0)


def test_render_gets_the_pose_the_camera_sees():
    seen = []

    def render(R, t):
        seen.append((R, t))
        return blank(R, t)

    s = GuidanceSettings(start=(10.0, -20.0, 60.0), max_steps=3)
    run_rendezvous(render, perfect, K, s)
    for R, t in seen:
        assert np.allclose(R @ R.T, np.eye(3)) and np.isclose(np.linalg.det(R), 1.0)
        assert np.allclose(t[:2], 0.0, atol=1e-9) and t[2] > 0  # camera points at the target


def test_bad_inputs_raise_clear_errors():
    s = GuidanceSettings()
    with pytest.raises(ValueError, match="outside the trajectory"):
        s.window(70, 5)
    with pytest.raises(ValueError, match="outside the trajectory"):
        s.window(5, 5)
    with pytest.raises(ValueError, match="at least 1 frame"):
        s.window(40, 0)
    with pytest.raises(ValueError, match="unknown guidance variant"):
        GuidanceSettings(variant="magic")


def _params(**changes: object) -> Guidance:
    g = {
        "eps": [0.5, 0.05],
        "start_ranges": [60, 40, 20, 10],
        "lengths": [5, 15],
        "start": [0.0, 0.0, 60.0],
        "target": [0.0, 0.0, 10.0],
        "tolerance": 1.0,
        "max_step": 1.0,
        "max_steps": 60,
        "slack_steps": 10,
        "variant": "paper",
        "method": "fgsm",
        "dynamics": ["paper"],
        "defenses": ["hold"],
        "standard_defenses": [],
        "execution": Execution(
            scale_std=0.02, noise_std=0.01, mean_motion=0.0011, frame_interval=10.0, approach="vbar"
        ),
    }
    return Guidance(**{**g, **changes})


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"eps": [0.5, 1.5]}, r"guidance.eps: 1.5 is not in \(0, 1\]"),
        ({"eps": [0.0]}, r"guidance.eps: 0.0 is not in \(0, 1\]"),
        ({"method": "deepfool"}, "guidance.method: unknown attack 'deepfool'"),
        ({"start_ranges": [60, 70]}, "S=70.0 m is outside the trajectory"),
        ({"start_ranges": [5]}, "S=5.0 m is outside the trajectory"),
        ({"variant": "teleport"}, "unknown guidance variant 'teleport'"),
    ],
)
def test_stage_refuses_bad_params_before_rendering(changes, message):
    from stages.errors import StageError
    from stages.guidance import _plan

    with pytest.raises(StageError, match=message):
        _plan(_params(**changes))


def test_stage_plans_the_whole_grid():
    from stages.guidance import _plan

    settings, grid = _plan(_params())
    assert settings.max_steps == 60 and len(grid) == 2 * 4 * 2
    assert {(e, s, k) for e, s, k, _ in grid} == {
        (e, s, k) for e in (0.5, 0.05) for s in (60, 40, 20, 10) for k in (5, 15)
    }


def test_arrival_step_is_when_the_chaser_reaches_the_goal_for_good():
    from pipeline.guidance.law import RendezvousResult, arrival_step

    z = np.array([60.0, 30.0, 10.5, 14.0, 10.2, 10.0, 10.0])  # in, out again, then in for good
    run = RendezvousResult(
        np.stack([np.zeros_like(z), np.zeros_like(z), z], axis=1),
        np.zeros((6, 3)),
        np.zeros(6, bool),
        "docked",
        0.0,
        None,
    )
    assert arrival_step(run, (0.0, 0.0, 10.0), 1.0) == 4
    short = RendezvousResult(run.positions[:4], np.zeros((3, 3)), np.zeros(3, bool), "missed without attack", 4.0, None)
    assert arrival_step(short, (0.0, 0.0, 10.0), 1.0) is None


def _defense():
    from pipeline.defense.fusion import Defense
    from pipeline.defense.gate import MotionSettings
    from pipeline.defense.noise import NoiseModel
    from pipeline.defense.settings import DefenseSettings

    return Defense(
        DefenseSettings(hold_after=20),
        MotionSettings(false_alarm=0.005),
        NoiseModel((0.05, 0.05, 0.1), (0.004, 0.004, 0.015), 1.0, 0.02),
    )


def noisy_attacked(offset, seed=0):
    """Small seeded estimate noise; `offset` (camera frame, m) on attacked frames, which the
    detector misses (probability 0): only the motion check can catch them."""
    from pipeline.guidance.law import Estimate

    rng = np.random.default_rng(seed)
    return lambda image, attacked, pose: Estimate(
        pose[1] + rng.normal(0, 0.03, 3) + (np.asarray(offset) if attacked else 0.0), 0.0
    )


@pytest.mark.parametrize("variant", ["paper", "true_state"])
def test_recovery_keeps_the_rendezvous_on_course_through_a_15_frame_attack(variant):
    from pipeline.defense.fusion import COAST

    s = GuidanceSettings(variant=variant, max_steps=60)
    attack = noisy_attacked([5.0, 0.0, 3.0])
    undefended = run_rendezvous(blank, attack, K, s, s.window(20, 15))
    assert undefended.outcome in (SUCCEEDED, LOST)
    r = run_rendezvous(
        blank,
        noisy_attacked([5.0, 0.0, 3.0]),
        K,
        dataclasses.replace(s, defense="recover"),
        s.window(20, 15),
        defense=_defense(),
    )
    assert r.outcome == DOCKED and r.miss < 0.5
    assert r.flags[r.attacked].all() and (r.modes[r.attacked] == COAST).all()
    assert not r.flags[~r.attacked].any()
    if variant == "true_state":  # the paper variant places the chaser at its (noisy) belief
        assert np.abs(np.diff(r.positions, axis=0)).max() <= 1.0 + 1e-9


def test_detect_and_hold_stops_the_chaser_while_flagged_and_resumes():
    s = GuidanceSettings(variant="true_state", max_steps=75, defense="hold")
    r = run_rendezvous(blank, noisy_attacked([5.0, 0.0, 3.0]), K, s, s.window(20, 15), defense=_defense())
    hit = np.flatnonzero(r.attacked)
    assert r.flags[hit].all()
    assert np.allclose(r.positions[hit + 1], r.positions[hit[0]])  # held in place during the attack
    assert r.outcome == DOCKED


def test_defense_settings_and_defense_object_must_agree():
    s = GuidanceSettings(defense="recover")
    with pytest.raises(ValueError, match="needs a Defense"):
        run_rendezvous(blank, perfect, K, s)
    with pytest.raises(ValueError, match="unknown guidance defense 'magic'"):
        GuidanceSettings(defense="magic")


def test_paper_variant_hold_reads_a_biased_estimate_as_bias_not_motion():
    """The paper variant lands the chaser at its belief: the defense must predict that point, or a
    steady range bias (here 0.3 m, clean frames) looks like a ramp and detect-and-hold never moves."""
    from pipeline.guidance.law import Estimate

    rng = np.random.default_rng(1)
    bias = np.array([0.0, 0.0, 0.3])
    estimate = lambda image, attacked, pose: Estimate(pose[1] + bias + rng.normal(0, 0.02, 3), 0.0)  # noqa: E731
    s = GuidanceSettings(variant="paper", max_steps=70, defense="hold")
    r = run_rendezvous(blank, estimate, K, s, defense=_defense())
    assert r.flags.sum() <= 1 and r.outcome == DOCKED


def test_the_defended_page_explains_the_paper_dynamics_clean_flags_and_only_when_there_are_some() -> None:
    """The paper dynamics puts the chaser at its belief, so a steady estimate error reaches the sequential test in
    a clean defended run: the page says why, with the undefended run's pace and the true-state counts beside."""
    from stages.config import params as params_mod
    from stages.config.schema import build
    from stages.pages.guidance import defended_section

    g = build(params_mod.compose("default")).guidance

    def block(flags, arrival):
        return {
            "baseline": {"outcome": "docked", "miss_m": 0.0, "arrival_step": arrival, "flags": flags},
            "docked": {},
            "not_met": {},
            "runs": [],
        }

    d = {
        "dynamics": {
            "paper": {"undefended": block(None, 36), "recover": block(28, 46)},
            "true_state": {"undefended": block(None, 50), "recover": block(4, 50)},
        }
    }
    text = defended_section(d, g)
    assert "Flags without an attack" in text and "28 flags with detect-and-recover" in text
    assert "arrives after 36 steps, not 50: about 0.39 m" in text and "(true_state: 4 with detect-and-recover)" in text
    d["dynamics"]["paper"]["recover"] = block(0, 46)
    assert "Flags without an attack" not in defended_section(d, g)


def test_a_recover_run_records_its_protection_and_says_why_its_last_hold_began():
    """run_rendezvous keeps, per defended frame, the PL, the AL it was judged against (at the trusted range) and the
    PL's parts (law.protection_parts, each <= the PL, together no more than it); a detect-and-recover chaser holds
    exactly where PL > AL (or the defense holds), and closed_loop.final_hold names the frame its last hold began with
    PL > AL there and a PL that did not shrink by the end; the guidance page says it in words."""
    from functools import partial

    from pipeline.defense.integrity import AlertLimitSettings, alert_limit
    from pipeline.evaluation.closed_loop import final_hold
    from pipeline.guidance.law import PROTECTION
    from stages.pages.guidance import hold_why

    d = _defense()
    d.alert_limit = partial(alert_limit, settings=AlertLimitSettings(kind="persistent", tolerance=0.3))
    s = GuidanceSettings(variant="true_state", max_steps=70, defense="recover")
    r = run_rendezvous(blank, noisy_attacked([0.0, 0.0, 0.0]), K, s, defense=d)
    assert r.protection.shape == (len(r.held), len(PROTECTION))
    pl, al, parts = r.protection[:, 0], r.protection[:, 1], r.protection[:, 2:]
    has = np.isfinite(pl)
    assert has.sum() > 20 and (parts[has] >= 0).all() and (parts[has].sum(axis=1) <= pl[has] + 1e-9).all()
    flown = has & (pl <= al) & (r.modes != "hold")
    assert np.array_equal(~flown, r.held)
    hold = final_hold(r)
    assert r.held[-1] and hold is not None and r.held[hold["frame"] :].all() and not r.held[hold["frame"] - 1]
    assert hold["pl_m"] > hold["al_m"] and hold["pl_end_m"] >= hold["pl_m"]
    assert hold["frames_held"] == len(r.held) - hold["frame"]
    text = hold_why(hold)
    assert f"held from frame {hold['frame']}" in text and f"> AL {hold['al_m']:.2f} m" in text
    assert hold_why(None) == "" and hold_why(dict(hold, pl_m=None)) == ""
    undefended = run_rendezvous(blank, perfect, K, GuidanceSettings(variant="true_state"))
    assert undefended.protection is None and final_hold(undefended) is None


def test_the_closed_loop_safety_index_fails_a_planted_persistent_bias() -> None:
    """Issue 39: what the guidance flew on is judged as a trajectory is: a 2 m lateral bias held to the 10 m goal
    is an error / AL of 2 there (AL 1 m, the docking tolerance) and of 2 / PL with a 1 m PL; a held frame (NaN)
    flies on nothing and does not count; a result made without `acted` has no index."""
    from functools import partial

    from pipeline.defense.integrity import AlertLimitSettings, alert_limit
    from pipeline.evaluation.closed_loop import safety_index
    from pipeline.guidance.law import PROTECTION

    positions = np.stack([np.zeros(53), np.zeros(53), np.arange(61.0, 8.0, -1.0)], axis=1)  # frames 61 m .. 10 m
    acted = positions[:-1] + [2.0, 0.0, 0.0]
    acted[0] = np.nan  # held on the first frame
    protection = np.full((52, len(PROTECTION)), np.nan)
    protection[:, 0] = 1.0
    run = RendezvousResult(positions, acted, np.ones(52, bool), "missed", 2.0, 0, protection=protection, acted=acted)
    index = safety_index(run, partial(alert_limit, settings=AlertLimitSettings(kind="persistent")))
    assert index["frames_flown"] == 51
    assert index["max_error_al"] == pytest.approx(2.0)  # the 10 m frame: AL 1 m (at 11 m: 2 / 2 m)
    assert index["max_error_pl"] == pytest.approx(2.0)
    unbiased = dataclasses.replace(run, acted=positions[:-1].copy())
    assert safety_index(unbiased, partial(alert_limit, settings=AlertLimitSettings(kind="persistent")))[
        "max_error_al"
    ] == pytest.approx(0.0)
    assert safety_index(dataclasses.replace(run, acted=None), alert_limit)["max_error_al"] is None
    raw = safety_index(run, partial(alert_limit, settings=AlertLimitSettings(kind="persistent")), flies_trusted=False)
    assert raw["max_error_pl"] is None and raw["max_error_al"] == pytest.approx(
        2.0
    )  # hold: the PL bounds no raw estimate
