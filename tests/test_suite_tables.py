"""The strongest-attack suite as the stages report it (pipeline/evaluation/strongest.py, pipeline/formats/capacity.py,
stages/pages/suite.py): the attacked-error table with its checks, the split by background, the per-frame capacity
and its overbound, on a tiny stand-in pose regressor."""

from __future__ import annotations

import numpy as np
import pytest
from test_attack_suite import ToyPose, frames

from pipeline.attacks.strongest import SuiteConfig, run_suite
from pipeline.evaluation.strongest import attacked_table, background_rows, capacity_frames, fit_overbound
from pipeline.formats.capacity import read_capacity, write_capacity
from pipeline.io.errors import DataError

pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py

EPS = [0.01, 0.05, 0.1]
LEAN = SuiteConfig(members=("bpda/position", "bpda/attitude"), steps=3, restarts=1, starts=("lift",), batch_size=4)
FULL = SuiteConfig(
    members=("apgd/position", "bpda/position", "bpda/attitude", "square/attitude"),
    steps=4,
    restarts=2,
    queries=8,
    square_eps=0.05,
    batch_size=4,
)


def test_the_table_has_the_suite_rows_and_its_checks():
    images, targets = frames(6, black=True)
    out = attacked_table(
        ToyPose(black_level=0.07),
        images,
        targets,
        EPS,
        LEAN,
        check=np.array([1, 4]),
        full_check=np.array([0, 2, 5]),
        full=FULL,
    )
    suite = [r for r in out["rows"] if r["attack"] == "suite"]
    assert [r["eps"] for r in suite] == EPS and out["frames"] == 6 and out["cpu_seconds"] > 0
    assert [r["pos_m"] for r in suite] == sorted(r["pos_m"] for r in suite)  # nested: never drops
    assert {r["attack"] for r in out["rows"]} == {"clean", "suite", *LEAN.members}
    for r in suite:  # the worst case is >= each member's mean at its eps
        members = [m for m in out["rows"] if m["eps"] == r["eps"] and m["attack"] in LEAN.members]
        assert all(r["pos_m"] >= m["pos_m"] - 1e-9 and r["att_deg"] >= m["att_deg"] - 1e-9 for m in members)
    assert len(out["sanity"]) == 2 * len(EPS) and all(r["ok"] for r in out["sanity"])
    assert out["stability"]["frames"] == 2 and out["full_check"]["frames"] == 3
    checked = [(r["eps"], r["error"]) for r in out["full_check"]["rows"]]
    assert checked == [(e, k) for k in ("position_m", "attitude_deg") for e in EPS]
    assert all(r["ok"] == (abs(r["ratio"] - 1) < 0.05) for r in out["stability"]["rows"] + out["full_check"]["rows"])
    bare = attacked_table(ToyPose(black_level=0.07), images, targets, EPS, LEAN)
    untimed = [[{k: v for k, v in r.items() if "seconds" not in k} for r in t["rows"]] for t in (bare, out)]
    assert bare["stability"] is None and bare["full_check"] is None and untimed[0] == untimed[1]
    with pytest.raises(ValueError, match="needs the full suite's config"):
        attacked_table(ToyPose(), images, targets, EPS, LEAN, full_check=np.array([0]))


def test_the_background_split_selects_each_kinds_frames():
    images, targets = frames(6, black=True)
    result = run_suite(ToyPose(black_level=0.07), images, targets, EPS, LEAN)
    kinds = np.array(["earth", "black", "earth", "space", "black", "black"])
    split = background_rows(result, kinds)
    assert list(split) == ["black", "space", "earth"]  # KINDS order, only those present
    for kind, rows in split.items():
        mask = kinds == kind
        assert [r["attack"] for r in rows] == ["clean", *["suite"] * len(EPS)] and rows[0]["n"] == mask.sum()
        assert rows[0]["pos_m"] == pytest.approx(result.clean["position_m"][mask].mean())
        assert [r["att_deg"] for r in rows[1:]] == pytest.approx(result.worst("attitude_deg")[:, mask].mean(1))
    assert list(background_rows(result, None)) == ["black"]  # no column: every frame black
    with pytest.raises(ValueError, match="kinds of black, space, earth"):
        background_rows(result, np.array(["cloud"] * 6))


def test_capacity_is_per_frame_and_eps_nested_and_its_files_round_trip(tmp_path):
    images, targets = frames(8, black=True)
    index = np.array([3, 7, 11, 12, 20, 21, 30, 41])
    table = capacity_frames(ToyPose(black_level=0.07), images, targets, EPS, LEAN, index)
    assert list(table.columns) == ["index", "range_m", "eps", "along_m", "across_m", "attitude_deg"]
    assert len(table) == len(EPS) * 8 and sorted(set(table["index"])) == index.tolist()
    for key in ("along_m", "across_m", "attitude_deg"):
        wide = table.pivot(index="index", columns="eps", values=key)
        assert (np.diff(wide[EPS].to_numpy(), axis=1) >= 0).all()  # a frame's shift cannot drop as eps grows
    np.testing.assert_allclose(table["range_m"][:8], np.linalg.norm(targets[:, :3], axis=1))
    overbounds = fit_overbound(table, [0, 30, 100], 0.9, 0.25, 1)
    assert [c.eps for c in overbounds] == EPS and all(c.count.sum() == 8 for c in overbounds)
    assert all((b.along >= a.along).all() for a, b in zip(overbounds, overbounds[1:]))
    near = table[(table["eps"] == 0.05) & (table["range_m"] < 30)]["along_m"]
    assert overbounds[1].along[0] == pytest.approx(np.quantile(near, 0.9) * 1.25)
    with pytest.raises(ValueError, match="fewer than 9"):
        fit_overbound(table, [0, 30, 100], 0.9, 0.25, 9)
    written = write_capacity(tmp_path, "robust", table, overbounds, {"split": "val"})
    back, fitted, meta = read_capacity(tmp_path, "robust")
    assert back.equals(table) and meta == {"split": "val"} and written["per_eps"][2]["eps"] == 0.1
    assert all(np.array_equal(a.along, b.along) and a.eps == b.eps for a, b in zip(fitted, overbounds))
    with pytest.raises(DataError, match="not a rpodguard-capacity/1 file of the standard model"):
        (tmp_path / "standard.json").write_text((tmp_path / "robust.json").read_text())
        read_capacity(tmp_path, "standard")


