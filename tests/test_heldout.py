"""`rpod heldout` (issue 38, item 5): the held-out set never meets a set a choice read, the verdicts follow the
measured differences (they can come out "reversed"), and a missing pose trial is one clear error."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.evaluation.heldout import (
    calibration_verdict,
    clamp_verdict,
    compare_models,
    pose_errors_by_frame,
    verdict,
)
from pipeline.seeds import STREAMS, run_base, seed_for
from pipeline.stats import Rate


def _poses(n: int, rng: np.random.Generator, ranges: np.ndarray) -> np.ndarray:
    """Poses (n, 9): t along the optical axis at `ranges` (m) plus a small lateral offset, identity rotation."""
    t = np.column_stack([rng.normal(0, 0.5, n), rng.normal(0, 0.5, n), ranges])
    return np.column_stack([t, np.tile([1.0, 0, 0, 0, 1.0, 0], (n, 1))])


def test_the_heldout_trajectories_meet_no_evaluation_or_validation_draw():
    items = {"eval_render.trajectory": 200, "eval_render.execution": 200, "background": 1}
    for seed in range(4):
        drawn = {}
        for stream in ("evaluate", "validation", "heldout"):
            base = run_base(seed, stream)
            seeds = {seed_for(base, s, i) for s, n in items.items() for i in range(n)}
            if stream == "validation":  # the envelope set of the validation base
                env = seed_for(base, "eval_render.envelope")
                seeds |= {seed_for(env, s, i) for s, n in items.items() for i in range(n)}
            drawn[stream] = seeds
        assert not drawn["heldout"] & (drawn["evaluate"] | drawn["validation"])
    assert "heldout" in STREAMS and run_base(1, "heldout") != run_base(0, "heldout") != run_base(0, "evaluate")


def test_pose_errors_by_frame_measures_depth_only_within_the_band():
    rng = np.random.default_rng(0)
    ranges = np.array([5.0, 12.0, 25.0, 40.0])
    target = _poses(4, rng, ranges)
    pred = target.copy()
    pred[:, 2] += 0.5  # 0.5 m too far on every frame
    e = pose_errors_by_frame(pred, target, np.array([0, 0, 1, 1]))
    assert np.isnan(e["tz_near_pct"][[0, 3]]).all()
    np.testing.assert_allclose(e["tz_near_pct"][1:3], 100 * 0.5 / np.linalg.norm(target[1:3, :3], axis=1))
    np.testing.assert_allclose(e["position_m"], 0.5)
    with pytest.raises(ValueError, match="poses"):
        pose_errors_by_frame(pred[:, :3], target, np.zeros(4))


@pytest.mark.parametrize(
    "difference, expected",
    [
        ((-0.2, -0.3, -0.1), "holds"),
        ((-0.05, -0.2, 0.1), "holds (not significant)"),
        ((0.05, -0.1, 0.2), "reversed (not significant)"),
        ((0.2, 0.1, 0.3), "reversed"),
    ],
)
def test_verdict_follows_the_interval(difference, expected):
    assert verdict(difference) == expected


def test_compare_models_says_reversed_when_the_alternative_is_better():
    rng = np.random.default_rng(1)
    n, traj = 400, np.repeat(np.arange(8), 50)
    ranges = np.linspace(60.0, 10.0, n)
    target = _poses(n, rng, ranges)
    small, large = target.copy(), target.copy()
    small[:, :3] += rng.normal(0, 0.05, (n, 3))
    large[:, :3] += rng.normal(0, 0.5, (n, 3))
    good, bad = (pose_errors_by_frame(p, target, traj) for p in (small, large))
    better = compare_models(good, bad)
    worse = compare_models(bad, good)
    assert better["position_m"]["verdict"] == "holds" and worse["position_m"]["verdict"] == "reversed"
    assert better["tz_near_pct"]["frames"] == int(((ranges >= 10) & (ranges <= 30)).sum())
    assert better["position_m"]["difference"][0] < 0 < worse["position_m"]["difference"][0]
    far = pose_errors_by_frame(small, target, traj, near=(100.0, 200.0))  # no frame in the band
    assert compare_models(far, far)["tz_near_pct"] == {
        "chosen": None,
        "alternative": None,
        "difference": None,
        "verdict": "no frames",
        "frames": 0,
    }


def _summary(availability: float, lo: float, fused: float) -> dict:
    return {
        "availability": Rate(availability, lo, min(1.0, availability + 0.01), 100),
        "fused": Rate(fused, 0, 0.01, 100),
    }


def test_calibration_verdict():
    assert calibration_verdict(_summary(0.9, 0.85, 0.001), _summary(0.8, 0.75, 0.0), 0.005) == "holds"
    assert calibration_verdict(_summary(0.9, 0.85, 0.01), _summary(0.8, 0.75, 0.0), 0.005) == (
        "misses its false-alarm target"
    )
    assert calibration_verdict(_summary(0.8, 0.7, 0.0), _summary(0.82, 0.78, 0.0), 0.005).startswith("holds (")
    assert calibration_verdict(_summary(0.7, 0.6, 0.0), _summary(0.9, 0.85, 0.0), 0.005) == "reversed"


def test_clamp_verdict():
    assert clamp_verdict({"threshold": 0.07, "lab_black_999": 0.063}) == "holds"
    assert clamp_verdict({"threshold": 0.07, "lab_black_999": 0.08}) == "reversed"


def test_a_missing_fy360_trial_is_one_clear_error(tmp_path, monkeypatch):
    from stages import heldout
    from stages.config import params as params_mod
    from stages.config.schema import build
    from stages.errors import StageError

    monkeypatch.chdir(tmp_path)
    with pytest.raises(StageError, match="pose_trial fy360"):
        heldout.main(build(params_mod.compose("smoke", [])))


def test_the_page_gives_the_lab_half_of_the_camera_check_when_it_was_measured():
    import json
    from pathlib import Path

    from stages.config import params as params_mod
    from stages.config.schema import build
    from stages.pages.heldout import heldout_page

    m = json.loads((Path(__file__).resolve().parent.parent / "reports/metrics/heldout.json").read_text())
    p = build(params_mod.compose("default", []))
    m.pop("lab_camera", None)
    assert "are not re-checked here" in heldout_page(m, p)
    lab = {k: dict(m["camera"][k], verdict="reversed") for k in ("position_m", "attitude_deg", "tz_near_pct")}
    page = heldout_page({**m, "lab_camera": {"recordings": 9, **lab}}, p)
    assert "are not re-checked" not in page and "9\nheld-out lab-like recordings" in page
    assert "; lab: position: reversed, attitude: reversed, tz at 10-30 m: reversed" in page


def test_the_heldout_lab_recordings_are_drawn_apart_from_every_other_set():
    """The held-out lab draws use their own stream on the held-out base: none is `rpod lab`'s or a trajectory's."""
    for seed in (0, 1, 2):
        base = run_base(seed, "heldout")
        lab = {seed_for(base, "heldout.lab", d) for d in range(3)}
        trajectories = {seed_for(base, "eval_render.trajectory", i) for i in range(100)}
        others = {
            seed_for(run_base(seed, s), "eval_render.trajectory", i)
            for s in ("evaluate", "validation")
            for i in range(100)
        }
        assert not lab & (trajectories | others | {seed_for(0, "lab"), seed_for(base, "background")})


def test_the_fy360_trial_is_the_default_with_its_camera_and_a_trial_trained_otherwise_is_refused(tmp_path, monkeypatch):
    """The trial's record gives its camera only: params added since it was trained do not break the check (a
    defense knob here), the rest comes from params.yaml; a record that differs in what the trial trained on is
    refused naming the section, one whose camera is the default's is refused too."""
    import yaml

    from stages import heldout
    from stages.config import params as params_mod
    from stages.config.schema import build
    from stages.errors import StageError

    monkeypatch.chdir(tmp_path)
    now = params_mod.compose("smoke", [])
    params = build({k: v for k, v in now.items() if k != params_mod.CONF_STAMP})
    (tmp_path / "params.yaml").write_text(yaml.safe_dump(now))
    folder = tmp_path / heldout.POSE_TRIALS / heldout.ALTERNATIVE
    folder.mkdir(parents=True)
    record = {**now, "camera": {**now["camera"], "fy": 360.0}, "defense": {"position_noise": 0.022}}
    (folder / "params.yaml").write_text(yaml.safe_dump(record))
    trial = heldout._fy360_trial(params)
    assert trial.camera.fy == 360.0 and trial.defense == params.defense and trial.render == params.render
    (folder / "params.yaml").write_text(yaml.safe_dump({**record, "train": {**now["train"], "epochs": 99}}))
    with pytest.raises(StageError, match="differs from params.yaml in train, not in the camera alone"):
        heldout._fy360_trial(params)
    (folder / "params.yaml").write_text(yaml.safe_dump({**now}))
    with pytest.raises(StageError, match="nothing to compare"):
        heldout._fy360_trial(params)
    (folder / "params.yaml").write_text("- a list, not params\n")
    with pytest.raises(StageError, match="must hold a mapping of params sections"):
        heldout._fy360_trial(params)
