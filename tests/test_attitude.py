"""`rpod attitude`: the pose trials that make two others' changes at once are found, and the page says whether the
two causes add (issue 38, item 4: the attitude gap's contributions and what adding them assumes)."""

from __future__ import annotations

from stages.attitude import _combinations
from stages.pages.attitude import attitude_page

LABELS = {"render": {"target_attitude": "per_sequence"}}
SIZE = {"render": {"width": 320, "height": 180}}
BOTH = {"render": {"target_attitude": "per_sequence", "width": 320, "height": 180}}


def test_a_trial_that_merges_two_others_settings_is_their_combination():
    found = _combinations({"per_sequence": LABELS, "320x180": SIZE, "per_sequence_320x180": BOTH})
    assert found == {"per_sequence_320x180": ("320x180", "per_sequence")}
    assert _combinations({"per_sequence": LABELS, "320x180": SIZE}) == {}
    assert _combinations({"per_sequence": LABELS, "per_sequence_320x180": BOTH}) == {}  # one part missing
    wider = {"render": {**BOTH["render"], "width": 480}}
    assert _combinations({"per_sequence": LABELS, "320x180": SIZE, "x": wider}) == {}  # not exactly the two merged


def _summary(att: float) -> dict:
    stat = (att, att - 0.2, att + 0.2)
    one = {"frames": 10, "attitude_deg": stat, "tilt_deg": stat, "roll_deg": stat, "position_m": stat}
    return {"size": [160, 90], "validation": {**one, "groups": {}}, "test": {**one, "groups": {}}}


def _metrics(interactions: dict) -> dict:
    c = {"attitude_deg": (1.0, 0.5, 1.5), "position_m": (0.1, 0.0, 0.2)}
    return {
        "models": {"standard": _summary(2.5), "a": _summary(1.5), "b": _summary(2.0), "ab": _summary(1.2)},
        "cross": {},
        "contributions": {v: {"validation": c, "test": c} for v in ("a", "b", "ab")},
        "interactions": interactions,
    }


def test_the_page_says_the_additivity_is_unmeasured_without_a_combined_trial_and_gives_it_with_one():
    page = attitude_page(_metrics({}), {})
    assert "which was not measured" in page and "interaction" not in page
    x = {"alone_sum_deg": (1.5, 1.0, 2.0), "interaction_deg": (-0.2, -0.6, 0.1)}
    page = attitude_page(_metrics({"ab": {"of": ["a", "b"], "validation": x, "test": x}}), {})
    assert "which was not measured" not in page
    assert "a and b alone add to +1.50 [+1.00, +2.00] deg, interaction -0.20 [-0.60, +0.10] deg" in page
