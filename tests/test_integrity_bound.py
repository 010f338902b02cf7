"""pipeline/evaluation/integrity_bound.py: the integrity bound assembled per trajectory and over trajectories."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.attacks.capacity import proportional_capacity
from pipeline.defense.bound import ACCEPT, ALARM, HUBER, NONE, REJECT, START
from pipeline.defense.chain import Defended
from pipeline.defense.integrity import AlertLimitSettings
from pipeline.evaluation.integrity_bound import (
    bound_run,
    checks_only_rates,
    first_over,
    over_al_rate,
    targets_of,
    trusted_frame,
    worst_over_trajectories,
)
from tests.test_bound import FLAT, MOTION, SETTINGS, toy

EDGES = [0.0, 100.0]
DEFENDED = Defended(SETTINGS, MOTION, FLAT, AlertLimitSettings())


def caps(along: float, across: float) -> list:
    """Range-proportional capacities at eps 0.01 and 0.05 (m per m of range; the larger eps twice as far)."""
    return [
        proportional_capacity(0.01, EDGES, along, across),
        proportional_capacity(0.05, EDGES, 2 * along, 2 * across),
    ]


def test_targets_start_at_the_filters_start_and_end_at_the_last_frame() -> None:
    assert targets_of(25, 3, 10) == [3, 13, 23, 24]
    assert targets_of(5, 5, 2) == []
    with pytest.raises(ValueError, match="stride"):
        targets_of(10, 0, 0)


def test_the_trusted_frame_counts_the_frames_the_sequential_test_saw() -> None:
    class Rec:
        kind = np.array([NONE, START, REJECT, ACCEPT, HUBER, REJECT, ALARM, ACCEPT])
        start = 1

    assert trusted_frame(Rec(), 0) == 1
    assert trusted_frame(Rec(), 2) == 4  # frames 3 and 4 were tested; the gate's rejection at 2 was not
    assert trusted_frame(Rec(), 4) == 7
    assert trusted_frame(Rec(), 9) == 7  # never that many: the last frame


def test_one_trajectory_bound_covers_its_replay_grows_with_capacity_and_spares_nothing_it_should_not() -> None:
    rel, run = toy(60, 3, FLAT)
    small = bound_run(DEFENDED, "t0", run, rel, caps(0.005, 0.005), [0.01, 0.05], 10, AlertLimitSettings())
    large = bound_run(DEFENDED, "t0", run, rel, caps(0.02, 0.02), [0.01], 10, AlertLimitSettings())
    zero = bound_run(DEFENDED, "t0", run, rel, caps(0.0, 0.0), [0.01], 10, AlertLimitSettings())
    assert small["targets"][0] == small["start"] and small["targets"][-1] == 59
    for e in ("0.01", "0.05"):
        b, s = small["per_eps"][e]["bound"], small["per_eps"][e]["spared"]
        assert b["unmodelled"] == 0 and len(b["ratio"]) == len(small["targets"])
        assert b["max_achieved_m"] <= b["max_error_m"] + 1e-3  # the replayed attack never beats the bound
        assert b["max_error_m"] >= s["max_error_m"] - 1e-6  # sparing the trusted frames can only help the PL
    assert small["per_eps"]["0.05"]["bound"]["max_error_m"] > small["per_eps"]["0.01"]["bound"]["max_error_m"]
    assert large["per_eps"]["0.01"]["bound"]["max_error_m"] > small["per_eps"]["0.01"]["bound"]["max_error_m"]
    assert zero["per_eps"]["0.01"]["bound"]["max_error_m"] == pytest.approx(zero["clean"]["max_error_m"], abs=1e-4)
    worst = worst_over_trajectories([small, large], "0.01")
    assert worst["bound"]["max_error_m"] == large["per_eps"]["0.01"]["bound"]["max_error_m"]
    assert worst["bound"]["trajectories"] == 2


def test_a_capacity_measured_below_the_eps_asked_is_refused() -> None:
    rel, run = toy(30, 4, FLAT)
    with pytest.raises(ValueError, match="above every measured eps"):
        bound_run(DEFENDED, "t0", run, rel, caps(0.01, 0.01), [0.1], 10, AlertLimitSettings())


def _track(ratios: list[float | None]) -> dict:
    return {"per_eps": {"0.01": {"bound": {"ratio": ratios}}}}


def test_the_share_of_frames_over_al_has_an_interval_over_trajectories() -> None:
    tracks = [_track([0.5, 1.5, None]), _track([0.2, 0.3]), _track([2.0, 3.0, 0.9, 0.1])]
    r = over_al_rate(tracks, "0.01")
    assert r.n == 8 and r.value == pytest.approx(3 / 8)
    assert r.lo <= r.value <= r.hi and r.hi - r.lo > 0.1


def test_first_over_is_the_smallest_eps_whose_bound_exceeds_al() -> None:
    rows = {
        "0.01": {"bound": {"max_error_al": 0.4}},
        "0.02": {"bound": {"max_error_al": 1.2}},
        "0.05": {"bound": {"max_error_al": 3.0}},
    }
    assert first_over(rows) == 0.02
    assert first_over({"0.01": {"bound": {"max_error_al": None}}}) is None


def test_the_checks_only_attacker_bounds_every_capacity_counts_every_frame_once_and_floors_a_sound_pl() -> None:
    rel, run = toy(60, 3, FLAT)
    out = bound_run(DEFENDED, "t0", run, rel, caps(0.02, 0.02), [0.05], 10, AlertLimitSettings())
    c = out["checks_only"]
    assert c["targets"][0] == out["start"] and c["targets"][-1] == 59
    assert sum(c["weight"]) == 60 - out["start"]  # every frame from the start stands once
    assert c["unmodelled"] == 0 and c["largest_shift_range"] < 1.0  # the box (the range) never binds
    # no capacity: at least the capacity-limited attacker that spares the same trusted frames
    assert c["max_error_m"] >= out["per_eps"]["0.05"]["spared"]["max_error_m"] - 1e-6
    # a sound PL is at least the replayed error: every frame the PL makes available is within the ceiling
    for ratio, avail in zip(c["achieved_al"], c["pl_available"]):
        assert not avail or ratio <= 1.0
    r = checks_only_rates([out, out])
    assert r["ceiling"]["n"] == 2 * (60 - out["start"])
    assert r["pl"]["value"] <= r["ceiling"]["value"]


def test_the_ceiling_weights_each_target_by_the_frames_it_stands_for() -> None:
    goal = {"achieved_m": 2.0, "alert_m": 1.0, "pl_m": 5.0}

    def track(ratios: list, flown: list, avail: list, weight: list) -> dict:
        c = {"targets": list(range(len(ratios))), "weight": weight, "achieved_al": ratios, "flown": flown}
        return {"checks_only": {**c, "pl_available": avail, "goal": goal, "largest_shift_range": 0.3}}

    a = track([0.2, 0.9, 1.5, None], [True, True, True, True], [True, False, False, False], [10, 1, 1, 1])
    b = track([0.1, 2.0], [True, False], [True, False], [5, 5])  # a held frame is never available
    r = checks_only_rates([a, b])
    assert r["ceiling"]["n"] == 22 and r["ceiling"]["value"] == pytest.approx(16 / 22)
    assert r["pl"]["value"] == pytest.approx(15 / 22)
    assert r["goal_achieved_m"]["max"] == 2.0 and r["targets"] == 6
