"""The two chains (issue 28): the chain that ships is the robust pose model with its own detector and defense,
the paper's reproduction is the standard model with its own; every loader picks them by model (stages.artifacts.
paths.CHAINS) and refuses a detector or defense made for the other model (hash checks). Tiny random models."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import torch
from test_predict import H, W, _save_models, defense_record

from pipeline.formats.bundle import FILES, SOURCES
from pipeline.io.atomic import file_hash, read_json, write_json
from pipeline.io.errors import DataError
from stages.artifacts.paths import CHAINS, PAPER, SHIPPED, Model
from stages.config import params as params_mod


def _run(root: Path) -> Path:
    """ROOT/models as a run leaves it: the standard chain (pose.pt, detector.pt) and the robust one, whose pose
    model has the black-level clamp (pose_robust.pt, detector_robust.pt), each detector made on its own model."""
    models = root / "models"
    _save_models(models)
    robust = _save_models(root / "robust", black_level=0.07, seed=1)
    for name in ("pose", "detector"):
        shutil.copy(robust / f"{name}.pt", models / f"{name}_robust.pt")
    return models


def _defense(models: Path, model: Model, threshold: float, params=None) -> dict:
    """A defense file as `rpod calibrate` records it for the chain `model` (with the detector threshold `threshold`)
    under `params` (their defense settings and alert limit; made-up calibration results)."""
    import dataclasses

    from stages.config.build import alert_limit_settings, defense_settings

    changes = {}
    if params is not None:
        settings, motion = defense_settings(params.defense, 0.9, None if params.defense.doubt_share is None else 0.5)
        changes = {
            "settings": settings,
            "motion": dataclasses.replace(motion, cusum_threshold=8.0),
            "alert_limit": alert_limit_settings(params),
        }
    return defense_record(models / CHAINS[model].pose.name, threshold, model.value, **changes)


@pytest.fixture
def run(tmp_path, monkeypatch) -> Path:
    monkeypatch.chdir(tmp_path)
    p = params_mod.compose("smoke")
    p["render"]["width"], p["render"]["height"], p["train"]["width"] = W, H, 0.125
    params_mod.write_params(p)
    return _run(tmp_path)


def test_the_shipped_chain_is_the_robust_model_and_the_paper_rows_the_standard_one():
    assert SHIPPED == Model.robust and PAPER == Model.standard
    assert (CHAINS[SHIPPED].pose, CHAINS[SHIPPED].detector, CHAINS[SHIPPED].defense) == (
        Path("models/pose_robust.pt"),
        Path("models/detector_robust.pt"),
        Path("models/defense.json"),
    )
    assert (CHAINS[PAPER].pose, CHAINS[PAPER].detector, CHAINS[PAPER].defense) == (
        Path("models/pose.pt"),
        Path("models/detector.pt"),
        Path("models/defense_standard.json"),
    )
    # the weights bundle and rpodguard read the shipped chain's files of a run by the same names
    assert {n: Path("models") / SOURCES[n] for n in FILES} == {
        "pose.pt": CHAINS[SHIPPED].pose,
        "detector.pt": CHAINS[SHIPPED].detector,
        "defense.json": CHAINS[SHIPPED].defense,
    }


def test_the_stage_loader_gives_each_model_its_own_chain(run):
    from stages.artifacts.models import load_chain

    params = params_mod.load()
    shipped, paper = (load_chain(params, m, defended=False) for m in (SHIPPED, PAPER))
    assert shipped.pose_hash == file_hash(run / "pose_robust.pt") and paper.pose_hash == file_hash(run / "pose.pt")
    assert shipped.model.black_level == 0.07 and paper.model.black_level == 0
    assert shipped.defended is None and shipped.files[2] == CHAINS[SHIPPED].defense
    x = torch.rand(2, 3, H, W)
    assert not torch.equal(shipped.onboard(x).pose, paper.onboard(x).pose)


def test_a_detector_of_the_other_model_is_refused(run):
    from stages.artifacts.models import load_chain

    shutil.copy(run / "detector.pt", run / "detector_robust.pt")  # the standard model's detector
    with pytest.raises(DataError, match="detector_robust.pt was trained for pose checkpoint"):
        load_chain(params_mod.load(), SHIPPED, defended=False)


def test_each_defense_file_belongs_to_its_own_chain(run):
    from stages.artifacts.models import load_chain

    params = params_mod.load()
    threshold = {m: load_chain(params, m, defended=False).threshold for m in Model}
    for model in Model:
        write_json(CHAINS[model].defense, _defense(run, model, threshold[model], params))
        chain = load_chain(params, model)  # flies what the file records: the params' settings, calibrated
        assert chain.defended.settings.threshold == 0.9 and chain.defended.motion.cusum_threshold == 8.0
        assert chain.calibration.model == model.value
    shutil.copy(run / "defense_standard.json", run / "defense.json")
    with pytest.raises(DataError, match="defense.json was calibrated for another pose model"):
        load_chain(params, SHIPPED)
    write_json(
        run / "defense.json",
        _defense(run, PAPER, threshold[SHIPPED], params) | {"pose_model_hash": file_hash(run / "pose_robust.pt")},
    )
    with pytest.raises(DataError, match="calibrated for the standard chain, not the robust one"):
        load_chain(params, SHIPPED)


def test_a_defense_file_calibrated_under_other_params_is_refused_naming_both_values(run):
    """issue 42: after defense.false_alarm 0.001 -> 0.3 the stages ran the old calibration; now they refuse it."""
    import dataclasses

    from stages.artifacts.models import load_chain

    params = params_mod.load()
    threshold = load_chain(params, SHIPPED, defended=False).threshold
    write_json(run / "defense.json", _defense(run, SHIPPED, threshold, params))
    load_chain(params, SHIPPED)
    changed = {
        "defense.false_alarm": dataclasses.replace(params.defense, false_alarm=0.3),
        "defense.hold_after": dataclasses.replace(params.defense, hold_after=params.defense.hold_after + 1),
        "defense.doubt_share": dataclasses.replace(
            params.defense, doubt_share=None if params.defense.doubt_share else 0.05
        ),
    }
    for key, defense in changed.items():
        with pytest.raises(
            DataError,
            match=rf"defense.json records settings\.\w+ = .* but params.yaml gives {key} = "
            r".*: calibrated under other settings",
        ) as e:
            load_chain(dataclasses.replace(params, defense=defense), SHIPPED)
        assert "\n" not in str(e.value)
    guidance = dataclasses.replace(params.guidance, tolerance=params.guidance.tolerance * 2)
    with pytest.raises(DataError, match=r"records alert_limit.tolerance = .* but params.yaml gives guidance.tolerance"):
        load_chain(dataclasses.replace(params, guidance=guidance), SHIPPED)


def test_rpodguard_and_rpod_predict_load_the_shipped_chain_of_a_run(run):
    from rpodguard import load_chain

    for folder in (run, run.parent):  # models/, or the project root holding it
        chain = load_chain(folder)
        assert chain.files == (run / "pose_robust.pt", run / "detector_robust.pt", run / "defense.json")
        assert chain.safety.model.black_level == 0.07
    only_standard = run.parent / "standard"
    only_standard.mkdir()
    for name in ("pose.pt", "detector.pt"):
        shutil.copy(run / name, only_standard / name)
    assert load_chain(only_standard).files[:2] == (only_standard / "pose.pt", only_standard / "detector.pt")


def test_the_bundle_script_copies_the_shipped_chain(run):
    from pipeline.formats.bundle import write_bundle
    from rpodguard import load_chain

    write_json(run / "defense.json", _defense(run, SHIPPED, load_chain(run).safety.threshold))
    manifest = write_bundle(run.parent / "bundle", run, {"profile_name": "smoke"}, "0" * 40, [], "rebuild")
    assert manifest["sources"]["pose.pt"] == "models/pose_robust.pt"
    assert file_hash(run.parent / "bundle" / "pose.pt") == file_hash(run / "pose_robust.pt")
    assert load_chain(run.parent / "bundle").safety.model.black_level == 0.07
    write_json(run / "defense.json", {"pose_model_hash": file_hash(run / "pose.pt")})
    with pytest.raises(DataError, match="calibrated for another pose model"):
        write_bundle(run.parent / "bundle2", run, {}, "0" * 40, [], "rebuild")


def test_the_guidance_plan_flies_the_paper_grid_on_the_paper_chain_and_the_rest_on_the_shipped_one():
    from pipeline.guidance.grid import GridPlan, InLoopRun
    from pipeline.guidance.law import GuidanceSettings

    s = GuidanceSettings(max_steps=70)
    plan = GridPlan(
        s, ((0.5, 40, 5, s.window(40, 5)),), 10, ("paper", "true_state"), ("recover",), ((0.05, "collide", 20.0),)
    )
    runs = plan.runs()
    assert {r[0] for r in runs[: plan.paper_size]} == {"paper"}
    assert {r[0] for r in runs[plan.paper_size :]} == {"shipped"}
    assert ("shipped", "paper", "undefended", None) in runs  # its own undefended reference
    assert [r for r in runs if isinstance(r[3], InLoopRun)] == plan.in_loop_runs() and len(set(runs)) == len(runs)


@pytest.mark.parametrize(
    "doubt, message",
    [
        ("0.3", r"settings.update_below must be a number, got '0.3'"),
        (1.5, r"settings: defense.update_below must be in \(0, threshold"),
        (0.0, r"settings: defense.update_below must be in \(0, threshold"),
    ],
)
def test_a_defense_file_with_a_bad_doubt_level_is_refused_with_one_line(tmp_path, doubt, message):
    from pipeline.formats.defense import read_defense
    from rpodguard.api import BUNDLE

    cal = read_json(BUNDLE / "defense.json")
    read_defense(BUNDLE / "defense.json", cal["pose_model_hash"], cal["detector_threshold"])  # as calibrated
    cal["settings"]["update_below"] = doubt
    write_json(tmp_path / "defense.json", cal)
    with pytest.raises(DataError, match=r"defense.json:? " + message) as e:
        read_defense(tmp_path / "defense.json", cal["pose_model_hash"], cal["detector_threshold"])
    assert "\n" not in str(e.value)
