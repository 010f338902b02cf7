"""DVC conventions and standalone help: `dvc metrics show` prints a small flat summary, plots carry
titles and axis units with no duplicates, every stage's --help lists the params dvc.yaml gives it
(with conf/config.yaml's comments), and a missing input names the stage that writes it."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from typer.testing import CliRunner

from pipeline.io.errors import DataError
from stages.artifacts.dvc import dvc_stages, producer
from stages.cli import STAGES, app
from stages.errors import StageError

REPO = Path(__file__).resolve().parent.parent
DVC = Path(sys.executable).with_name("dvc")
DVC_YAML = yaml.safe_load((REPO / "dvc.yaml").read_text())


def _committed_metrics() -> dict[str, dict]:
    return {p.stem: json.loads(p.read_text()) for p in (REPO / "reports" / "metrics").glob("*.json")
            if p.stem != "summary"}


# ----------------------------------------------------------------------------- metrics
def test_summary_is_flat_short_and_has_every_headline():
    from stages.pages.summary import HEADLINES, summary

    s = summary(_committed_metrics())
    assert list(s) == [h.key for h in HEADLINES]
    assert all(isinstance(v, float) and len(k) <= 8 for k, v in s.items())
    assert 0 < s["pos_m"] < 50 and all(0 <= s[k] <= 100 for k in ("lstm", "chain", "held", "hmi01", "hmi05", "avail",
                                                                   "collide"))


def test_summary_leaves_out_a_stage_that_did_not_run():
    from stages.pages.summary import summary

    metrics = _committed_metrics()
    del metrics["robustness"]
    s = summary(metrics)
    assert "hmi01" not in s and "pos_m" in s


def test_only_the_summary_is_a_dvc_metric_and_details_stay_outputs():
    metrics = {s: [next(iter(m)) for m in st.get("metrics", [])] for s, st in DVC_YAML["stages"].items()}
    assert {s: m for s, m in metrics.items() if m} == {"report": ["reports/metrics/summary.json"]}
    for stage in ("train", "attack", "guidance", "detect", "evaluate", "robustness", "lab"):
        outs = {next(iter(o)): o[next(iter(o))] for o in DVC_YAML["stages"][stage]["outs"] if isinstance(o, dict)}
        assert outs[f"reports/metrics/{stage}.json"] == {"cache": False}


def test_every_output_path_is_an_out_of_the_stage_that_writes_it():
    """stages/artifacts/paths.py WRITTEN_BY: each output (or a folder holding it) is in the `outs` or
    `metrics` of the dvc.yaml stage it names."""
    from stages.artifacts.paths import WRITTEN_BY

    def listed(stage: str) -> set[Path]:
        st = DVC_YAML["stages"][stage]
        return {Path(o if isinstance(o, str) else next(iter(o))) for o in st.get("outs", []) + st.get("metrics", [])}

    for path, stage in WRITTEN_BY.items():
        assert any(path == out or out in path.parents for out in listed(stage)), f"{path} is not an out of {stage}"


@pytest.mark.skipif(not DVC.exists(), reason="dvc not installed beside python")
def test_dvc_metrics_show_fits_in_120_columns(tmp_path):
    from pipeline.io.atomic import write_json
    from stages.pages.summary import summary

    for name in ("dvc.yaml", "params.yaml"):   # dvc.yaml templates external-input deps from params.yaml
        shutil.copy(REPO / name, tmp_path / name)
    write_json(tmp_path / "reports" / "metrics" / "summary.json", summary(_committed_metrics()))
    subprocess.run([str(DVC), "init", "--no-scm", "-q"], cwd=tmp_path, check=True)
    out = subprocess.run([str(DVC), "metrics", "show"], cwd=tmp_path, check=True, capture_output=True, text=True)
    lines = out.stdout.splitlines()
    assert len(lines) == 2 and "pos_m" in lines[0] and max(map(len, lines)) <= 120, out.stdout


# ----------------------------------------------------------------------------- plots
def test_plots_have_titles_axis_units_and_no_duplicates():
    assert not [s for s, st in DVC_YAML["stages"].items() if "plots" in st], "stage-level plots draw curves twice"
    curves = []
    for entry in DVC_YAML["plots"]:
        (name, plot), = entry.items()
        assert plot.get("title") and plot.get("x_label") and plot.get("y_label"), name
        assert "(" in plot["y_label"] and "(" in plot["x_label"], f"{name}: axis names give units"
        curves += [(path, field) for path, field in plot["y"].items()]
    assert len(curves) == len(set(curves))
    for path, _ in curves:
        assert producer(path) is not None, f"{path} is no stage's output"
        assert subprocess.run(["git", "check-ignore", "-q", path], cwd=REPO).returncode == 1, f"{path} is ignored"
    assert subprocess.run(["git", "check-ignore", "-q", "dvc_plots/index.html"], cwd=REPO).returncode == 0


# ----------------------------------------------------------------------------- help
DVC_COMMANDS = [c for c in STAGES if any(st["cmd"].split()[:2] == ["rpod", c] for st in DVC_YAML["stages"].values())]


def test_commands_outside_dvc_have_help_too():
    for command in sorted(set(STAGES) - set(DVC_COMMANDS)):      # e.g. `rpod export`
        result = CliRunner().invoke(app, [command, "--help"], terminal_width=200)
        assert result.exit_code == 0 and "SPEC" not in result.output, command


@pytest.mark.parametrize("command", DVC_COMMANDS)
def test_stage_help_lists_its_params_with_comments(command):
    from stages.config.help import CONFIG, command_params, config_comments

    comments = config_comments(CONFIG.read_text())
    keys = command_params(command, comments)
    listed = {p for s, st in DVC_YAML["stages"].items() if st["cmd"].split()[:2] == ["rpod", command]
              for p in st.get("params", [])}
    assert listed and all(any(k == p or k.startswith(p + ".") for k in keys) for p in listed), listed
    result = CliRunner().invoke(app, [command, "--help"], terminal_width=200)
    assert result.exit_code == 0, result.output
    assert "SPEC" not in result.output
    for key in keys:
        assert comments[key][1], f"conf/config.yaml: {key} has no comment"
        assert f"{key}: {comments[key][1][:30]}" in " ".join(result.output.split()), key


def test_config_comments_parse_sections_and_continuations():
    from stages.config.help import config_comments

    text = ("defaults:\n  - _self_\nseed: 0   # base\nsec:      # a section\n  a: [1, 2]   # metres;\n"
            "              # more\n  sub:\n    b: 3\nempty: {}\n")
    c = config_comments(text)
    assert c == {"seed": (True, "base"), "sec": (False, "a section"), "sec.a": (True, "metres; more"),
                 "sec.sub": (False, ""), "sec.sub.b": (True, ""), "empty": (False, "")}


# ----------------------------------------------------------------------------- missing inputs
def test_every_input_a_stage_reads_has_a_producer():
    """Each dvc.yaml data dep (not code) is some stage's output: the map behind the missing-input errors (benchmarks
    and the seed spread come from scripts)."""
    for name, st in dvc_stages().items():
        for dep in st.get("deps", []):
            scripted = ("reports/benchmarks.md", "reports/variance.json")
            external = dep.startswith("${")           # a user's file named by a param (inputs/none when unset)
            if not dep.startswith(("pipeline/", "stages/")) and dep not in scripted and not external:
                assert producer(dep) not in (None, name), f"{name}: {dep}"
    assert producer(REPO / "models" / "pose.pt") == "train" and producer("datasets/render/meta.json") == "render"
    assert producer("somewhere/else.json") is None


@pytest.mark.parametrize("load, message", [
    ("pose", "models/pose.pt not found: run `dvc repro train` (or `rpod train`)"),
    ("surrogate", "models/surrogate.pt not found: run `dvc repro surrogate` (or `rpod train --surrogate`)"),
    ("eval_render", "datasets/eval_render/meta.json not found: run `dvc repro eval_render` (or `rpod eval_render`)"),
    ("shap", "datasets/shap.zarr not found: run `dvc repro shap` (or `rpod shap`)"),
])
def test_missing_input_names_the_stage_that_writes_it(tmp_path, monkeypatch, load, message):
    from stages.artifacts import models, readers as artifacts
    from stages.artifacts.paths import SHAP
    from stages.config.params import load as load_params

    params = load_params(REPO / "params.yaml")
    monkeypatch.chdir(tmp_path)
    call = {"pose": lambda: models.load_pose(params),
            "surrogate": lambda: models.load_pose(params, "models/surrogate.pt"),
            "eval_render": lambda: artifacts.read_eval_render(params),
            "shap": lambda: artifacts.read_shap_store(SHAP, "hash")}[load]
    with pytest.raises(DataError) as err:
        call()
    assert message in str(err.value)


def test_report_refuses_a_missing_figure_input(tmp_path, monkeypatch):
    """Every metrics file and stage report present but no SHAP store: no page, and the message says
    which stage makes it (before, the SHAP figure was silently left out)."""
    for sub in ("reports/metrics", "reports/plots"):
        shutil.copytree(REPO / sub, tmp_path / sub)
    for md in (REPO / "reports").glob("*.md"):
        shutil.copy(md, tmp_path / "reports" / md.name)
    (tmp_path / "reports" / "README.md").unlink()
    (tmp_path / "reports" / "metrics" / "summary.json").unlink()   # committed, written by `rpod report`
    (tmp_path / "reports" / "plots" / "roc" / "lid.csv").unlink()
    shutil.copy(REPO / "params.yaml", tmp_path / "params.yaml")
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(app, ["report"])
    assert result.exit_code != 0 and isinstance(result.exception, StageError)
    message = str(result.exception)
    assert "datasets/shap.zarr: run `dvc repro shap`" in message
    assert "reports/plots/roc/lid.csv: run `dvc repro detect`" in message
    assert not (tmp_path / "reports" / "README.md").exists()
    assert not (tmp_path / "reports" / "metrics" / "summary.json").exists()
