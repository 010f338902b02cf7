"""Typed params (stages/config/schema.py): every profile builds; bad keys, types and ranges are refused by
`stages.config.params.load` with a message naming the key."""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import replace

import pytest

from stages.config import params as params_mod
from stages.config.device import torch_device, torch_setup
from stages.config.schema import Params, build
from stages.config.sections import ParamsError


@pytest.mark.parametrize("profile", params_mod.profiles())
def test_every_profile_builds_typed_params(profile):
    p = build(params_mod.compose(profile))
    assert isinstance(p, Params) and p.profile_name == profile
    assert isinstance(p.evaluate.lateral_range[0], float) and isinstance(p.render.width, int)
    assert p.lab.zed.width == 1920 and (p.threads is None or p.threads >= 1)


@pytest.mark.parametrize(
    "edit, message",
    [
        (("train", "widht", 1), r"unknown parameter 'train.widht' \(did you mean 'train.width'\?\)"),
        (("render", "width", 1.5), r"render.width must be a whole number, got 1.5"),
        (("attack", "eps", "0.5"), r"attack.eps must be a list"),
        (("attack", "max_images", None), None),  # null allowed where Optional
        (("train", "max_minutes", None), None),
        (("render", "samples", True), r"render.samples must be a whole number, got True"),
        (("evaluate", "p_start", 1.5), r"evaluate: p_start must be in \[0, 1\]"),
        (("evaluate", "lateral_range", [20.0, 10.0]), r"evaluate: lateral_range must be \[low, high\]"),
        ((None, "threads", 0), r"threads must be null or a whole number >= 1, got 0"),
        ((None, "threads", None), None),
        ((None, "device", "gpu"), r"device must be auto, cpu, cuda or cuda:N, got 'gpu'"),
        ((None, "device", "cuda:x"), r"device must be auto, cpu, cuda or cuda:N, got 'cuda:x'"),
        ((None, "device", "cuda:1"), None),  # checked against the GPUs when a stage runs
        ((None, "amp", "yes"), r"params.yaml amp must be true or false, got 'yes'"),
        (("lab", "zed", {"width": 1920}), r"missing parameter 'lab.zed.height'"),
        (
            ("detect", "baselines", ["mlp", "knn"]),
            r"detect.baselines\[1\] must be one of mlp, mahalanobis, lid, squeeze",
        ),
        (("detect", "val_fraction", 1.0), r"detect: val_fraction must be in \(0, 1\), got 1.0"),
        (
            ("defense", "position_noise", 0.0),
            r"params.yaml defense.position_noise must be a finite number > 0, got 0.0",
        ),
        (("defense", "attitude_noise_deg", -1.0), r"defense.attitude_noise_deg must be a finite number > 0"),
        (
            ("defense", "false_alarm", 1.0),
            r"defense.false_alarm is a gate probability and must be in \(0, 1\), got 1.0",
        ),
        (("defense", "false_alarm", 0), r"defense.false_alarm is a gate probability and must be in \(0, 1\), got 0.0$"),
        (("defense", "hold_after", 0), r"defense.hold_after \(K consecutive flags before a hold\) must be >= 1, got 0"),
        (("defense", "fusion", "and"), r"defense.fusion must be one of paper, motion, or"),
        (("defense", "doubt_share", None), None),
        (
            ("defense", "doubt_share", 1.0),
            r"defense.doubt_share must be a positive number in \(0, 1\) \(probability\), got 1.0",
        ),
        (("defense", "val_seed", 3000), r"unknown parameter 'defense.val_seed'"),  # it follows `seed` now
        (("defense", "harm_m", 0.0), r"defense.harm_m must be a positive number in \(0, 100000\] \(metres\)"),
        (("guidance", "defenses", ["hold", "pray"]), r"guidance.defenses\[1\] must be one of hold, recover"),
        (("guidance", "standard_defenses", ["pray"]), r"guidance.standard_defenses\[0\] must be one of hold, recover"),
        (
            ("guidance", "standard_defenses", ["recover", "recover"]),
            r"guidance.standard_defenses lists 'recover' twice",
        ),
        (("guidance", "defenses", ["hold", "hold"]), r"guidance.defenses lists 'hold' twice"),
        (("attack", "eps", [0.1, 0.05, 0.1]), r"attack.eps lists 0.1 twice"),  # issue 42 item 10: the guards
        (("shap", "eps", [0.05, 0.05]), r"shap.eps lists 0.05 twice"),
        (("evaluate", "eps", [0.01, 0.01]), r"evaluate.eps lists 0.01 twice"),
        (("robustness", "unseen_eps", [0.2, 0.2]), r"robustness.unseen_eps lists 0.2 twice"),
        (("train", "range_bins", [60, 30, 30]), r"train.range_bins lists 30 twice"),
        (("train", "range_bins", []), r"train.range_bins is empty"),
        (("detect", "squeeze_median", 2), r"detect.squeeze_median=2 must be odd"),
    ],
)
def test_load_refuses_bad_params_naming_the_key(tmp_path, monkeypatch, edit, message):
    monkeypatch.chdir(tmp_path)
    p = params_mod.compose("smoke")
    section, key, value = edit
    (p if section is None else p[section])[key] = value
    params_mod.write_params(p)
    if message is None:  # the mapping read, as YAML holds it (a tuple field's list read as a tuple)
        assert json.loads(json.dumps(dataclasses.asdict(params_mod.load()))) == p
    else:
        with pytest.raises(ParamsError, match=message):
            params_mod.load()


