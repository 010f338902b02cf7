"""`rpod report`: gather every stage's metrics and reports into reports/README.md, with figures.

Reads reports/metrics/<stage>.json and reports/<stage>.md (written by the stages before it),
datasets/shap.zarr (for the SHAP heatmaps) and dvclive/detect/plots/sklearn/*.json (DVCLive's ROC data),
and writes:

    reports/metrics/summary.json           the headline numbers (`dvc metrics show`; stages/pages/summary.py)
    reports/README.md                      the results page: a summary against the paper, figures, then every
                                           stage's report with its profile (no times: those are in the metrics JSON)
    reports/figures/{pose_errors,error_vs_eps}.png   error per range bin (train/test); FGSM error against eps
    reports/figures/shap_heatmaps.png      mean |phi| per output, normal vs adversarial
    reports/figures/roc.png                ROC curves of every detector

`--sync-readme` copies the summary and the generated "Known differences" bullets into the project README
(between the `results` and `differences` markers), on the default profile only: the README publishes the
default profile's numbers, so a smoke run or a `dvc exp run` sweep leaves it alone. `--check` writes
nothing and fails if README and reports/README.md drifted apart, if README's measured differences table is not
reports/gaps.md's (`rpod gaps --sync-readme`), or if a stage report changed after the page was built from it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

from pipeline.io.atomic import atomic_write_text, read_json, save_figure, write_json
from stages.artifacts.dvc import make_hint
from stages.artifacts.paths import BENCHMARKS, GAPS_REPORT, PAGE, README, REPORT_FIGURES, ROC_DATA, SUMMARY, VARIANCE
from stages.artifacts.paths import SHAP as SHAP_STORE
from stages.config.params import PARAMS_FILE, load
from stages.config.schema import Params
from stages.errors import StageError
from stages.pages.differences import differences
from stages.pages.readme import DETECTOR_NAMES, summary_tables
from stages.pages.report import SECTIONS, page_head, section
from stages.pages.summary import summary

BLOCK = "results"
DIFFERENCES = "differences"
GAPS = "gaps"  # README's measured differences table, a copy of reports/gaps.md's (`rpod gaps`)
README_PROFILE = "default"  # the only profile whose numbers README.md publishes


def main(
    sync_readme: bool = typer.Option(False, "--sync-readme", help="Also copy the summary table into README.md."),
    check: bool = typer.Option(
        False,
        "--check",
        help="Write nothing; fail if README.md's results or differences "
        "block differs from reports/README.md's, or a stage report changed since the page "
        "was built.",
    ),
) -> None:
    """Gather all stage metrics into reports/README.md (tables beside the paper's numbers, figures)."""
    if check:
        _check()
        return
    from pipeline.report.markdown import replace_block

    params = load()
    metrics = _load_metrics()
    write_json(SUMMARY, summary(metrics))
    figures = _write_figures(metrics)
    page = build_page(metrics, params, figures)
    atomic_write_text(PAGE, page)
    typer.echo(f"report: {len(SECTIONS)} sections, {len(figures)} figures -> {PAGE}")
    if sync_readme:
        profile = params.profile_name
        if profile != README_PROFILE:
            typer.echo(
                f"report: profile {profile!r}, so {README} is left as it is (it shows the {README_PROFILE} "
                "profile's results)"
            )
            return
        if not README.exists():
            raise StageError(f"{README} not found: run `rpod report` from the repository root")
        from pipeline.report.markdown import extract_block

        text = README.read_text()
        for block in (BLOCK, DIFFERENCES):
            text = replace_block(text, block, extract_block(page, block) or "")
        atomic_write_text(README, text)
        typer.echo(f"report: results and differences blocks copied into {README}")


def write_benchmark(section: str, body: str) -> Path:
    """Replace (or append) the `## section` of reports/benchmarks.md atomically; benchmarks/*.py call this."""
    from pipeline.report.markdown import replace_section

    old = BENCHMARKS.read_text() if BENCHMARKS.exists() else "# Benchmarks\n"
    atomic_write_text(BENCHMARKS, replace_section(old, section, body))
    return BENCHMARKS


def _check() -> None:
    from pipeline.report.markdown import extract_block

    for path in (PAGE, README):
        if not path.exists():
            raise StageError(f"{path} not found: run `rpod report --sync-readme` first")
    page = PAGE.read_text()
    profile = load().profile_name if PARAMS_FILE.exists() else README_PROFILE
    for block in (BLOCK, DIFFERENCES) if profile == README_PROFILE else ():
        ours, theirs = extract_block(page, block), extract_block(README.read_text(), block)
        if ours is None or theirs is None:
            missing = PAGE if ours is None else README
            raise StageError(f"{missing} has no <!-- {block}:start --> ... <!-- {block}:end --> block")
        if ours != theirs:
            raise StageError(
                f"{README}'s {block} block differs from {PAGE}'s: run `rpod report --sync-readme` "
                f"on the {README_PROFILE} profile"
            )
    if profile == README_PROFILE and GAPS_REPORT.exists():  # `rpod gaps`'s table (optional/dvc.yaml)
        if extract_block(GAPS_REPORT.read_text(), GAPS) != extract_block(README.read_text(), GAPS):
            raise StageError(f"{README}'s {GAPS} block differs from {GAPS_REPORT}'s: run `rpod gaps --sync-readme`")
    stale = [report for _, report, _ in SECTIONS if report.exists() and _section_body(report) not in page]
    if stale:
        raise StageError(f"{PAGE} is older than {', '.join(str(r) for r in stale)}: run `rpod report`")
    compared = (
        f"{README} results and differences match {PAGE}"
        if profile == README_PROFILE
        else f"profile {profile!r}: {README} (the {README_PROFILE} profile's results) not compared"
    )
    typer.echo(f"report: {compared}; {PAGE} holds every stage report")


def _section_body(path: Path) -> str:
    """A stage report as build_page embeds it (headings one level down, without its title line)."""
    from pipeline.report.markdown import demote_headings

    return demote_headings(path.read_text().strip(), 1).partition("\n")[2]


def _load_metrics() -> dict[str, dict[str, Any]]:
    """Every stage's metrics; a StageError naming each missing input (metrics, reports, figure data) and the
    stage that writes it, so no page is written with a section or figure left out."""
    missing = [m for _, _, m in SECTIONS if m]
    missing += [r for s, r, _ in SECTIONS if s != "benchmarks"]
    missing = [p for p in missing if not p.exists()]
    metrics = {} if missing else {m.stem: read_json(m) for _, _, m in SECTIONS if m}
    if metrics:
        missing = [
            p for p in [SHAP_STORE, *(ROC_DATA / f"{d}.json" for d in metrics["detect"]["detectors"])] if not p.exists()
        ]
    if missing:
        raise StageError(
            "report: missing inputs (`dvc repro` makes them all): " + "; ".join(f"{p}: {make_hint(p)}" for p in missing)
        )
    return metrics


def _spread(params: Params) -> dict[str, Any] | None:
    """reports/variance.json when it describes runs of this profile (else None: no spread column)."""
    spread = read_json(VARIANCE) if VARIANCE.exists() else {}
    return spread if spread.get("profile") == params.profile_name else None


def build_page(metrics: dict[str, dict[str, Any]], params: Params, figures: list[tuple[str, str, str]]) -> str:
    """reports/README.md: title, summary block, then each stage report one level down with the
    report's own figures (`figures`: (stage, title, file name)) at the end of its section."""
    from pipeline.report.markdown import demote_headings, replace_block

    page = replace_block(page_head(metrics, params), BLOCK, summary_tables(metrics, _spread(params)))
    page += "\n## Known differences from the paper\n"
    page = replace_block(page, DIFFERENCES, differences(metrics, params))
    for stage, report, metric in SECTIONS:
        if report.exists():
            page += section(
                stage,
                report.name,
                metrics.get(metric.stem, {}) if metric else None,
                demote_headings(report.read_text().strip(), 1),
                [(title, name) for st, title, name in figures if st == stage],
            )
    return page


def _write_figures(metrics: dict[str, dict[str, Any]]) -> list[tuple[str, str, str]]:
    """Draw the report's own figures; return (stage, title, file name) for each."""
    import pandas as pd

    from pipeline.report import figures as F

    tr, at, de = metrics["train"], metrics["attack"], metrics["detect"]
    save_figure(
        F.pose_error_bars({"train": tr["train"]["bins"], "test": tr["test"]["bins"]}), REPORT_FIGURES["pose_errors"]
    )
    eps = sorted(at["eps"], key=float)
    save_figure(
        F.error_vs_eps(
            [float(e) for e in eps],
            [at["eps"][e]["position_mean_m"] for e in eps],
            [at["eps"][e]["attitude_mean_deg"] for e in eps],
            at["clean"]["position_mean_m"],
            at["clean"]["attitude_mean_deg"],
            at["method"],
        ),
        REPORT_FIGURES["error_vs_eps"],
    )
    out = [
        ("train", "Mean error per range bin, train and test", "pose_errors.png"),
        ("attack", "Pose error against eps", "error_vs_eps.png"),
    ]
    save_figure(F.shap_heatmaps(_shap_means()), REPORT_FIGURES["shap_heatmaps"])
    out.append(
        ("detect", "SHAP signatures: mean |phi| per output and GAP feature, normal vs adversarial", "shap_heatmaps.png")
    )
    curves = {}
    for name in de["detectors"]:
        roc = pd.DataFrame(read_json(ROC_DATA / f"{name}.json")["roc"])  # DVCLive: [{fpr, tpr, threshold}]
        curves[DETECTOR_NAMES.get(name, name)] = (
            roc["fpr"].to_numpy(),
            roc["tpr"].to_numpy(),
            float(de["detectors"][name]["all"]["roc_auc"]),
        )
    if curves:
        save_figure(F.roc_curves(curves, highlight=DETECTOR_NAMES["lstm"]), REPORT_FIGURES["roc"])
        out.append(("detect", "ROC curves of all detectors on the SHAP test split", "roc.png"))
    return out


def _shap_means() -> dict[str, Any]:
    """Mean |phi| (9, F) over normal and adversarial samples of the SHAP store, read chunk by chunk."""
    from pipeline.io.store import open_zarr
    from pipeline.report.markdown import mean_abs_by_class

    root = open_zarr(SHAP_STORE, "SHAP store")
    values, adv = root["values"], root["is_adversarial"][:].astype(bool)
    step = values.chunks[0]
    return mean_abs_by_class(
        ((values[i : i + step], adv[i : i + step]) for i in range(0, values.shape[0], step)), values.shape[1:]
    )
