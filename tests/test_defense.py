"""The defended chain: fusion, coast on flags, hold after K flags and release, bad settings."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.defense.fusion import COAST, HOLD, TRACK, Defense, run_defense
from pipeline.defense.gate import MotionSettings
from pipeline.defense.noise import NoiseModel
from pipeline.defense.settings import DefenseSettings
from pipeline.geometry.trajectories import look_at

NOISE = NoiseModel((0.05, 0.05, 0.1), (0.004, 0.004, 0.015), 1.0, 0.02)
MOTION = MotionSettings(false_alarm=0.005)


def straight(n: int = 60, seed: int = 0):
    """A straight 1 m/frame approach from 60 m with small estimate noise: (rel, t_pred, R_cam, u)."""
    rng = np.random.default_rng(seed)
    rel = np.column_stack([np.zeros(n), np.zeros(n), 60.0 - np.arange(n) * 0.8])
    R_cam = look_at(rel)
    t = np.einsum("nji,nj->ni", R_cam, rel)
    t_pred = t + rng.normal(0, 0.05, (n, 3))
    u = np.vstack([np.zeros(3), np.diff(rel, axis=0)])
    return rel, t_pred, R_cam, u


@pytest.mark.parametrize("fusion, expect", [("paper", [True, False]), ("motion", [False, True]), ("or", [True, True])])
def test_fusion_decides_which_check_flags(fusion, expect):
    rel, t_pred, R_cam, u = straight()
    prob = np.zeros(len(rel))
    prob[20] = 0.9  # the detector fires on a clean-looking frame
    t_pred = t_pred.copy()
    t_pred[40, 2] += 3.0  # the detector misses a 3 m jump
    tr = run_defense(DefenseSettings(fusion=fusion), MOTION, NOISE, t_pred, prob, R_cam, u)
    assert [bool(tr.flag[20]), bool(tr.flag[40])] == expect
    assert tr.shap_flag[20] and not tr.shap_flag[40] and tr.motion_flag[40]


def test_flagged_frames_coast_on_the_prediction():
    rel, t_pred, R_cam, u = straight()
    t_pred = t_pred.copy()
    t_pred[30:33] += np.array([2.0, 0.0, 4.0])
    tr = run_defense(DefenseSettings(hold_after=5), MOTION, NOISE, t_pred, np.zeros(len(rel)), R_cam, u)
    assert tr.flag[30:33].all() and not tr.flag[33:].any()
    assert list(tr.mode[30:33]) == [COAST] * 3 and tr.mode[33] == TRACK
    assert np.abs(tr.trusted[30:33] - rel[30:33]).max() < 0.3  # the prediction, not the attacked estimate
    assert np.linalg.norm(t_pred[30] - np.einsum("ji,j->i", R_cam[30], rel[30])) > 4


def test_hold_engages_after_k_flags_and_releases_on_clean_frames():
    rel, t_pred, R_cam, u = straight()
    prob = np.zeros(len(rel))
    prob[10:18] = 0.99  # 8 flagged frames in a row
    tr = run_defense(
        DefenseSettings(fusion="paper", hold_after=3, release_after=2), MOTION, NOISE, t_pred, prob, R_cam, u
    )
    assert list(tr.mode[10:12]) == [COAST, COAST]
    assert (tr.mode[12:18] == HOLD).all()
    assert list(tr.mode[18:20]) == [HOLD, TRACK]  # released after 2 clean frames (18 and 19)
    assert (tr.mode[20:] == TRACK).all()


def test_before_a_trusted_frame_the_defense_holds():
    rel, t_pred, R_cam, u = straight(10)
    prob = np.array([0.9, 0.9] + [0.0] * 8)
    tr = run_defense(DefenseSettings(), MOTION, NOISE, t_pred, prob, R_cam, u)
    # the filter starts on frame 2, which stays on probation (held) until a second clean frame passes
    assert list(tr.mode[:4]) == [HOLD, HOLD, HOLD, TRACK] and np.isnan(tr.trusted[:2]).all()
    assert np.allclose(tr.trusted[2], R_cam[2] @ t_pred[2]) and not tr.available[:3].any()


def test_a_start_frame_is_flown_on_only_after_release_after_clean_frames():
    rel, t_pred, R_cam, u = straight(10)
    one = run_defense(DefenseSettings(release_after=1), MOTION, NOISE, t_pred, np.zeros(10), R_cam, u)
    assert one.mode[0] == TRACK and one.available[0]
    # a flag right after the start restarts the count: the chain holds until two clean frames in a row
    prob = np.array([0.0, 0.9] + [0.0] * 8)
    tr = run_defense(DefenseSettings(release_after=2), MOTION, NOISE, t_pred, prob, R_cam, u)
    assert list(tr.mode[:4]) == [HOLD, HOLD, HOLD, TRACK]


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"hold_after": 0}, r"defense.hold_after \(K consecutive flags before a hold\) must be >= 1"),
        ({"release_after": 0}, "defense.release_after must be >= 1"),
        ({"fusion": "and"}, "unknown defense.fusion 'and'"),
        ({"threshold": 1.5}, r"threshold must be in \(0, 1\)"),
    ],
)
def test_bad_settings_name_the_parameter(changes, message):
    with pytest.raises(ValueError, match=message):
        DefenseSettings(**changes)


def test_run_defense_refuses_misshapen_input():
    rel, t_pred, R_cam, u = straight(10)
    with pytest.raises(ValueError, match=r"t_pred \(N, 3\), prob \(N,\)"):
        run_defense(DefenseSettings(), MOTION, NOISE, t_pred, np.zeros(9), R_cam, u)
    with pytest.raises(ValueError, match="u must be"):
        run_defense(DefenseSettings(), MOTION, NOISE, t_pred, np.zeros(10), R_cam, u[:5])


def test_defense_is_deterministic():
    rel, t_pred, R_cam, u = straight()
    a = run_defense(DefenseSettings(), MOTION, NOISE, t_pred, np.zeros(len(rel)), R_cam, u)
    b = Defense(DefenseSettings(), MOTION, NOISE)
    assert np.allclose(a.trusted, [b.step(t_pred[i], 0.0, R_cam[i], u[i]).trusted for i in range(len(rel))])


def test_a_slow_ramp_is_flagged_and_the_state_recovers_after_it():
    """A slow ramp (5 cm per frame sideways, up to 1 m) drags the filter a little before the
    sequential test flags it (and the gate its last frames); when it ends, the clean frames are
    taken again and the state returns: no lock-out."""
    rel, t_pred, R_cam, u = straight(70, seed=3)
    t_pred = t_pred.copy()
    ramp = np.zeros((70, 3))
    ramp[20:40, 0] = 0.05 * np.arange(1, 21)  # up to 1 m sideways, 5 cm per frame
    t_pred += np.einsum("nji,nj->ni", R_cam, ramp)
    tr = run_defense(DefenseSettings(fusion="motion"), MOTION, NOISE, t_pred, np.zeros(70), R_cam, u)
    assert tr.sequential_flag[20:40].any() and not tr.flag[:20].any() and not tr.flag[40:].any()
    error = np.linalg.norm(tr.trusted - rel, axis=1)
    assert error[20:40].max() < 0.5 and error[-1] < 0.1


def test_clean_frames_after_a_bad_start_restart_the_filter():
    """The filter started on a bad first frame (an attack the detector missed): the clean frames
    that follow agree with one another and, once M of them are in, with nothing else the filter
    accepted: it restarts on them after reacquire_after frames."""
    rel, t_pred, R_cam, u = straight(30, seed=4)
    t_pred = t_pred.copy()
    t_pred[0] += np.array([0.0, 0.0, 6.0])
    m = MotionSettings(false_alarm=0.005, reacquire_after=4)
    tr = run_defense(DefenseSettings(fusion="motion"), m, NOISE, t_pred, np.zeros(30), R_cam, u)
    assert tr.flag[1:4].all() and not tr.flag[4:].any()
    assert np.linalg.norm(tr.trusted[-1] - rel[-1]) < 0.2


@pytest.mark.parametrize("prob, word", [(0.2, "clean"), (0.4, "doubt"), (0.6, "attack"), (float("nan"), "attack")])
def test_the_detector_word_is_what_the_defense_acts_on(prob, word):
    """`DefenseSettings.word` (rpodguard's per-image verdict) is the defended chain's own reading of a frame: "attack"
    flags it, "doubt" coasts it unflagged, "clean" lets it update the filter."""
    rel, t_pred, R_cam, u = straight(40, seed=5)
    t_pred = t_pred.copy()
    t_pred[30, 0] += 0.25  # a small error the gate lets through: an update would move the state
    probs = np.zeros(40)
    probs[30] = prob
    settings = DefenseSettings(threshold=0.5, update_below=0.3)
    assert settings.word(prob) == word
    tr = run_defense(settings, MOTION, NOISE, t_pred, probs, R_cam, u)
    assert tr.shap_flag[30] == (word == "attack") and tr.flag[30] == (word == "attack")
    coasted = np.allclose(tr.trusted[30], tr.trusted[29] + u[30], atol=1e-9)
    assert coasted == (word != "clean")


def test_a_doubtful_frame_is_not_flagged_but_does_not_update_the_filter():
    rel, t_pred, R_cam, u = straight(40, seed=5)
    t_pred = t_pred.copy()
    t_pred[30, 0] += 0.25  # a small error the gate lets through
    prob = np.zeros(40)
    prob[30] = 0.4  # doubtful: above update_below, below the threshold
    settings = DefenseSettings(threshold=0.5, update_below=0.3)
    tr = run_defense(settings, MOTION, NOISE, t_pred, prob, R_cam, u)
    trusting = run_defense(DefenseSettings(threshold=0.5), MOTION, NOISE, t_pred, prob, R_cam, u)
    assert not tr.flag[30] and not trusting.flag[30]
    assert np.allclose(tr.trusted[30], tr.trusted[29] + u[30], atol=0.05)  # coasted
    assert not np.allclose(tr.trusted[30], trusting.trusted[30], atol=1e-6)  # the other one updated
    with pytest.raises(ValueError, match="defense.update_below must be in"):
        DefenseSettings(threshold=0.5, update_below=0.7)
