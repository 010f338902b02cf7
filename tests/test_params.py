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
    (("defense", "position_noise", 0.0), r"defense.position_noise must be > 0 \(a noise std\), got 0.0"),
    (("defense", "attitude_noise_deg", -1.0), r"defense.attitude_noise_deg must be > 0"),
    (("defense", "false_alarm", 1.0), r"defense.false_alarm must be a gate probability in \(0, 1\), got 1.0"),
    (("defense", "false_alarm", 0), r"defense.false_alarm must be a gate probability in \(0, 1\), got 0.0"),
    (("defense", "hold_after", 0), r"defense.hold_after must be a whole number >= 1, got 0"),
    (("defense", "fusion", "and"), r"defense.fusion must be one of or, paper, motion"),
    (("defense", "update_below", None), None),
    (("defense", "val_seed", 1000), r"defense.val_seed must differ from evaluate.seed"),
    (("defense", "harm_m", 0.0), r"defense.harm_m must be > 0"),
    (("guidance", "defenses", ["hold", "pray"]), r"guidance.defenses\[1\] must be one of hold, recover"),
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


def test_unset_external_inputs_and_workers_leave_the_render_fingerprint_alone():
    """inputs/none (the DVC-dep placeholder) fingerprints like null, so renders made before the
    placeholder existed stay valid; a real mesh or SPEED source changes it."""
    from stages.params import compose, render_fingerprint

    p = compose("smoke")
    base = render_fingerprint(p)
    old = {**p, "render": {k: v for k, v in p["render"].items() if k not in ("source", "source_test")} | {"mesh": None}}
    assert render_fingerprint(old) == base
    assert render_fingerprint({**p, "render": {**p["render"], "workers": 7}}) == base
    assert render_fingerprint({**p, "render": {**p["render"], "mesh": "meshes/sat.obj"}}) != base
    assert render_fingerprint({**p, "render": {**p["render"], "source": "/data/speedplus"}}) != base
