"""Measures that can fail (pipeline/evaluation/measures.py) and the persistent-bias alert limit
(pipeline/defense/integrity.py): a planted persistent bias, which no motion check can see, fails them
in the closed loop (docking miss > tolerance) and on a recorded trajectory (error / AL > 1), where the
single-frame AL let it through; the persistent AL is tight in the closed loop; Stanford regions, the
breaking point, nesting in eps, the worst over attackers and Clopper-Pearson counts."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pipeline.defense.fusion import COAST, HOLD, TRACK, Defense, run_defense
from pipeline.defense.gate import MotionSettings
from pipeline.defense.integrity import (
    AlertLimitSettings,
    IntegrityFrames,
    alert_limit,
    defense_frames,
    persistent_alert_limit,
    single_frame_alert_limit,
)
from pipeline.defense.noise import NoiseModel
from pipeline.defense.settings import DefenseSettings
from pipeline.evaluation.integrity_runs import undefended_trace
from pipeline.evaluation.measures import (
    COLLISION,
    DOCKED,
    HELD,
    HMI,
    MI,
    MISSED,
    NO_ESTIMATE,
    NOMINAL,
    TIMED_OUT,
    UNAVAILABLE,
    UNAVAILABLE_MI,
    TrajectoryMeasures,
    breaking_point,
    docking,
    hmi_trajectories,
    nest_in_eps,
    stanford_counts,
    stanford_regions,
    trajectory_measures,
    worst_over_attackers,
)
from pipeline.geometry.camera import Intrinsics
from pipeline.guidance.law import LOST, GuidanceSettings, RendezvousResult, run_rendezvous
from pipeline.guidance.settings import ExecutionSettings
from pipeline.stats import clopper_pearson

WIDE = Intrinsics(160, 90, 20.0, 20.0, 79.5, 44.5)  # a wide camera: a displaced chaser keeps the target in view
NOISE = NoiseModel((0.05, 0.05, 0.1), (0.002, 0.002, 0.01), 1.0, 0.0)
PERSISTENT = AlertLimitSettings(kind="persistent")


def blank(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    return np.zeros((WIDE.height, WIDE.width, 3), np.uint8)


def biased_world(b_world: np.ndarray, while_z: float = 0.0):
    """An estimator that reports the truth plus a world-frame bias, on frames whose true rel_z (the approach
    still to go, m) is >= while_z: t = R_c^T (rel + b), R_c the camera's attitude (from the true pose:
    R = R_c^T R_target, R_target = I)."""

    def estimate(image, attacked, pose):
        R, t = pose
        return t + (R @ b_world if (R.T @ t)[2] >= while_z else 0.0)

    return estimate


def test_persistent_alert_limit_is_the_docking_cone_and_the_single_frame_one_is_kept() -> None:
    r = np.array([60.0, 30.0, 15.0, 10.0, 8.0])
    np.testing.assert_allclose(persistent_alert_limit(r), [51.0, 21.0, 6.0, 1.0, 1.0])
    np.testing.assert_allclose(alert_limit(r, PERSISTENT), persistent_alert_limit(r))
    np.testing.assert_allclose(alert_limit(r), single_frame_alert_limit(r))  # the default is unchanged
    np.testing.assert_allclose(single_frame_alert_limit(r), [11.0, 11.0, 11.0, 6.0, 4.0])
    with pytest.raises(ValueError, match="kind"):
        AlertLimitSettings(kind="sometimes")


@pytest.mark.parametrize("start_range", [30.0, 20.0, 14.0])
def test_a_bias_that_disappears_is_removed_within_the_persistent_alert_limit_and_not_beyond(start_range) -> None:
    """true_state dynamics, no slack (one step past the nominal 50): a lateral bias held at every frame while
    the approach still has r - r_g to go, then gone, docks within tolerance at AL_p(r) - 0.2 m and misses at
    AL_p(r) + 2 m (the one-step lag of the law is the step past the nominal)."""
    s = GuidanceSettings(variant="true_state", max_steps=51)
    al = float(persistent_alert_limit(start_range))
    for size, docks in ((al - 0.2, True), (al + 2.0, False)):
        r = run_rendezvous(blank, biased_world(np.array([size, 0.0, 0.0]), start_range), WIDE, s)
        d = docking(r, s.goal, s.tolerance, 5.0)
        assert (d.outcome == DOCKED) == docks, (size, d)


@pytest.mark.parametrize("defended", [False, True])
def test_a_planted_persistent_bias_fails_the_closed_loop(defended) -> None:
    """A 2 m lateral world bias from the first frame (capture at acquisition): consistent with the commanded
    motion, so the defense never flags it; the chaser docks 2 m off: a mission failure (missed), lateral."""
    s = GuidanceSettings(
        variant="true_state",
        max_steps=60,
        defense="recover" if defended else "undefended",
        execution=ExecutionSettings(seed=1),
    )
    defense = Defense(DefenseSettings(), MotionSettings(position_noise=0.03), NOISE) if defended else None
    r = run_rendezvous(blank, biased_world(np.array([2.0, 0.0, 0.0])), WIDE, s, defense=defense)
    d = docking(r, s.goal, s.tolerance, 5.0)
    assert d.failed and d.outcome == MISSED and not d.ended_in_hold and d.arrived
    assert abs(d.lateral_miss - 2.0) < 0.3 and abs(d.range_miss) < 0.3 and d.lateral_miss > s.tolerance
    if defended:
        assert not r.flags.any()
    clean = run_rendezvous(
        blank,
        biased_world(np.zeros(3)),
        WIDE,
        s,
        defense=None if not defended else Defense(DefenseSettings(), MotionSettings(position_noise=0.03), NOISE),
    )
    assert not docking(clean, s.goal, s.tolerance, 5.0).failed


def _result(positions, held=None, modes=None) -> RendezvousResult:
    p = np.asarray(positions, np.float64)
    n = len(p) - 1
    return RendezvousResult(p, p[:-1], np.zeros(n, bool), "", 0.0, None, None, modes, held)


def test_docking_outcomes_split_the_miss_and_count_a_safe_hold_apart() -> None:
    goal, tol = (0.0, 0.0, 10.0), 1.0
    assert docking(_result([[0, 0, 12], [0.3, 0, 10.5]], [False]), goal, tol, 5.0).outcome == DOCKED
    d = docking(_result([[0, 0, 12], [3.0, 4.0, 12.0]], [False]), goal, tol, 5.0)
    assert d.outcome == MISSED and d.failed and np.isclose(d.range_miss, 2.0) and np.isclose(d.lateral_miss, 5.0)
    held = docking(_result([[0, 0, 30], [0, 0, 29], [0, 0, 29]], [False, True]), goal, tol, 5.0)
    assert held.outcome == HELD and not held.failed and held.hold_steps == 1
    crash = docking(_result([[0, 0, 6], [0, 0, -1], [0, 0, 10]], [False, False]), goal, tol, 5.0)
    assert crash.outcome == COLLISION and crash.failed and crash.closest_range < 1e-9
    by_modes = docking(_result([[0, 0, 30], [0, 0, 29]], None, np.array([HOLD])), goal, tol, 5.0)
    assert by_modes.ended_in_hold
    lost = docking(dataclasses.replace(_result([[0, 0, 30], [0, 0, 29]], [False]), outcome=LOST), goal, tol, 5.0)
    assert lost.outcome == "target lost" and lost.failed
    with pytest.raises(ValueError, match="goal"):
        docking(_result([[0, 0, 1], [0, 0, 1]]), (0.0, 0.0), tol, 5.0)


def test_a_run_whose_holds_spent_its_steps_times_out_and_one_that_arrives_wrong_misses() -> None:
    """The same end 10 m short of the goal on its line of sight: still commanding full steps toward it by its own
    estimate, with holds that forwent at least the 9 m left beyond the tolerance, is timed out, not a failure; with
    too few holds, believing it had reached the goal, lateral off, or without max_step, it is a miss, a failure; a
    run without the believed log counts as arrived (the conservative reading)."""
    goal, tol = (0.0, 0.0, 10.0), 1.0

    def end(holds: int, last=(0.0, 0.0, 20.0), lateral: float = 0.0):
        p = [[0, 0, 21]] * (holds + 1) + [[lateral, 0, 20]]
        b = np.array([[np.nan] * 3] * holds + [last])
        return dataclasses.replace(_result(p, [True] * holds + [False]), believed=b)

    d = docking(end(9), goal, tol, 5.0, max_step=1.0)
    assert d.outcome == TIMED_OUT and not d.failed and not d.arrived and d.hold_steps == 9
    for r, step in ((end(8), 1.0), (end(9, goal), 1.0), (end(9, lateral=1.5), 1.0), (end(9), None)):
        d = docking(r, goal, tol, 5.0, max_step=step)
        assert d.outcome == MISSED and d.failed, (r.positions[-1], r.believed[-1], step)
    assert docking(end(9), goal, tol, 5.0, max_step=1.0).timed_out
    with pytest.raises(ValueError, match="max_step"):
        docking(end(9), goal, tol, 5.0, max_step=0.0)
    assert docking(dataclasses.replace(end(9), believed=None), goal, tol, 5.0, max_step=1.0).outcome == MISSED
    held_last = dataclasses.replace(_result([[0, 0, 21], [0, 0, 20], [0, 0, 20]], [False, True]))
    assert docking(held_last, goal, tol, 5.0, max_step=1.0).outcome == HELD


def test_the_closed_loop_logs_where_each_command_aimed() -> None:
    """run_rendezvous: the believed log is the estimate minus the command (an exact estimator: the next true rel),
    NaN in no row without a hold; a budget too short for the approach, without a hold, misses (a failure: no hold
    spent the steps); the full budget docks."""
    short = GuidanceSettings(variant="true_state", max_steps=30)
    r = run_rendezvous(blank, biased_world(np.zeros(3)), WIDE, short)
    assert r.believed.shape == (30, 3) and np.isfinite(r.believed).all()
    assert np.allclose(r.believed, r.positions[1:])
    d = docking(r, short.goal, short.tolerance, 5.0, short.max_step)
    assert d.outcome == MISSED and not d.arrived and d.hold_steps == 0
    full = GuidanceSettings(variant="true_state", max_steps=60)
    assert docking(run_rendezvous(blank, biased_world(np.zeros(3)), WIDE, full), full.goal, 1.0, 5.0).outcome == DOCKED


def _approach(n: int = 60, seed: int = 0, scatter: float = 0.05):
    rel = np.column_stack([np.linspace(6.0, 0.0, n), np.linspace(-4.0, 0.0, n), np.linspace(60.0, 10.0, n)])
    R_cam = np.repeat(np.eye(3)[None], n, 0)
    u = np.vstack([np.zeros(3), np.diff(rel, axis=0)])
    return rel, R_cam, u, np.random.default_rng(seed).normal(size=(n, 3)) * scatter


FINE = NoiseModel((0.01, 0.01, 0.02), (0.0005, 0.0005, 0.001), 1.0, 0.0, floor=0.01)  # a PL under 1 m at the goal


@pytest.mark.parametrize("bias, defended, fails", [(2.0, True, True), (2.0, False, True), (0.5, True, False)])
def test_a_planted_persistent_bias_fails_the_recorded_trajectory_measures(bias, defended, fails) -> None:
    """Open loop: a world bias on every frame from the first passes every check of the real defense (no
    flag; the trusted-start frames hide it from the PL) and the trusted error sits at the bias; the chain
    stays available to the goal (PL < AL_p), so error / AL_p > 1 near the goal fails the trajectory at 2 m,
    defended or not, and not at 0.5 m; the single-frame AL (6 m at the goal) would never have said so."""
    rel, R_cam, u, scatter = _approach(scatter=0.015)
    t_pred = rel + scatter + np.array([bias, 0.0, 0.0])
    if defended:
        trace = run_defense(
            DefenseSettings(), MotionSettings(trusted_start=20), FINE, t_pred, np.zeros(len(rel)), R_cam, u
        )
        assert not trace.flag.any() and trace.pl[-1] < 1.0
    else:
        trace = undefended_trace(t_pred, R_cam)
    frames = defense_frames(trace, rel, "T1", PERSISTENT)
    m = trajectory_measures(frames, trace.flag, single_frame_alert_limit(np.linalg.norm(rel, axis=1)))
    # the defended chain holds its start frame on probation: available on every frame but that one
    assert m.failed == fails and (m.hmi > 0) == fails and m.availability == (1 - 1 / len(rel) if defended else 1.0)
    assert abs(m.final_error - bias) < 0.1 and m.max_error_al_single < 1.0 and m.flags == 0
    assert np.isnan(m.max_error_pl) != defended and m.frames == len(rel)


@pytest.mark.parametrize("trusted_start", [0, 20])
def test_the_capture_is_unavailable_under_a_protection_level_that_counts_it_and_hmi_inside_its_blind_window(
    trusted_start: int,
) -> None:
    """The same 2 m capture with a coarser noise model. A PL that counts every frame after the start
    (trusted_start 0) covers it: error < PL everywhere and the frames near the goal, where AL_p < PL, are
    unavailable (a hold, not a failure; the final error still reports the miss it would have caused). A PL
    that assumes the first 20 frames fault-free (assumption A) never sees the bias that arrived with them:
    misleading (error > PL) on almost every frame. Whether that becomes an HMI depends on the PL at the goal:
    since the PL's noise term covers the whole innovations after the trusted window (pipeline/defense/protection.py),
    it exceeds AL_p near the goal here, so those frames are unavailable (a hold) rather than HMI."""
    rel, R_cam, u, scatter = _approach()
    trace = run_defense(
        DefenseSettings(),
        MotionSettings(trusted_start=trusted_start),
        NOISE,
        rel + scatter + [2.0, 0.0, 0.0],
        np.zeros(len(rel)),
        R_cam,
        u,
    )
    m = trajectory_measures(defense_frames(trace, rel, "T1", PERSISTENT), trace.flag)
    assert not trace.flag.any() and abs(m.final_error - 2.0) < 0.3 and np.isnan(m.max_error_al_single)
    if trusted_start == 0:
        assert not m.failed and m.hmi == 0 and m.mi == 0 and m.availability < 0.9
    else:
        assert m.mi > 0.9 * len(rel) and m.max_error_pl > 1.0 and m.availability < 1.0


def test_stanford_regions_on_hand_made_frames() -> None:
    err = np.array([0.5, 2.0, 5.0, 0.5, 3.0, np.nan, 4.0])
    pl = np.array([1.0, 1.0, 1.0, 9.0, 2.0, np.inf, 3.0])
    mode = np.array([TRACK, TRACK, COAST, TRACK, HOLD, HOLD, TRACK])
    truth = np.zeros((7, 3)) + [0, 0, 20]
    trusted = truth + err[:, None] * [1.0, 0, 0]
    f = IntegrityFrames(np.full(7, "a"), np.arange(7), trusted, truth, mode, np.full(7, 4.5), pl)
    assert list(stanford_regions(f)) == [NOMINAL, MI, HMI, UNAVAILABLE, UNAVAILABLE_MI, NO_ESTIMATE, MI]
    counts = stanford_counts(f, np.arange(7) < 3)
    assert counts == {NOMINAL: 1, MI: 1, HMI: 1, UNAVAILABLE: 0, UNAVAILABLE_MI: 0, NO_ESTIMATE: 0}
    raw = dataclasses.replace(f, pl=None)
    assert list(stanford_regions(raw)) == [NOMINAL, NOMINAL, HMI, NOMINAL, UNAVAILABLE, NO_ESTIMATE, NOMINAL]


def _m(name: str, al: float, final: float = 0.0, hmi: int = 0) -> TrajectoryMeasures:
    return TrajectoryMeasures(name, 10, al, al / 2, al * 3, final, 0, hmi, 0, 1.0)


def test_breaking_point_nesting_and_worst_over_attackers() -> None:
    assert breaking_point([(0.05, False), (0.1, True), (0.02, False), (0.2, True)]) == 0.1
    assert breaking_point([(0.05, False)]) is None
    nested = nest_in_eps(
        {0.05: [_m("a", 1.5), _m("b", 0.2)], 0.01: [_m("a", 0.4), _m("b", 0.9)], 0.1: [_m("a", 0.7), _m("b", 0.1)]}
    )
    assert [m.max_error_al for m in nested[0.1]] == [1.5, 0.9]  # never drops as eps grows
    assert breaking_point((e, any(m.failed for m in ms)) for e, ms in nested.items()) == 0.05
    rows = worst_over_attackers(
        {"capture": [_m("a", 0.5, 0.3), _m("b", 1.2)], "drift": [_m("a", 0.8), _m("b", 0.1, 0.7)]}
    )
    assert [r["worst_attacker"] for r in rows] == ["drift", "capture"] and [r["failed"] for r in rows] == [False, True]
    assert rows[1]["final_error"] == 0.7 and rows[0]["max_error_pl"] == pytest.approx(2.4)
    with pytest.raises(ValueError, match="same trajectories"):
        worst_over_attackers({"x": [_m("a", 1.0)], "y": [_m("b", 1.0)]})


def test_hmi_counts_carry_clopper_pearson_intervals_over_trajectories() -> None:
    r = hmi_trajectories([_m(str(k), 0.5) for k in range(30)])
    assert r.value == 0 and r.lo == 0 and abs(r.hi - (1 - 0.025 ** (1 / 30))) < 1e-9
    r = hmi_trajectories([_m("a", 2.0, hmi=3), _m("b", 0.1), _m("c", 0.1), _m("d", 0.1)])
    assert r.value == 0.25 and r.lo < 0.25 < r.hi
    assert clopper_pearson(0, 0).n == 0
    with pytest.raises(ValueError, match="clopper_pearson"):
        clopper_pearson(3, 2)


def test_the_outcome_words_have_one_home() -> None:
    """The closed loop's end words are law.py's: measures re-uses them, and no stage, page or script compares an
    outcome with a literal (issue 36: a renamed outcome cannot leave a stale copy behind)."""
    import re
    from pathlib import Path

    from pipeline.evaluation import measures
    from pipeline.guidance import law

    assert measures.DOCKED is law.DOCKED and measures.LOST is law.LOST
    root = Path(__file__).resolve().parents[1]
    literal = re.compile(r"""outcome["'\]\)]*\s*[!=]=\s*["']""")
    for folder in ("pipeline", "stages", "scripts", "rpodguard"):
        for path in sorted((root / folder).rglob("*.py")):
            hits = [line.strip() for line in path.read_text().splitlines() if literal.search(line)]
            assert not hits, f"{path}: compare outcomes with the names in pipeline/guidance/law.py: {hits}"