def test_unset_external_inputs_leave_the_render_fingerprint_alone():
    """inputs/none (the DVC-dep placeholder) fingerprints like null, so renders made before the
    placeholder existed stay valid; a real mesh or SPEED source changes it."""
    from stages.config.params import render_fingerprint

    p = build(params_mod.compose("smoke"))
    base = render_fingerprint(p)
    assert render_fingerprint(replace(p, render=replace(p.render, mesh=None, source=None))) == base
    assert render_fingerprint(replace(p, render=replace(p.render, mesh="meshes/sat.obj"))) != base
    assert render_fingerprint(replace(p, render=replace(p.render, source="/data/speedplus"))) != base


def _raw_key(p: dict, *extra: tuple[str, tuple[str, ...]]) -> str:
    """A fingerprint as it was computed before params were typed: JSON of the params.yaml mapping itself."""
    r = dict(p["render"])
    if r["background"]["share"] == 0:  # off: left out, as before render.background existed
        r.pop("background")
    r["mesh"] = params_mod.given(r["mesh"])
    if params_mod.given(r["source"]) is None:
        r.pop("source"), r.pop("source_test")
    if r["target_attitude"] == "per_frame":  # the default: the hash renders had before the option
        r.pop("target_attitude")
    if r["device"] == "cpu":  # the default Cycles device, likewise
        r.pop("device")
    key = {"seed": p["seed"], "camera": p["camera"], "render": r} | {
        s: {k: p[s][k] for k in ks} for s, ks in extra if s in p
    }
    key |= {s: dict(ks) for s, ks in extra if s not in p}  # derived values, given as (name, value) pairs
    return hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:16]


@pytest.mark.parametrize("profile", params_mod.profiles())
def test_typed_params_keep_the_yaml_values_and_every_fingerprint(profile):
    """A whole number where a float is expected stays an int (e.g. guidance.start_ranges [60, 40]): the typed
    params are the params.yaml mapping, so the fingerprints (JSON of params sub-mappings) and every value
    echoed into metrics and reports are those of the YAML."""
    from pipeline.seeds import run_base

    raw = params_mod.compose(profile)
    p = build(raw)
    assert json.loads(json.dumps(dataclasses.asdict(p))) == raw and type(p.guidance.start_ranges[0]) is type(
        raw["guidance"]["start_ranges"][0]
    )
    assert params_mod.render_fingerprint(p) == _raw_key(raw)
    flown = ("execution", (*raw["guidance"]["execution"].items(), ("max_step", raw["guidance"]["max_step"])))
    evaluate = {
        "evaluate": {k: raw["evaluate"][k] for k in ("trajectories", "frames", "lateral_range")}
        | {"seed": run_base(raw["seed"], "evaluate")}
    }  # the evaluation's base seed follows `seed`
    assert params_mod.eval_render_fingerprint(p) == _raw_key(
        {**raw, **evaluate}, ("evaluate", ("trajectories", "frames", "lateral_range", "seed")), flown
    )
    validation = {
        "defense": {
            "val_trajectories": raw["defense"]["val_trajectories"],
            "val_seed": run_base(raw["seed"], "validation"),
        }
    }
    assert params_mod.val_render_fingerprint(p) == _raw_key(
        {**raw, **validation},
        ("evaluate", ("frames", "lateral_range")),
        ("defense", ("val_trajectories", "val_seed")),
        flown,
    )


