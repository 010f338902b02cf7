"""scripts/variance.py: mean and spread of the headline numbers over runs that differ only in seed."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from script_loader import load_script

REPO = Path(__file__).resolve().parent.parent


def _load():
    return load_script("variance")


def _run(root: Path, seed: int, pos: float, detect_acc: float | None) -> Path:
    run = root / f"seed{seed}"
    (run / "reports" / "metrics").mkdir(parents=True)
    (run / "params.yaml").write_text(f"profile_name: default\nseed: {seed}\n")
    train = {"test": {"pos_mean_m": pos, "att_mean_deg": 3.0, "tz_pct_10_30": 1.0}}
    (run / "reports" / "metrics" / "train.json").write_text(json.dumps(train))
    (run / "models").mkdir()
    (run / "models" / "pose.pt").write_bytes(f"weights of seed {seed}".encode())
    if detect_acc is not None:
        from pipeline.io.atomic import file_hash

        detect = {
            "detectors": {"lstm": {"all": {"accuracy": detect_acc}, "0.01": {"recall": 0.5}}},
            "model_hash": file_hash(run / "models" / "pose.pt"),
        }
        (run / "reports" / "metrics" / "detect.json").write_text(json.dumps(detect))
    return run


def test_rows_count_the_runs_that_have_each_number(tmp_path):
    runs = [_run(tmp_path, 0, 0.40, 0.93), _run(tmp_path, 1, 0.46, 0.91), _run(tmp_path, 2, 0.43, None)]
    rows = {r["key"]: r for r in _load().variance_rows(runs)}
    pos = rows["pose.standard_position_m"]
    assert pos["runs"] == 3 and pos["mean"] == pytest.approx(0.43) and pos["sd"] == pytest.approx(0.03)
    assert (pos["min"], pos["max"]) == (0.40, 0.46)
    acc = rows["detector.standard_accuracy_pct"]
    assert acc["runs"] == 2 and acc["mean"] == pytest.approx(92.0)
    assert "lab.standard_accuracy_pct" not in rows  # no run has it: no row


def test_a_single_run_has_no_spread(tmp_path):
    rows = _load().variance_rows([_run(tmp_path, 0, 0.40, None)])
    assert rows[0]["runs"] == 1 and rows[0]["sd"] == "-"


def test_metrics_of_another_pose_model_do_not_count(tmp_path):
    """A copy of the repository carries committed metrics of stages it never ran: they name another model."""
    run = _run(tmp_path, 1, 0.40, 0.93)
    (run / "models" / "pose.pt").write_bytes(b"retrained")  # detect.json now belongs to another model
    rows = {r["key"]: r for r in _load().variance_rows([run])}
    assert "detector.standard_accuracy_pct" not in rows and rows["pose.standard_position_m"]["runs"] == 1


def test_metrics_a_stage_wrote_under_another_seed_do_not_count(tmp_path):
    """Metrics without a model hash (robust.json) that the copy's dvc.lock records for another seed, or that the
    stage did not write (another md5), are the committed run's, not this run's."""
    import hashlib

    import yaml

    run = _run(tmp_path, 2, 0.40, None)
    train = run / "reports" / "metrics" / "train.json"

    def lock(seed: int, md5: str) -> None:
        stage = {
            "params": {"params.yaml": {"seed": seed}},
            "outs": [{"path": "reports/metrics/train.json", "md5": md5}],
        }
        (run / "dvc.lock").write_text(yaml.safe_dump({"schema": "2.0", "stages": {"train": stage}}))

    own = hashlib.md5(train.read_bytes()).hexdigest()
    lock(2, own)
    assert "train" in _load().run_metrics(run)
    lock(0, own)
    assert "train" not in _load().run_metrics(run)
    lock(2, "0" * 32)
    assert "train" not in _load().run_metrics(run)
    (run / "dvc.lock").write_text("stages: [not, a, mapping")
    with pytest.raises(SystemExit, match="dvc.lock: not a readable dvc.lock"):
        _load().run_metrics(run)


def test_every_headline_has_a_unique_key():
    keys = [k for k, *_ in _load().HEADLINES]
    assert len(keys) == len(set(keys))


def test_readme_results_show_the_spread_of_each_headline_number():
    """Each headline number's sd from reports/variance.json lands beside it in the README results table
    (a typo in a key would leave a "-" there), and without a spread there is no such column."""
    from stages.pages.readme import summary_tables

    metrics = {
        m: json.loads((REPO / "reports" / "metrics" / f"{m}.json").read_text())
        for m in ("train", "robust", "attack", "guidance", "detect", "detect_robust", "evaluate", "lab", "robustness")
    }
    # in variance.md only: the README shows these per eps or per dynamics (or not at all)
    not_shown = {
        "pose_tz_pct",
        "lstm_recall_0.01_pct",
        "lstm_eval_fa_pct",
        "integrated_0.01_pct",
        "shipped_test_fa_pct",
        "shipped_lab_max_prob",
        "robustness.shipped_harmful_missed_pct",
        "guidance.shipped_docked_pct",
    }
    keys = [k for k, *_ in _load().HEADLINES if k not in not_shown]
    spread = {
        "profile": "default",
        "seeds": ["0", "1", "2"],
        "numbers": {
            k: {"runs": 3, "mean": 1.0, "sd": 1.01 + 0.01 * i, "min": 0.0, "max": 2.0} for i, k in enumerate(keys)
        },
    }
    text = summary_tables(metrics, spread)
    assert "sd over seeds" in text and "differ only in `seed`" in text and "over the 3 runs that" in text
    fewer = dict(spread, numbers={**spread["numbers"], keys[0]: dict(spread["numbers"][keys[0]], runs=2)})
    assert "over the 2 to 3 runs that" in summary_tables(metrics, fewer)
    for i, k in enumerate(keys):
        assert any(f"{1.01 + 0.01 * i:.2f}{note} (3 seeds)" in text for note in ("", " %", " at eps 0.05")), k
    assert "sd over seeds" not in summary_tables(metrics)
    mixed = dict(spread, seeds=["0", "1", "2", "0"], isas=["AVX2", "AVX2", "AVX2", "AVX512"])
    text = summary_tables(metrics, mixed)
    assert "differ only in `seed` (0, 1, 2) and in torch's CPU kernels (AVX2, AVX512)" in text
    assert "(3 runs)" in text and "(3 seeds)" not in text


def test_a_spread_of_another_profile_is_not_shown(tmp_path, monkeypatch):
    from stages import report
    from stages.config.params import compose
    from stages.config.schema import build

    monkeypatch.chdir(tmp_path)
    (tmp_path / "reports").mkdir()
    (tmp_path / "reports" / "variance.json").write_text(json.dumps({"profile": "default", "seeds": [], "numbers": {}}))
    assert report._spread(build(compose("smoke"))) is None
    assert report._spread(build(compose("default")))["profile"] == "default"


def test_the_spread_covers_every_summary_json_number():
    """The seed spread and `dvc metrics show` read the same headline definitions (stages/pages/summary.py)."""
    from stages.pages.summary import HEADLINES as SUMMARY

    keys = [h.key for h in _load().HEADLINES]
    assert keys[: len(SUMMARY)] == [h.key for h in SUMMARY]


def test_the_committed_spread_names_only_headline_numbers():
    """reports/variance.json (read by `rpod report`) uses the headline keys: an unknown key would drop its sd (a
    headline added or renamed after the runs has no spread until they are re-run)."""
    spread = json.loads((REPO / "reports" / "variance.json").read_text())
    assert set(spread["numbers"]) <= {h.key for h in _load().HEADLINES}


def test_runs_of_two_instruction_sets_make_a_seed_by_isa_table(tmp_path, monkeypatch):
    """Runs are named by seed and the kernels their torch stages ran (the `cpu_isa` stamp), or by hand."""
    mod = _load()
    runs = []
    for seed, isa, pos in ((0, "AVX2", 0.40), (0, "AVX512", 0.43), (1, "AVX2", 0.46), (1, "AVX512", 0.47)):
        run = _run(tmp_path / isa, seed, pos, None)
        train = json.loads((run / "reports/metrics/train.json").read_text())
        train["cpu_isa"] = {"cap": "avx2" if isa == "AVX2" else "native", "kernels": isa}
        (run / "reports/metrics/train.json").write_text(json.dumps(train))
        runs.append(run)
    isas = [mod.run_isa(mod.run_metrics(r)) for r in runs]
    assert isas == ["AVX2", "AVX512", "AVX2", "AVX512"]
    rows = {r["key"]: r for r in mod.isa_rows(runs, ["0", "0", "1", "1"], isas)}
    pos = rows["pose.standard_position_m"]
    assert pos["seed 0, AVX2"] == 0.40 and pos["seed 1, AVX512"] == 0.47
    assert pos["largest ISA difference at one seed"] == pytest.approx(0.03)
    assert pos["sd over seeds, one ISA"] == pytest.approx(((0.06**2 / 2 + 0.04**2 / 2) / 2) ** 0.5)
    assert mod.parse_runs([f"AVX2={runs[0]}", str(runs[1])]) == [(runs[0], "AVX2"), (runs[1], None)]
    assert mod.run_isa({"train": {}}) == "?"  # a run from before the stamp
    monkeypatch.setattr(mod, "ROOT", tmp_path)
    (tmp_path / "reports").mkdir()
    mod.main([str(r) for r in runs])
    text = (tmp_path / "reports/variance.md").read_text()
    assert "## Seed x instruction set" in text and "| seed 0, AVX512" in text
    assert json.loads((tmp_path / "reports/variance.json").read_text())["isas"] == isas


def test_a_run_whose_calibration_missed_its_target_is_named(tmp_path):
    import json

    ok, missed = tmp_path / "ok", tmp_path / "missed"
    for run in (ok, missed):
        (run / "models").mkdir(parents=True)
        (run / "models" / "defense.json").write_text(json.dumps({"unmet": []}))
    (missed / "models" / "defense_standard.json").write_text(
        json.dumps(
            {
                "unmet": [
                    "calibrate: the fused chain flags 0.520% of 5000 clean validation frames, above defense.target_false_alarm "
                    "0.5%, although each check met its share; set defense.allow_unmet: true to continue anyway"
                ]
            }
        )
    )
    note = _load()._unmet_note([ok, missed], ["0", "2"], ["AVX2", "AVX2"])
    assert "seed 2, AVX2: defense_standard.json: calibrate: the fused chain flags 0.520%" in note
    assert "seed 0" not in note and note.count("\n- ") == 1
    assert _load()._unmet_note([ok], ["0"], ["AVX2"]) == ""


def _campaign(run: Path, per_eps: dict[str, tuple[int, int, float]], availability: float) -> None:
    """RUN's robustness.json with the shipped chain's integrity summary: eps -> (failed, trajectories, error/AL)."""
    n = next(iter(per_eps.values()))[1]
    clean = [
        {"frames": 200, "availability": availability, "max_error_al": 0.01 * (i + 1), "failed": False, "flags": i}
        for i in range(n)
    ]
    summary = {
        "breaking_eps": next((float(e) for e, (f, _, _) in per_eps.items() if f), None),
        "clean": {"trajectories": clean},
        "per_eps": {
            e: {"failed": f, "trajectories": t, "max_error_al": r, "final_error_max_m": 2 * r}
            for e, (f, t, r) in per_eps.items()
        },
    }
    robustness = {"integrity": {"chains": {"robust": {"summary": summary}}}}
    (run / "reports" / "metrics" / "robustness.json").write_text(json.dumps(robustness))


def test_the_campaign_trajectories_pool_over_the_seed_runs(tmp_path):
    """Issue 39 item 5: the runs' trajectories add up, failures with a Clopper-Pearson interval over the pooled
    trajectories; an eps a run never flew (it broke before) counts only the runs that flew it, and says so."""
    variance = _load()
    a, b = _run(tmp_path, 0, 0.4, None), _run(tmp_path, 1, 0.4, None)
    _campaign(a, {"0.01": (0, 4, 0.02), "0.05": (1, 4, 1.3)}, 0.8)
    _campaign(b, {"0.01": (0, 4, 0.03), "0.05": (0, 4, 0.5), "0.2": (4, 4, 3.0)}, 0.9)
    metrics = [variance.run_metrics(r) for r in (a, b)]
    (chain,) = variance.pooled_chain_rows(metrics, ["0", "1"])
    assert chain["trajectories"] == 8 and chain["runs"] == 2
    assert chain["breaking point per run (survived, broke]"] == "seed 0: (0.01, 0.05], seed 1: (0.05, 0.2]"
    assert chain["clean availability (%)"].startswith("85.0 [")
    assert chain["clean false alarms (%)"].startswith("0.8 [")  # (0 + 1 + 2 + 3) x 2 of 1,600 frames
    rows = {r["eps"]: r for r in variance.pooled_eps_rows(metrics, ["0", "1"])}
    assert rows["0.05"]["trajectories failed / flown"] == "1/8" and rows["0.05"]["largest error / AL"] == 1.3
    assert rows["0.05"]["failed (%)"] == "12.5 [0.3, 52.7]"  # Clopper-Pearson 1 of 8
    assert rows["0.2"]["trajectories failed / flown"] == "4/4" and "seed 0 broke before" in rows["0.2"]["runs flown"]
    assert "pooled over the seed runs" in variance.pooled_section([a, b], ["0", "1"])
    assert variance.pooled_section([_run(tmp_path, 2, 0.4, None)], ["2"]) == ""  # no campaign: no section
    old = _run(tmp_path, 3, 0.4, None)  # a run made before the safety summary: its chains have none
    (old / "reports" / "metrics" / "robustness.json").write_text(json.dumps({"integrity": {"chains": {"robust": {}}}}))
    (pooled,) = variance.pooled_chain_rows([variance.run_metrics(r) for r in (a, old)], ["0", "3"])
    assert pooled["runs"] == 1 and pooled["trajectories"] == 4
    no_count = json.loads((a / "reports" / "metrics" / "robustness.json").read_text())
    for t in no_count["integrity"]["chains"]["robust"]["summary"]["clean"]["trajectories"]:
        del t["flags"]
    (a / "reports" / "metrics" / "robustness.json").write_text(json.dumps(no_count))
    (pooled,) = variance.pooled_chain_rows([variance.run_metrics(a)], ["0"])
    assert pooled["clean false alarms (%)"] == "-"


def test_the_shipped_over_control_ratio_is_only_claimed_within_both_brackets(tmp_path):
    variance = _load()
    run = _run(tmp_path, 0, 0.4, None)
    _campaign(run, {"0.01": (0, 4, 0.02), "0.07": (0, 4, 0.2), "0.1": (1, 4, 1.3)}, 0.8)
    path = run / "reports" / "metrics" / "robustness.json"
    m = json.loads(path.read_text())
    control = json.loads(json.dumps(m["integrity"]["chains"]["robust"]))
    control["summary"]["per_eps"] = {"0.01": control["summary"]["per_eps"]["0.01"], "0.07": {"failed": 2}}
    control["summary"]["breaking_eps"] = 0.07
    m["integrity"]["chains"]["control"] = control
    path.write_text(json.dumps(m))
    (row,) = variance.ratio_rows([variance.run_metrics(run)], ["0"])
    assert row == {
        "run": "seed 0",
        "shipped breaks in": "(0.07, 0.1]",
        "control breaks in": "(0.01, 0.07]",
        "shipped / control": "ratio above 1.00, below 10.00 (the grid cannot tell)",
        ">= 2x": "not shown",
    }


def test_the_pooled_closed_loop_counts_runs_that_did_not_dock_apart_from_failures():
    """Held and timed-out runs (availability losses) are summed over eps and runs beside the failures."""
    variance = _load()

    def run(failed: int, outcomes: dict, ratio: float | None = None) -> dict:
        cell = {"met": 3, "failed": failed, "outcomes": outcomes, "largest_error_al": ratio}
        hold = {"breaking_eps": 0.05 if failed else None, "clean": {"miss": 0.2}, "per_eps": {"0.05": cell}}
        return {"guidance": {"closed_loop": {"variants": {"true_state": {"hold": hold}}}}}

    (row,) = variance.closed_loop_rows(
        [run(1, {"missed": 1, "timed out": 2}, 1.4), run(0, {"held": 1, "docked": 2}, 0.3)], ["0", "1"]
    )
    assert row["eps 0.05: failed / met, largest error / AL"] == "1/6, 1.40" and row["held / timed out"] == "1/2"
    assert row["breaking eps per run"] == "seed 0: 0.05, seed 1: none"
    (row,) = variance.closed_loop_rows([run(0, {"docked": 3})], ["0"])  # a run made before the safety index
    assert row["eps 0.05: failed / met, largest error / AL"] == "0/3, -"
