"""`rpod pose_trial VARIANT` (issue 38, items 3 and 5): a variant of the data set differs from the main params in its
own settings only, and a failing step is one clear error naming the trial."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from stages.config import params as params_mod
from stages.config.schema import build
from stages.errors import StageError


@pytest.mark.parametrize(
    "variant, section, changed",
    [
        ("per_sequence", "render", {"target_attitude": "per_sequence"}),
        ("320x180", "render", {"width": 320, "height": 180}),
        ("fy360", "camera", {"fy": 360.0}),
    ],
)
def test_a_trial_changes_its_own_settings_only(variant, section, changed):
    from stages.pose_trial import trial_params

    p = build(params_mod.compose("default", []))
    sub = trial_params(p, variant)
    before = dataclasses.asdict(getattr(p, section))
    assert {k: v for k, v in dataclasses.asdict(getattr(sub, section)).items() if before[k] != v} == changed
    same = [s for s in ("seed", "train", "label", "camera", "render") if s != section]
    assert all(getattr(sub, s) == getattr(p, s) for s in same) and sub.engine.store is None
    assert params_mod.render_fingerprint(sub) != params_mod.render_fingerprint(p)
    with pytest.raises(StageError, match="unknown pose trial 'huge'"):
        trial_params(p, "huge")


def test_a_failing_trial_step_is_one_clear_error(tmp_path, monkeypatch):
    from stages import pose_trial
    from stages.engine import subrun

    def run_step(args: list[str], folder: Path) -> None:
        assert args == ["render"] and (folder / "params.yaml").exists()
        raise StageError("params.yaml render: boom")

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(subrun, "run_step", run_step)
    with pytest.raises(
        StageError,
        match=r"^pose_trial per_sequence \(render in datasets/pose_trials/per_sequence/\): "
        r"params.yaml render: boom$",
    ):
        pose_trial.main(build(params_mod.compose("smoke", [])), "per_sequence")
    assert not (tmp_path / "datasets" / "pose_trials" / "per_sequence").exists()
