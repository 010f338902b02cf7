"""The README's generated bullet on choices made on reported numbers (issue 38 item 5): it names the data of each
choice and follows the metrics and params it is given."""
from __future__ import annotations

import dataclasses

from stages.config.params import load
from stages.pages.differences import _choices


def test_the_choices_bullet_names_each_choice_its_data_and_follows_the_metrics():
    p = load()
    robust = {"black_level": {"threshold": 0.07, "images": 200}}
    text = _choices(p, robust, {"shipped": {"clamp_erased": 0.006}})
    assert "square pixels" in text and f"seed {p.defense.val_seed}" in text
    assert f"the evaluation's seed {p.evaluate.seed} is never read" in text
    assert "t = 0.07 was set from 200 training frames" in text and "erases 0.60%" in text
    assert text.count("no held-out check yet") == 2
    assert "erases" not in _choices(p, robust, {})                           # no lab run: no lab clause
    printed = dataclasses.replace(p, camera=dataclasses.replace(p.camera, fy=360.0))
    assert "(fy = 360)" in _choices(printed, robust, {})
