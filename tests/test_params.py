"""Typed params (stages/schema.py): every profile builds; bad keys, types and ranges are refused by
`stages.params.load` with a message naming the key."""
from __future__ import annotations

import pytest

from stages import params as params_mod
from stages.schema import Params, ParamsError, build


@pytest.mark.parametrize("profile", params_mod.profiles())
def test_every_profile_builds_typed_params(profile):
    p = build(params_mod.compose(profile))
    assert isinstance(p, Params) and p.profile_name == profile
    assert isinstance(p.evaluate.lateral_range[0], float) and isinstance(p.render.width, int)
    assert p.lab.zed.width == 1920 and p.threads >= 1


@pytest.mark.parametrize("edit, message", [
    (("train", "widht", 1), r"unknown parameter 'train.widht' \(did you mean 'train.width'\?\)"),
    (("render", "width", 1.5), r"render.width must be a whole number, got 1.5"),
    (("attack", "eps", "0.5"), r"attack.eps must be a list"),
    (("attack", "max_images", None), None),                          # null allowed where Optional
    (("train", "max_minutes", None), None),
    (("render", "samples", True), r"render.samples must be a whole number, got True"),
    (("evaluate", "p_start", 1.5), r"evaluate: p_start must be in \[0, 1\]"),
    (("evaluate", "lateral_range", [20.0, 10.0]), r"evaluate: lateral_range must be \[low, high\]"),
    ((None, "threads", 0), r"threads must be a whole number >= 1, got 0"),
    (("lab", "zed", {"width": 1920}), r"missing parameter 'lab.zed.height'"),
    (("detect", "baselines", ["mlp", "knn"]), r"detect.baselines\[1\] must be one of mlp, mahalanobis, lid, squeeze"),
    (("detect", "val_fraction", 1.0), r"detect: val_fraction must be in \(0, 1\), got 1.0"),
])
def test_load_refuses_bad_params_naming_the_key(tmp_path, monkeypatch, edit, message):
    monkeypatch.chdir(tmp_path)
    p = params_mod.compose("smoke")
    section, key, value = edit
    (p if section is None else p[section])[key] = value
    params_mod.write_params(p)
    if message is None:
        assert params_mod.load() == p
    else:
        with pytest.raises(ParamsError, match=message):
            params_mod.load()
