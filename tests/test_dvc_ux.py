"""DVC conventions and standalone help: `dvc metrics show` prints one row of readable names, plots carry
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
    return {
        p.stem: json.loads(p.read_text()) for p in (REPO / "reports" / "metrics").glob("*.json") if p.stem != "summary"
    }


# ----------------------------------------------------------------------------- metrics
UNITS = ("_m", "_deg", "_pct", "_eps", "_ratio")  # every headline name ends in its unit (stages/pages/summary.py)


def test_summary_is_grouped_readable_and_has_every_headline():
    from stages.pages.summary import DVC_METRICS, HEADLINES, headline_values, summary

    values = headline_values(_committed_metrics())
    assert list(values) == [h.key for h in HEADLINES if not h.optional or h.key in values]
    assert set(DVC_METRICS) <= {h.key for h in HEADLINES} and len(set(DVC_METRICS)) == len(DVC_METRICS) <= 14
    shown = summary(_committed_metrics())
    assert sum(map(len, shown.values())) == len([k for k in values if k in DVC_METRICS])
    for key, value in values.items():
        group, name = key.split(".")
        assert isinstance(value, float) and name.endswith(UNITS) and len(key) <= 40, key
        if key in DVC_METRICS:
            assert shown[group][name] == value
    assert 0 < values["pose.standard_position_m"] < 50
    assert all(0 <= v <= 100 for k, v in values.items() if k.endswith("_pct"))


def test_summary_leaves_out_a_stage_that_did_not_run():
    from stages.pages.summary import summary

    metrics = _committed_metrics()
    del metrics["robustness"]
    s = summary(metrics)
    assert "robustness" not in s and "integrity" not in s and "standard_position_m" in s["pose"]


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
        st = dvc_stages()[stage]  # dvc.yaml's or optional/dvc.yaml's
        return {Path(o if isinstance(o, str) else next(iter(o))) for o in st.get("outs", []) + st.get("metrics", [])}

    for path, stage in WRITTEN_BY.items():
        assert any(path == out or out in path.parents for out in listed(stage)), f"{path} is not an out of {stage}"


@pytest.mark.skipif(not DVC.exists(), reason="dvc not installed beside python")
def test_dvc_metrics_show_prints_one_row_of_readable_names(tmp_path):
    """One header and one row; every column is `<group>.<what>_<unit>` (DVC joins the nested keys with dots)."""
    from pipeline.io.atomic import write_json
    from stages.pages.summary import DVC_METRICS, HEADLINES, headline_values, summary

    values = headline_values(_committed_metrics())
    assert set(values) >= {h.key for h in HEADLINES if not h.optional}
    values = [k for k in values if k in DVC_METRICS]
    for name in ("dvc.yaml", "params.yaml"):  # dvc.yaml templates external-input deps from params.yaml
        shutil.copy(REPO / name, tmp_path / name)
    write_json(tmp_path / "reports" / "metrics" / "summary.json", summary(_committed_metrics()))
    subprocess.run([str(DVC), "init", "--no-scm", "-q"], cwd=tmp_path, check=True)
    out = subprocess.run([str(DVC), "metrics", "show"], cwd=tmp_path, check=True, capture_output=True, text=True)
    header, row = out.stdout.splitlines()
    assert header.split() == ["Path", *sorted(values)] and len(values) >= 10, header
    assert row.split()[0] == "reports/metrics/summary.json" and len(row.split()) == 1 + len(values)


# ----------------------------------------------------------------------------- plots
def test_plots_have_titles_axis_units_and_no_duplicates():
    assert not [s for s, st in DVC_YAML["stages"].items() if "plots" in st], "stage-level plots draw curves twice"
    curves, images = [], []
    for entry in DVC_YAML["plots"]:
        if isinstance(entry, str):  # an image plot: a PNG figure or a folder of them
            images.append(entry)
            continue
        ((name, plot),) = entry.items()
        assert plot.get("title") and plot.get("x_label") and plot.get("y_label"), name
        assert "(" in plot["y_label"] and "(" in plot["x_label"], f"{name}: axis names give units"
        curves += [(path, field) for path, field in plot["y"].items()]
    assert len(curves) == len(set(curves)) and len(images) == len(set(images))
    for path in [p for p, _ in curves] + images:
        assert producer(path) is not None, f"{path} is no stage's output"
        assert subprocess.run(["git", "check-ignore", "-q", path], cwd=REPO).returncode == 1, f"{path} is ignored"
    assert subprocess.run(["git", "check-ignore", "-q", "dvc_plots/index.html"], cwd=REPO).returncode == 0


def test_dvc_plots_show_draws_offline_with_the_vega_dvc_render_names():
    """.dvc/config points `dvc plots show` at conf/plots/offline.html: dvc-render's page with the Vega, Vega-Lite and
    Vega-Embed it loads from a CDN written in (same versions, so a dvc-render upgrade that moves them fails here)."""
    import configparser
    import re

    from dvc_render.vega import VegaRenderer

    config = configparser.ConfigParser()
    config.read(REPO / ".dvc" / "config")
    template = (REPO / ".dvc" / config["plots"]["html_template"]).resolve()
    assert template == REPO / "conf" / "plots" / "offline.html"
    page = template.read_text()
    assert "{plot_divs}" in page and "{scripts}" not in page and "<script src" not in page
    wanted = re.findall(r"npm/([\w-]+)@([\d.]+)", VegaRenderer.SCRIPTS)
    assert len(wanted) == 3
    for name, version in wanted:
        assert f"/* {name} {version} (npm, build/{name}.min.js) */" in page, (name, version)


def test_every_figure_is_an_image_plot():
    from stages.artifacts.paths import WRITTEN_BY

    figures = {str(p) for p in WRITTEN_BY if p.suffix == ".png" or p.name == "previews"}
    assert figures == {e for e in DVC_YAML["plots"] if isinstance(e, str)}


def test_the_roc_curves_are_dvclive_sklearn_plots_of_every_detector():
    """The ROC plot reads what `Live.log_sklearn_plot("roc", ...)` writes for the LSTM and each baseline."""
    from stages.artifacts.paths import ROC_DATA

    (roc,) = [e["roc"] for e in DVC_YAML["plots"] if isinstance(e, dict) and "roc" in e]
    detectors = ["lstm", *yaml.safe_load((REPO / "params.yaml").read_text())["detect"]["baselines"]]
    assert roc["y"] == {str(ROC_DATA / f"{d}.json"): "tpr" for d in detectors} and roc["x"] == "fpr"


def test_the_shipped_detector_has_its_roc_and_training_curves():
    """The chain that ships has its own detector (detect_robust): its ROC and training curves are plotted too."""
    plots = {name: plot for e in DVC_YAML["plots"] if isinstance(e, dict) for name, plot in e.items()}
    assert plots["roc_shipped"]["y"] == {"dvclive/detect_robust/plots/sklearn/lstm.json": "tpr"}
    for name in ("detector_loss", "detector_accuracy"):
        assert {Path(p).parts[1] for p in plots[name]["y"]} == {"detect", "detect_robust"}, name


@pytest.mark.skipif(not DVC.exists(), reason="dvc not installed beside python")
def test_the_models_are_dvc_model_artifacts():
    """dvc.yaml's `artifacts` (what DVCLive's log_artifact(type="model") writes) name every model a stage makes."""
    from dvc.repo import Repo

    from stages.artifacts.paths import DEFENSE, DEFENSE_STANDARD, DETECTOR, DETECTOR_ROBUST, POSE, POSE_ROBUST

    with Repo(str(REPO)) as repo:
        found = {name: (a.path, a.type) for a in repo.artifacts.read().values() for name, a in a.items()}
    assert found == {
        "pose": (str(POSE), "model"),
        "detector": (str(DETECTOR), "model"),
        "defense": (str(DEFENSE), "model"),
        "pose_robust": (str(POSE_ROBUST), "model"),
        "detector_robust": (str(DETECTOR_ROBUST), "model"),
        "defense_standard": (str(DEFENSE_STANDARD), "model"),
    }
    assert all(producer(path) for path, _ in found.values())


# ----------------------------------------------------------------------------- help
DVC_COMMANDS = [c for c in STAGES if any(st["cmd"].split()[:2] == ["rpod", c] for st in dvc_stages().values())]


def test_commands_outside_dvc_have_help_too():
    for command in sorted(set(STAGES) - set(DVC_COMMANDS)):  # e.g. `rpod export`
        result = CliRunner().invoke(app, [command, "--help"], terminal_width=200)
        assert result.exit_code == 0 and "SPEC" not in result.output, command


@pytest.mark.parametrize("command", DVC_COMMANDS)
def test_stage_help_lists_its_params_with_comments(command):
    from stages.help import CONFIG, command_params, config_comments

    comments = config_comments(CONFIG.read_text())
    keys = command_params(command, comments)
    listed = {
        p for s, st in dvc_stages().items() if st["cmd"].split()[:2] == ["rpod", command] for p in st.get("params", [])
    }
    assert listed and all(any(k == p or k.startswith(p + ".") for k in keys) for p in listed), listed
    result = CliRunner().invoke(app, [command, "--help"], terminal_width=200)
    assert result.exit_code == 0, result.output
    assert "SPEC" not in result.output
    from stages.help import _shown, current_values

    now = current_values()
    text = " ".join(result.output.split())
    for key in keys:
        assert comments[key][1], f"conf/config.yaml: {key} has no comment"
        value = f" = {' '.join(_shown(now[key]).split())}" if key in now else ""
        assert f"{key}{value}: {comments[key][1][:30]}" in text, key
    assert "dvc exp run -S key=value" in text


def test_stage_help_shows_the_value_params_yaml_holds_now(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "params.yaml").write_text("train:\n  epochs: 7\n  max_minutes: null\n")
    text = " ".join(CliRunner().invoke(app, ["train", "--help"], terminal_width=200).output.split())
    assert "train.epochs = 7: " in text and "train.max_minutes = null: " in text
    assert "train.batch_size: " in text  # not in this params.yaml: no value shown


def test_stage_help_does_not_block_on_a_fifo_params_yaml(tmp_path, monkeypatch):
    """--help reads params.yaml for the values it shows: a FIFO there shows none instead of hanging."""
    import os

    monkeypatch.chdir(tmp_path)
    os.mkfifo(tmp_path / "params.yaml")
    result = CliRunner().invoke(app, ["train", "--help"], terminal_width=200)
    text = " ".join(result.output.split())
    assert result.exit_code == 0 and "train.epochs: " in text and "train.epochs = " not in text


def _plain(output: str) -> str:
    """A CLI error as one line: the box Rich draws around it (80 columns whatever the terminal) taken away."""
    return " ".join(output.replace("│", " ").split())


@pytest.mark.parametrize(
    "args, key",
    [
        (["train", "--epochs", "3"], "train.epochs"),
        (["attack", "--eps", "0.1"], "attack.eps"),
        (["render", "--samples", "8"], "render.samples"),
    ],
)
def test_an_option_that_is_a_param_says_how_to_set_it(args, key, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "params.yaml").write_text(f"profile_name: smoke\n{key.split('.')[0]}:\n  {key.split('.')[1]}: 5\n")
    result = CliRunner().invoke(app, args, terminal_width=300)
    text = _plain(result.output)
    assert result.exit_code == 2, result.output
    assert f"No such option: {args[1]}. {key} is a param (now 5 in params.yaml)" in text, text
    assert f"rpod params smoke -S {key}=VALUE" in text and f"dvc exp run -S {key}=VALUE" in text, text


def test_an_unknown_option_is_still_refused_plainly():
    result = CliRunner().invoke(app, ["train", "--no-such-thing"], terminal_width=200)
    assert result.exit_code == 2 and "No such option: --no-such-thing" in result.output and "param" not in result.output


def test_a_stage_name_that_is_a_flag_names_its_command():
    flagged = {n: st["cmd"] for n, st in dvc_stages().items() if st["cmd"].split()[:2] != ["rpod", n]}
    assert {"robust", "surrogate", "shap_robust", "detect_robust", "detect_render", "calibrate_standard"} <= set(
        flagged
    )
    for name, cmd in flagged.items():
        result = CliRunner().invoke(app, [name], terminal_width=300)
        assert result.exit_code == 2 and f"runs `{cmd}`" in _plain(result.output), (name, result.output)


def test_root_help_maps_every_stage_to_its_command_and_version_is_the_installed_one(monkeypatch):
    from importlib.metadata import version

    monkeypatch.setenv("COLUMNS", "200")  # rich wraps at the terminal's width (80 without one): one row per stage here
    text = CliRunner().invoke(app, ["--help"], terminal_width=200).output
    rows = {tuple(line.strip(" │").split(None, 1)) for line in text.splitlines()}
    assert all((name, st["cmd"]) in rows for name, st in dvc_stages().items()), text
    assert "Each command is one DVC stage" not in text
    result = CliRunner().invoke(app, ["--version"])
    assert result.exit_code == 0 and result.output == f"rpodguard {version('rpodguard')}\n"


def test_config_comments_parse_sections_and_continuations():
    from stages.help import config_comments

    text = (
        "defaults:\n  - _self_\nseed: 0   # base\nsec:      # a section\n  a: [1, 2]   # metres;\n"
        "              # more\n  sub:\n    b: 3\nempty: {}\n"
    )
    c = config_comments(text)
    assert c == {
        "seed": (True, "base"),
        "sec": (False, "a section"),
        "sec.a": (True, "metres; more"),
        "sec.sub": (False, ""),
        "sec.sub.b": (True, ""),
        "empty": (False, ""),
    }


# ----------------------------------------------------------------------------- missing inputs
def test_every_input_a_stage_reads_has_a_producer():
    """Each dvc.yaml data dep (not code) is some stage's output: the map behind the missing-input errors (benchmarks
    and the seed spread come from scripts)."""
    for name, st in dvc_stages().items():
        for dep in st.get("deps", []):
            scripted = ("reports/benchmarks.md", "reports/variance.json")
            external = dep.startswith("${")  # a user's file named by a param (inputs/none when unset)
            if not dep.startswith(("pipeline/", "stages/")) and dep not in scripted and not external:
                assert producer(dep) not in (None, name), f"{name}: {dep}"
    assert producer(REPO / "models" / "pose.pt") == "train" and producer("datasets/render/meta.json") == "render"
    assert producer("somewhere/else.json") is None


@pytest.mark.parametrize(
    "load, message",
    [
        ("pose", "models/pose.pt not found: run `dvc repro train` (or `rpod train`)"),
        ("surrogate", "models/surrogate.pt not found: run `dvc repro surrogate` (or `rpod train --surrogate`)"),
        (
            "eval_render",
            "datasets/eval_render/meta.json not found: run `dvc repro eval_render` (or `rpod eval_render`)",
        ),
        ("shap", "datasets/shap.zarr not found: run `dvc repro shap` (or `rpod shap --model standard`)"),
    ],
)
def test_missing_input_names_the_stage_that_writes_it(tmp_path, monkeypatch, load, message):
    from stages.artifacts import models
    from stages.artifacts import readers as artifacts
    from stages.artifacts.paths import SHAP
    from stages.config.params import load as load_params

    params = load_params(REPO / "params.yaml")
    monkeypatch.chdir(tmp_path)
    call = {
        "pose": lambda: models.load_pose(params),
        "surrogate": lambda: models.load_pose(params, "models/surrogate.pt"),
        "eval_render": lambda: artifacts.read_eval_render(params),
        "shap": lambda: artifacts.read_shap_store(SHAP, "hash"),
    }[load]
    with pytest.raises(DataError) as err:
        call()
    assert message in str(err.value)


def test_report_refuses_a_missing_figure_input(tmp_path, monkeypatch):
    """Every metrics file and stage report present but no SHAP store: no page, and the message says
    which stage makes it (before, the SHAP figure was silently left out)."""
    from stages.artifacts.paths import ROC_DATA

    shutil.copytree(REPO / "reports/metrics", tmp_path / "reports/metrics")
    for name in _committed_metrics()["detect"]["detectors"]:  # DVCLive's ROC data, as `rpod detect` writes it
        (tmp_path / ROC_DATA).mkdir(parents=True, exist_ok=True)
        (tmp_path / ROC_DATA / f"{name}.json").write_text('{"roc": [{"fpr": 0, "tpr": 0, "threshold": 1}]}')
    for md in (REPO / "reports").glob("*.md"):
        shutil.copy(md, tmp_path / "reports" / md.name)
    (tmp_path / "reports" / "README.md").unlink()
    (tmp_path / "reports" / "metrics" / "summary.json").unlink()  # committed, written by `rpod report`
    (tmp_path / "dvclive" / "detect" / "plots" / "sklearn" / "lid.json").unlink()
    shutil.copy(REPO / "params.yaml", tmp_path / "params.yaml")
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(app, ["report"])
    assert result.exit_code != 0 and isinstance(result.exception, StageError)
    message = str(result.exception)
    assert "datasets/shap.zarr: run `dvc repro shap`" in message
    assert "dvclive/detect/plots/sklearn/lid.json: run `dvc repro detect`" in message
    assert not (tmp_path / "reports" / "README.md").exists()
    assert not (tmp_path / "reports" / "metrics" / "summary.json").exists()