def test_device_param_resolves_in_one_place(monkeypatch):
    """auto -> cpu without a GPU; cuda without one -> one-line StageError; with (faked) GPUs, auto and
    cuda:N pick one and torchrun's local rank picks its own (a bad value is refused by the schema)."""
    import torch

    from stages.errors import StageError

    p = build(params_mod.compose("smoke"))
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert torch_device(replace(p, device="auto")) == torch.device("cpu")
    assert torch_device(replace(p, device="cpu")) == torch.device("cpu")
    for value in ("cuda", "cuda:0"):
        with pytest.raises(
            StageError,
            match=rf"^params.yaml device: '{value}' asks for a CUDA GPU but torch \S+ "
            r"sees none; set device: auto or cpu$",
        ):
            torch_device(replace(p, device=value))
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert torch_device(replace(p, device="auto")) == torch.device("cuda", 0)
    assert torch_device(replace(p, device="cuda:1")) == torch.device("cuda", 1)
    assert torch_device(replace(p, device="cpu")) == torch.device("cpu")
    assert torch_device(replace(p, device="cuda"), local_rank=1) == torch.device("cuda", 1)
    with pytest.raises(StageError, match=r"^params.yaml device: GPU 2 asked for but torch sees 2$"):
        torch_device(replace(p, device="cuda:2"))


def test_threads_param_sets_torch_threads():
    import os

    import torch

    before = torch.get_num_threads()
    p = replace(build(params_mod.compose("smoke")), device="cpu")
    try:
        assert torch_setup(replace(p, threads=1)) == torch.device("cpu") and torch.get_num_threads() == 1
        torch_setup(replace(p, threads=None))
        assert torch.get_num_threads() == (os.cpu_count() or 1)
        torch_setup(replace(p, threads=None), processes=64)
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before)


def test_an_edit_of_conf_without_rpod_params_is_refused_with_one_line(tmp_path, monkeypatch):
    """Issue 41: editing conf/ was silently ignored until `rpod params` ran again; params.yaml's conf_sha catches it."""
    import shutil

    from typer.testing import CliRunner

    from stages.cli import app

    shutil.copytree(params_mod.CONF_DIR, tmp_path / "conf")
    monkeypatch.chdir(tmp_path)
    runner = CliRunner()
    assert runner.invoke(app, ["params", "smoke"]).exit_code == 0
    stamp = params_mod.read_yaml(tmp_path / "params.yaml")[params_mod.CONF_STAMP]
    assert stamp == params_mod.conf_sha() and params_mod.load().profile_name == "smoke"
    assert runner.invoke(app, ["params", "--check"]).exit_code == 0
    config = tmp_path / "conf" / "profile" / "smoke.yaml"
    config.write_text(config.read_text() + "\n# an edit\n")
    with pytest.raises(
        ParamsError,
        match=r"params.yaml is stale: conf/ changed since it was composed .* run "
        r"`rpod params smoke`",
    ):
        params_mod.load()
    checked = runner.invoke(app, ["params", "--check"])
    assert checked.exit_code == 1 and "is stale" in str(checked.exception)  # main() prints it as one line
    assert runner.invoke(app, ["params", "smoke"]).exit_code == 0
    assert params_mod.load().profile_name == "smoke"
