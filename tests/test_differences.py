"""The README's generated bullet on choices made on reported numbers (issue 38 item 5): it names the data of each
choice and follows the metrics and params it is given; the evaluate page's held-out clamp check."""

from __future__ import annotations

import dataclasses

from stages.config.params import evaluation_seed, load, validation_seed
from stages.pages.differences import _choices
from stages.pages.evaluate import clamp_section

TRAIN = {"threshold": 0.07, "images": 200, "lab_black_999": 0.0627, "target_erased": 0.048}
HELD = {
    "threshold": 0.07,
    "images": 200,
    "render_black": 0.9,
    "lab_black_999": 0.0612,
    "lab_passed": 0.0002,
    "target_erased": 0.051,
}


def test_the_choices_bullet_names_each_choice_its_data_and_follows_the_metrics():
    p = load()
    robust = {"black_level": TRAIN}
    text = _choices(p, robust, {"shipped": {"clamp_erased": 0.006}}, {"black_level_heldout": HELD})
    assert "square pixels" in text and f"base seed {validation_seed(p)}" in text
    assert f"the evaluation's base {evaluation_seed(p)} is never read" in text
    assert "t = 0.07 was set from 200 training frames" in text and "erases 0.60%" in text
    assert "percentile is 0.0612 (training frames: 0.0627), so t is still above it" in text
    assert "5.1% of the target's channel values fall below t (training frames: 4.8%" in text
    assert text.count("no held-out check yet") == 0 and text.count("`rpod heldout`") == 2
    bare = _choices(p, robust, {}, {})  # neither check ran: no clause
    assert "erases" not in bare and "evaluation frames" not in bare
    above = _choices(p, robust, {}, {"black_level_heldout": {**HELD, "lab_black_999": 0.08}})
    assert "so t is NOT above it" in above
    printed = dataclasses.replace(p, camera=dataclasses.replace(p.camera, fy=360.0))
    assert "(fy = 360)" in _choices(printed, robust, {}, {})


def test_the_held_out_clamp_section_says_whether_t_still_holds():
    assert "t is still above the\nlab black level" in clamp_section(HELD, 1000)
    text = clamp_section({**HELD, "lab_black_999": 0.09}, 1000)
    assert "t is NOT above the\nlab black level" in text and "base seed 1000" in text