def test_a_capacity_sample_short_in_a_range_bin_is_topped_up_from_that_bin() -> None:
    """The seed-1 default run stopped with 19 of the 20 frames the 45-70 m bin needs: the top-up draws the missing
    ones from the bin's other frames, leaves a sample that meets the minimum unchanged, and takes what there is."""
    from pipeline.evaluation.strongest import top_up_bins
    from pipeline.pose.robustness import sample_rows

    range_m = np.r_[np.linspace(6, 24, 120), np.linspace(26, 44, 120), np.linspace(46, 69, 72)]
    edges, rows = [5, 25, 45, 70], sample_rows(312, 80, 1)
    count = lambda r: np.histogram(range_m[r], bins=edges)[0]  # noqa: E731
    assert count(rows)[2] < 20  # this draw is short in the far bin
    topped = top_up_bins(rows, range_m, edges, 20, seed=1)
    assert (count(topped) >= 20).all() and set(rows) <= set(topped) and len(set(topped)) == len(topped)
    assert count(topped)[2] == 20 and (count(topped)[:2] == count(rows)[:2]).all()  # only the short bin grows
    assert np.array_equal(top_up_bins(topped, range_m, edges, 20, seed=1), topped)  # a full sample: unchanged
    assert np.array_equal(top_up_bins(rows, range_m, edges, 20, seed=1), topped)  # seeded
    assert count(top_up_bins(rows, range_m, edges, 100, seed=1))[2] == 72  # too few in the bin: all of them


def test_the_ablation_section_lists_neither_each_variant_and_both_per_background():
    from types import SimpleNamespace

    from stages.pages.suite import ablation_section

    images, targets = frames(4, black=True)
    kinds = np.array(["black", "earth", "black", "earth"])
    table = {
        name: attacked_table(ToyPose(black_level=level), images, targets, EPS, LEAN, backgrounds=kinds)
        for name, level in (("standard", 0.0), ("clamp", 0.07), ("adv", 0.0), ("robust", 0.07))
    }
    m = {
        "standard": {"suite": table["standard"]},
        "robust": {"suite": table["robust"]},
        "ablation": {
            "clamp only": {"suite": table["clamp"], "best_epoch": 3, "train_minutes": 1.0},
            "adversarial training only": {"suite": table["adv"], "best_epoch": 5, "train_minutes": 2.0},
        },
    }
    params = SimpleNamespace(train=SimpleNamespace(adversarial=SimpleNamespace(epochs=8, black_level=0.07)))
    page = ablation_section(m, params)
    lines = [line for line in page.splitlines() if line.startswith("| ") and "variant" not in line]
    names = ["neither (standard)", "clamp only", "adversarial training only", "both (robust)"]
    assert [line.split("|")[1].strip() for line in lines] == [n for n in names for _ in range(2 * (1 + len(EPS)))]
    assert {line.split("|")[2].strip() for line in lines} == {"black", "earth"}
    assert "Best epochs: clamp only 3, adversarial training only 5" in " ".join(page.split())
    assert ablation_section({k: v for k, v in m.items() if k != "ablation"}, params) == ""


def test_clean_errors_by_background_select_each_kinds_frames_with_floored_intervals():
    from pipeline.pose.metrics import errors_by_background, pose_errors

    rng = np.random.default_rng(0)
    _, target = frames(6, black=True)
    pred = target + rng.normal(0, [0.3] * 3 + [0.05] * 6, target.shape).astype(target.dtype)
    kinds = np.array(["earth", "black", "earth", "space", "black", "black"])
    split = errors_by_background(pred, target, kinds)
    pos, att = pose_errors(pred, target)
    assert list(split) == ["black", "space", "earth"]
    for kind, r in split.items():
        mask = kinds == kind
        assert r["n"] == mask.sum() and r["pos_m"] == pytest.approx(pos[mask].mean())
        assert r["att_deg"] == pytest.approx(att[mask].mean())
        assert 0 <= r["pos_ci"][0] <= r["pos_m"] <= r["pos_ci"][1] and r["att_ci"][0] >= 0
    assert list(errors_by_background(pred, target, None)) == ["black"]
    with pytest.raises(ValueError, match="kinds of black, space, earth"):
        errors_by_background(pred, target, np.array(["cloud"] * 6))
