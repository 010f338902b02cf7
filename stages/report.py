"""`rpod report`: gather every stage's metrics and reports into reports/README.md, with figures.

Reads reports/metrics/<stage>.json and reports/<stage>.md (written by the stages before it),
datasets/shap.zarr (for the SHAP heatmaps) and reports/plots/roc/*.csv (ROC curves), and writes:

    reports/README.md                      the results page: a summary against the paper, figures,
                                           then every stage's report with its profile and time
    reports/figures/pose_errors.png        train/test error per range bin
    reports/figures/error_vs_eps.png       FGSM pose error against eps
    reports/figures/shap_heatmaps.png      mean |phi| per output, normal vs adversarial
    reports/figures/roc.png                ROC curves of every detector

`--sync-readme` copies the summary into the project README (between the `results` markers);
`--check` only verifies that README and reports/README.md agree, and fails if they drifted.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

from stages import params as params_mod
from stages.detect import ROC_DIR, SHAP as SHAP_STORE
from stages.io import StageError, atomic_write_text, read_json

PAGE = Path("reports/README.md")
README = Path("README.md")
FIGURES = Path("reports/figures")
BLOCK = "results"
BENCHMARKS = Path(__file__).resolve().parent.parent / "reports" / "benchmarks.md"

# (stage, report file, metrics file or None) in pipeline order.
SECTIONS = [
    ("label", "dataset.md", None),
    ("train", "pose.md", "train"),
    ("attack", "attack.md", "attack"),
    ("guidance", "guidance.md", "guidance"),
    ("detect", "detector.md", "detect"),
    ("evaluate", "integrated.md", "evaluate"),
    ("robustness", "robustness.md", "robustness"),
    ("lab", "lab.md", "lab"),
    ("benchmarks", "benchmarks.md", None),
]

PAPER = {
    "position_m": 0.49, "attitude_deg": 0.68, "detector": 99.90, "integrated": 99.21, "lab": 96.29,
    "integrated_eps": {"0.5": 100.0, "0.3": 99.99, "0.1": 99.97, "0.05": 99.99, "0.01": 97.67},
    "lab_eps": {"0.5": 100.0, "0.3": 100.0, "0.1": 100.0, "0.05": 98.44, "0.01": 90.44},
}
DETECTOR_NAMES = {"lstm": "LSTM on SHAP (SPEC 7)", "mlp": "MLP on SHAP", "mahalanobis": "Mahalanobis (GAP)",
                  "lid": "LID (GAP)", "squeeze": "feature squeezing"}


def main(
    sync_readme: bool = typer.Option(False, "--sync-readme", help="Also copy the summary table into README.md."),
    check: bool = typer.Option(False, "--check", help="Write nothing; fail if README.md's results block differs "
                               "from reports/README.md's."),
) -> None:
    """Gather all stage metrics into reports/README.md (tables beside the paper's numbers, figures)."""
    if check:
        _check()
        return
    from pipeline.report import replace_block

    params = params_mod.load()
    metrics = _load_metrics()
    figures = _write_figures(metrics)
    page = build_page(metrics, params, figures)
    atomic_write_text(PAGE, page)
    typer.echo(f"report: {len(SECTIONS)} sections, {len(figures)} figures -> {PAGE}")
    if sync_readme:
        if not README.exists():
            raise StageError(f"{README} not found: run `rpod report` from the repository root")
        from pipeline.report import extract_block

        atomic_write_text(README, replace_block(README.read_text(), BLOCK, extract_block(page, BLOCK) or ""))
        typer.echo(f"report: results block copied into {README}")


def write_benchmark(section: str, body: str) -> Path:
    """Replace (or append) the `## section` of reports/benchmarks.md atomically; benchmarks/*.py call this."""
    from pipeline.report import replace_section

    old = BENCHMARKS.read_text() if BENCHMARKS.exists() else "# Benchmarks\n"
    atomic_write_text(BENCHMARKS, replace_section(old, section, body))
    return BENCHMARKS


def _check() -> None:
    from pipeline.report import extract_block

    for path in (PAGE, README):
        if not path.exists():
            raise StageError(f"{path} not found: run `rpod report --sync-readme` first")
    ours, theirs = extract_block(PAGE.read_text(), BLOCK), extract_block(README.read_text(), BLOCK)
    if ours is None or theirs is None:
        missing = PAGE if ours is None else README
        raise StageError(f"{missing} has no <!-- {BLOCK}:start --> ... <!-- {BLOCK}:end --> block")
    if ours != theirs:
        raise StageError(f"{README}'s results block differs from {PAGE}'s: run `rpod report --sync-readme`")
    typer.echo(f"report: {README} results match {PAGE}")


def _load_metrics() -> dict[str, dict[str, Any]]:
    missing = [f"reports/metrics/{m}.json (rpod {s})" for s, _, m in SECTIONS
               if m and not Path(f"reports/metrics/{m}.json").exists()]
    missing += [f"reports/{r} (rpod {s})" for s, r, _ in SECTIONS
                if s != "benchmarks" and not Path(f"reports/{r}").exists()]
    if missing:
        raise StageError("report: missing inputs, run their stages first (`dvc repro` runs all): " + ", ".join(missing))
    return {m: read_json(f"reports/metrics/{m}.json") for _, _, m in SECTIONS if m}


def _fmt(x: float | None, decimals: int = 2) -> str:
    return "-" if x is None else f"{x:.{decimals}f}"


def _eps_keys(d: dict[str, Any]) -> list[str]:
    """eps keys of a per-eps dict, largest first (the paper's column order)."""
    return sorted(d, key=float, reverse=True)


def summary_tables(metrics: dict[str, dict[str, Any]]) -> str:
    """The headline results against the paper, as Markdown (this is what README.md shows)."""
    from pipeline.report import markdown_table

    tr, at, gd, de, ev, lab = (metrics[k] for k in ("train", "attack", "guidance", "detect", "evaluate", "lab"))
    eps_at = _eps_keys(at["eps"])
    runs = [r for r in gd["runs"] if r.get("attacked_frames", 1) > 0]
    broken = sum(r["outcome"] != "rendezvous held" for r in runs)
    dets = de["detectors"]
    best_base = max((k for k in dets if k != "lstm"), key=lambda k: dets[k]["all"]["accuracy"])
    rows = [
        ("pose, test mean position error (m)", _fmt(tr["test"]["pos_mean_m"]), _fmt(PAPER["position_m"]), "train"),
        ("pose, test mean attitude error (deg)", _fmt(tr["test"]["att_mean_deg"]), _fmt(PAPER["attitude_deg"]), "train"),
        ("FGSM mean position error (m) at eps " + " / ".join(eps_at),
         " / ".join(_fmt(at["eps"][e]["position_mean_m"], 1) for e in eps_at), "-", "attack"),
        ("closed loop, no attack", f"{gd['baseline']['outcome']} (miss {_fmt(gd['baseline']['miss_m'])} m)",
         "reaches the target", "guidance"),
        ("closed loop, attacked runs that lost the rendezvous", f"{broken} of {len(runs)}", "-", "guidance"),
        ("LSTM detector accuracy, SHAP test split (%)", _fmt(100 * dets["lstm"]["all"]["accuracy"]),
         _fmt(PAPER["detector"]), "detect"),
        (f"best baseline detector accuracy (%): {DETECTOR_NAMES.get(best_base, best_base)}",
         _fmt(100 * dets[best_base]["all"]["accuracy"]), "-", "detect"),
        ("integrated detection accuracy, mean over eps (%)", _fmt(100 * ev["accuracy_mean"]),
         _fmt(PAPER["integrated"]), "evaluate"),
        (f"lab detection accuracy, mean over eps (%), {'main' if lab.get('reused_models', True) else 'retrained'} models",
         _fmt(100 * lab["accuracy_mean"]), _fmt(PAPER["lab"]), "lab"),
        *_robustness_rows(metrics["robustness"]),
    ]
    table = markdown_table([{"result": r, "this run": v, "paper": p, "stage": f"`{s}`"} for r, v, p, s in rows])
    eps_rows = []
    for e in sorted(set(ev["per_eps"]) | set(lab["per_eps"]), key=float, reverse=True):
        get = lambda m, k: _fmt(100 * m["per_eps"][e]["accuracy"]) if e in m["per_eps"] else "-"  # noqa: E731
        eps_rows.append({"eps": e, "integrated (%)": get(ev, e), "paper, integrated (%)": _fmt(PAPER["integrated_eps"].get(e)),
                         "lab, 10-frame attacks (%)": get(lab, e), "paper, lab (%)": _fmt(PAPER["lab_eps"].get(e))})
    profiles = sorted({m.get("profile", "unknown") for m in metrics.values()})
    produced = sorted(m.get("produced", "") for m in metrics.values() if m.get("produced"))
    when = f"{produced[0]} to {produced[-1]}" if produced else "time not recorded"
    head = (f"Profile `{'`, `'.join(profiles)}`; stages run {when}. Paper: 480x270 images, full-width network, "
            "50 epochs, 32,500 images; each stage's section of the results page says what differs and why.")
    return f"{head}\n\n{table}\nDetection accuracy per eps (correct flags over all frames):\n\n{markdown_table(eps_rows)}"


def _robustness_rows(m: dict[str, Any]) -> list[tuple[str, str, str, str]]:
    """Summary rows: worst harmful-undetected rate over all robustness attacks (adaptive included) at
    eps 0.05 and 0.01, percent with the 95% Wilson interval ("-" when the stage did not run that eps)."""
    out = []
    for e in ("0.05", "0.01"):
        w = m["worst_harmful_undetected"].get(e)
        value = "-"
        if w is not None:
            lo, hi = w["ci95_harmful_undetected"]
            value = (f"{_fmt(100 * w['harmful_undetected_rate'], 1)} [{_fmt(100 * lo, 1)}, {_fmt(100 * hi, 1)}] "
                     f"({w['attack']})")
        out.append((f"worst harmful-undetected rate (%) at eps {e}, any attack incl. adaptive", value, "-", "robustness"))
    return out


def build_page(metrics: dict[str, dict[str, Any]], params: dict[str, Any], figures: list[tuple[str, str, str]]) -> str:
    """reports/README.md: title, summary block, then each stage report one level down with the
    report's own figures (`figures`: (stage, title, file name)) at the end of its section."""
    from pipeline.report import demote_headings, replace_block

    profiles = {m.get("profile", "unknown") for m in metrics.values()}
    warn = ""
    if len(profiles) > 1:
        warn = (f"\n> **Mixed profiles** ({', '.join(sorted(profiles))}): some stages are stale; run `dvc repro` "
                "to bring them all to the current params.yaml.\n")
    hashes = {k: m["model_hash"] for k, m in metrics.items()
              if "model_hash" in m and not (k == "lab" and m.get("reused_models") is False)}
    if len(set(hashes.values())) > 1:
        warn += (f"\n> **Mixed pose models** ({', '.join(f'{k} {v}' for k, v in sorted(hashes.items()))}): "
                 "some stages ran on an older checkpoint.\n")
    page = (f"# rpodguard results\n\nWritten by `rpod report` from `reports/metrics/*.json` and the stage reports "
            f"beside this file; params profile `{params.get('profile_name', 'unknown')}`. Regenerate with "
            f"`dvc repro`. Every section below is one stage's report, stamped with the profile and time it ran."
            f"\n{warn}\n## Summary against the paper\n")
    page = replace_block(page, BLOCK, summary_tables(metrics))
    for stage, report, metric in SECTIONS:
        path = Path("reports") / report
        if not path.exists():
            continue
        m = metrics.get(metric or "", {})
        stamp = (f"_`rpod {stage}`, profile `{m.get('profile', 'unknown')}`, produced "
                 f"{m.get('produced', 'at an unrecorded time')}; source [{report}]({report})._" if metric
                 else f"_Source [{report}]({report})._")
        body = demote_headings(path.read_text().strip(), 1)
        first, _, rest = body.partition("\n")
        page += f"\n{first}\n\n{stamp}\n{rest}\n"
        extra = [(title, name) for st, title, name in figures if st == stage]
        if extra:
            page += "\n### Figures\n\n" + "\n\n".join(f"{title}:\n\n![{title}](figures/{name})" for title, name in extra)
            page += "\n"
    return page


def _save(fig, name: str) -> None:
    FIGURES.mkdir(parents=True, exist_ok=True)
    tmp = FIGURES / f".{name}.tmp.png"
    fig.savefig(tmp, dpi=110)
    tmp.replace(FIGURES / name)


def _write_figures(metrics: dict[str, dict[str, Any]]) -> list[tuple[str, str, str]]:
    """Draw the report's own figures; return (stage, title, file name) for each."""
    import pandas as pd

    from pipeline import figures as F

    tr, at, de = metrics["train"], metrics["attack"], metrics["detect"]
    _save(F.pose_error_bars({"train": tr["train"]["bins"], "test": tr["test"]["bins"]}), "pose_errors.png")
    eps = sorted(at["eps"], key=float)
    _save(F.error_vs_eps([float(e) for e in eps], [at["eps"][e]["position_mean_m"] for e in eps],
                         [at["eps"][e]["attitude_mean_deg"] for e in eps], at["clean"]["position_mean_m"],
                         at["clean"]["attitude_mean_deg"]), "error_vs_eps.png")
    out = [("train", "Mean error per range bin, train and test", "pose_errors.png"),
           ("attack", "Pose error against eps", "error_vs_eps.png")]
    heat = _shap_means()
    if heat is not None:
        _save(F.shap_heatmaps(heat), "shap_heatmaps.png")
        out.append(("detect", "SHAP signatures: mean |phi| per output and GAP feature, normal vs adversarial",
                    "shap_heatmaps.png"))
    curves = {}
    for name in de["detectors"]:
        path = ROC_DIR / f"{name}.csv"
        if path.exists():
            roc = pd.read_csv(path)
            curves[DETECTOR_NAMES.get(name, name)] = (roc["fpr"].to_numpy(), roc["tpr"].to_numpy(),
                                                       float(de["detectors"][name]["all"]["roc_auc"]))
    if curves:
        _save(F.roc_curves(curves), "roc.png")
        out.append(("detect", "ROC curves of all detectors on the SHAP test split", "roc.png"))
    return out


def _shap_means() -> dict[str, Any] | None:
    """Mean |phi| (9, F) over normal and adversarial samples of the SHAP store, read chunk by chunk."""
    if not SHAP_STORE.exists():
        return None
    import numpy as np

    from stages.io import open_zarr

    root = open_zarr(SHAP_STORE, "SHAP store")
    values, adv = root["values"], np.asarray(root["is_adversarial"][:], dtype=bool)
    step = values.chunks[0]
    sums = {False: np.zeros(values.shape[1:]), True: np.zeros(values.shape[1:])}
    for i in range(0, values.shape[0], step):
        block, flags = np.abs(np.asarray(values[i:i + step], dtype=np.float64)), adv[i:i + step]
        for flag in (False, True):
            sums[flag] += block[flags == flag].sum(axis=0)
    counts = {flag: int((adv == flag).sum()) for flag in (False, True)}
    if not all(counts.values()):
        return None
    return {f"normal ({counts[False]})": sums[False] / counts[False],
            f"adversarial ({counts[True]})": sums[True] / counts[True]}
