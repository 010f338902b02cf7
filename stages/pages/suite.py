"""The strongest-attack suite's sections (issue 37): in reports/pose_robust.md (`rpod train --robust`: both pose
models under the suite on a sample of test frames, its checks, the split by background, the ablation rows when
measured, and each chain's attacker capacity on validation frames) and reports/suite.md (`rpod suite`: the full
suite on every test frame beside the lean one).

Inputs: per model an `attacked_table` dict (pipeline/evaluation/strongest.py: frames, eps, members, rows, sanity,
stability, full_check, backgrounds), the fitted capacity per model (pipeline/formats/capacity.py JSON content) and,
when the robust model's metrics have it, `ablation`: per variant ("clamp only", "adversarial training only") its
attacked table (no checks), best epoch and training minutes."""

from __future__ import annotations

from typing import Any

from stages.config.schema import Params

MODELS = ("standard", "robust")
ERRORS = {"position_m": "position", "attitude_deg": "attitude"}


def ci(value: float, interval: list[float], decimals: int = 2) -> str:
    """A mean with its 95% interval: "1.23 [1.01, 1.45]"."""
    return f"{value:.{decimals}f} [{interval[0]:.{decimals}f}, {interval[1]:.{decimals}f}]"


def by_background(tables: dict[str, dict[str, Any]], label: str) -> list[dict[str, Any]]:
    """Per table (`label`: its column, e.g. model or variant), background kind and row of its split by background
    (the clean row, then the suite's worst case per eps): frames and mean errors with intervals."""
    return [
        {
            label: name,
            "background": kind,
            "frames": r["n"],
            "eps": "clean" if r["attack"] == "clean" else f"{r['eps']:g}",
            "position (m)": ci(r["pos_m"], r["pos_ci"]),
            "attitude (deg)": ci(r["att_deg"], r["att_ci"]),
        }
        for name, t in tables.items()
        for kind, rs in t["backgrounds"].items()
        for r in rs
    ]


def worst_rows(tables: dict[str, Any]) -> list[dict[str, Any]]:
    """Per eps (clean first) each model's clean error or the suite's worst case, position (m) and attitude (deg);
    "not run" where a model's table stops at a smaller eps (`rpod suite --partial`)."""
    keys = sorted(
        {(r["attack"], r["eps"]) for t in tables.values() for r in t["rows"] if r["attack"] in ("clean", "suite")},
        key=lambda k: k[1],
    )
    rows = []
    for attack, eps in keys:
        got = {
            k: next((r for r in t["rows"] if r["attack"] == attack and r["eps"] == eps), None)
            for k, t in tables.items()
        }
        rows.append(
            {
                "eps": "clean" if attack == "clean" else f"{eps:g}",
                **{f"{k} position (m)": ci(r["pos_m"], r["pos_ci"]) if r else "not run" for k, r in got.items()},
                **{f"{k} attitude (deg)": ci(r["att_deg"], r["att_ci"]) if r else "not run" for k, r in got.items()},
            }
        )
    return rows


def member_rows(tables: dict[str, Any]) -> list[dict[str, Any]]:
    """Per model, eps and member that ran: its mean errors (position, attitude, range, lateral) with intervals."""
    return [
        {
            "model": k,
            "eps": f"{r['eps']:g}",
            "member": r["attack"],
            "position (m)": ci(r["pos_m"], r["pos_ci"]),
            "attitude (deg)": ci(r["att_deg"], r["att_ci"]),
            "range (m)": ci(r["range_m"], r["range_ci"]),
            "lateral (m)": ci(r["lateral_m"], r["lateral_ci"]),
        }
        for k, t in tables.items()
        for r in t["rows"]
        if r["attack"] not in ("clean", "suite")
    ]


def check_rows(tables: dict[str, Any]) -> list[dict[str, Any]]:
    """Per model, eps and error: the sanity check and the ratios of the stability and lean-vs-full checks."""

    def ratio(check: dict[str, Any] | None, eps: float, error: str) -> str:
        if check is None:
            return "not run"
        r = next(r for r in check["rows"] if r["eps"] == eps and r["error"] == error)
        return f"{r['ratio']:.3f}" + ("" if r["ok"] else " (NOT within 5%)")

    return [
        {
            "model": k,
            "eps": f"{s['eps']:g}",
            "error": ERRORS[s["error"]],
            "suite >= every member, monotone in eps": "yes" if s["ok"] else "NO",
            "strongest member": s["strongest"],
            "doubled steps and restarts / suite": ratio(t["stability"], s["eps"], s["error"]),
            "suite / full suite": ratio(t["full_check"], s["eps"], s["error"]),
        }
        for k, t in tables.items()
        for s in t["sanity"]
    ]


def lower_bounds(tables: dict[str, Any]) -> str:
    """Where the suite's figures are lower bounds: the lean-vs-full check not run, or a ratio outside 5% (of it or,
    when it ran, of the stability check)."""

    def failing(key: str) -> list[str]:
        return [
            f"{k} {ERRORS[r['error']]} at eps {r['eps']:g}"
            for k, t in tables.items()
            if t[key]
            for r in t[key]["rows"]
            if not r["ok"]
        ]

    first = tables[MODELS[0]]
    if first["full_check"] is None:
        full = (
            "**Lower bounds.** The lean-vs-full check did not run here (suite.full_frames = 0), so every worst "
            "case and member figure above is a lower bound of what the full suite (apgd and bpda on every "
            "objective, Square, more restarts: suite.full) finds on these frames, most of all above the clamp "
            "(eps > t), where one lifting start per member can miss a frame's basin. `rpod suite` "
            "(optional/dvc.yaml) runs both suites on every test frame; the paper profile runs this check on a "
            'subsample; reports/benchmarks.md ("Strongest attack suite") has an earlier lean-vs-full comparison.'
        )
    else:
        bad = failing("full_check")
        full = f"On {first['full_check']['frames']} of the frames the suite is within 5% of the full suite " + (
            f"except {', '.join(bad)}: there its figure is a lower bound of the full suite's." if bad else "everywhere."
        )
    if first["stability"] is None:
        return full
    bad = failing("stability")
    return (
        full
        + f" Doubling the steps and restarts on {first['stability']['frames']} of the frames moved the "
        + (
            f"worst case by more than 5% at {', '.join(bad)} (not converged there: a lower bound)."
            if bad
            else "worst case by less than 5% everywhere."
        )
    )


def background_section(tables: dict[str, Any]) -> str:
    """Clean errors and the suite's worst case on the frames of each background kind, or why there is no split."""
    from pipeline.report.markdown import markdown_table

    kinds = {kind for t in tables.values() for kind in t["backgrounds"]}
    if kinds == {"black"}:
        return (
            "Every attacked test frame has a black background in this profile (render.background.share = 0): "
            "there are no Earth frames to split.\n"
        )
    return markdown_table(by_background(tables, "model"))


def capacity_section(capacity: dict[str, Any], params: Params) -> str:
    """The fitted attacker capacity of each chain per eps and range bin, with how it was fitted."""
    from pipeline.report.markdown import markdown_table

    first = capacity[MODELS[0]]
    rows = [
        {
            "model": k,
            "eps": f"{e['eps']:g}",
            "range (m)": f"{lo:g}-{hi:g}",
            "frames": n,
            "along (m)": a,
            "across (m)": c,
            "attitude (deg)": d,
        }
        for k, cap in capacity.items()
        for e in cap["per_eps"]
        for lo, hi, n, a, c, d in zip(
            cap["edges"], cap["edges"][1:], e["count"], e["along_m"], e["across_m"], e["attitude_deg"]
        )
    ]
    return f"""## Attacker capacity (validation frames)

What the integrity bound consumes: on {first["meta"]["frames"]} validation frames (train.val_fraction of
the training split, the standard model's validation split: never fitted by either model; the test split is not
read), the suite above at eps {", ".join(f"{e:g}" for e in first["meta"]["eps"])} (nested) moves each frame's
estimate from its clean estimate by at most `along` along the true line of sight, `across` across it and `attitude`
in attitude. The overbound F(eps, range) per range bin is the {first["quantile"]:g} quantile of those per-frame
shifts times 1 + {first["margin"]:g} (suite.capacity.quantile, margin; a bin needs {first["meta"]["min_count"]}
frames). Per-frame values: datasets/capacity/<model>.parquet; the overbound: datasets/capacity/<model>.json.

{markdown_table(rows)}"""


def suite_section(m: dict[str, Any], params: Params) -> str:
    """reports/pose_robust.md's attacked part: both models under the suite, its checks, the background split, the
    ablation rows (when measured) and the attacker capacity."""
    from pipeline.report.markdown import markdown_table

    tables = {k: m[k]["suite"] for k in MODELS}
    s, first = params.suite, tables[MODELS[0]]
    return f"""## Under the strongest attack suite

Mean error over {first["frames"]} test frames (a seeded sample) with its 95% interval, under the strongest-attack
suite (pipeline/attacks/strongest.py): {", ".join(first["members"])}, each {s.steps} APGD steps with momentum and
the best iterate kept, {s.restarts} restart(s) from the {"/".join(s.starts)} start. `bpda` passes the gradient
through the black-level clamp as the identity (on the standard model, which has no clamp, it is plain APGD); the
lifting start puts the background just above the clamp once eps exceeds it
(t = {params.train.adversarial.black_level:g}).
Every adversarial image is stored as 8 bits before it is scored; the worst case per frame is the largest error any
member found at any eps up to the row's (nested: it cannot drop as eps grows), position and attitude each on its
own. {_cost(m)}

{markdown_table(worst_rows(tables))}
### Each member

{markdown_table(member_rows(tables))}
### Checks

{markdown_table(check_rows(tables))}
{lower_bounds(tables)}

### By background

{background_section(tables)}
{ablation_section(m, params)}{capacity_section(m["capacity"], params)}"""


def ablation_section(m: dict[str, Any], params: Params) -> str:
    """The ablation (train.adversarial.ablation): the standard model (neither), the recipe's clamp alone (no
    attacks), its attacks alone (no clamp) and the robust model (both), clean and under the suite's worst case per
    eps on the same test frames, split by background; nothing when not measured."""
    from pipeline.report.markdown import markdown_table

    if "ablation" not in m:
        return ""
    variants = {
        "neither (standard)": m["standard"]["suite"],
        **{name: v["suite"] for name, v in m["ablation"].items()},
        "both (robust)": m["robust"]["suite"],
    }
    rows = by_background(variants, "variant")
    a = params.train.adversarial
    best = ", ".join(f"{name} {v['best_epoch']}" for name, v in m["ablation"].items())
    return f"""### Ablation: the clamp alone, adversarial training alone, both

What the black-level clamp and the adversarial training each buy: the robust recipe (train.adversarial, the same
frames, train.adversarial.epochs = {a.epochs}, seed and schedule, fine-tuned from the standard model) run without its attacks ("clamp
only": the clamp at t = {a.black_level:g}, checkpoint chosen on the clean validation score) and without its clamp
("adversarial training only": t = 0), beside the standard model (neither) and the robust model (both), under the
suite above (lean, its worst case nested in eps) on the same test frames, per background. Best epochs: {best}.

{markdown_table(rows)}
"""


def _cost(m: dict[str, Any]) -> str:
    """Where the suite's cost is: the metrics, never the page (a page holds results only, so a re-run is identical)."""
    return (
        "Its cost in this run is in reports/metrics/robust.json (`suite_seconds`: wall seconds of the table and of the "
        "attacker capacity)."
        if m.get("suite_seconds")
        else ""
    )


def _partial(m: dict[str, Any]) -> str:
    """The note of a page written from the parts kept (`rpod suite --partial`), naming the parts not run."""
    if not m.get("missing"):
        return ""
    names = ", ".join(p.removesuffix(".npz") for p in m["missing"])
    return (
        f"\n**Partial run** (`rpod suite --partial`): these parts (model-suite-eps) did not run: {names}. Each "
        "model's tables stop at the largest eps both its suites reached; `rpod suite` runs the rest and keeps "
        "what is here.\n"
    )


def suite_page(m: dict[str, Any], params: Params) -> str:
    """reports/suite.md (`rpod suite`): the full suite on every test frame of both models, the lean suite beside it
    and the lean suite over the full one."""
    from pipeline.report.markdown import markdown_table

    s = params.suite
    full, lean = ({k: m["models"][k][run] for k in MODELS} for run in ("full", "lean"))
    return f"""# The full strongest-attack suite (`rpod suite`)

Both pose models on all {m["frames"]} test frames, profile `{params.profile_name}`. The full suite:
{", ".join(full["robust"]["members"])} (on the standard model, which has no clamp, a bpda member is its apgd member
and runs once); {s.full.steps} APGD steps with momentum and the best iterate kept, {s.full.restarts}
restart(s) alternating the random and the background-lifting start, Square with {s.full.queries} queries at eps
{s.full.square_eps:g}. The lean suite is the one `rpod train --robust` runs for reports/pose_robust.md:
{", ".join(lean[MODELS[0]]["members"])}; {s.steps} steps, {s.restarts} restart(s), {"/".join(s.starts)} start.
Every adversarial image is stored as 8 bits before it is scored; the worst case per frame is the largest error any
member found at any eps up to the row's (nested in eps). Means with 95% intervals. Attacks ran on
{m["device"]}; every score in exact float32.
{_partial(m)}
## Worst case: the full suite

{markdown_table(worst_rows(full))}
## Worst case: the lean suite

{markdown_table(worst_rows(lean))}
## Checks

The full suite's sanity rows, then the lean suite's with its ratio to the full suite on the same frames.

{markdown_table(check_rows(full))}
{markdown_table(check_rows(lean))}
{lower_bounds(lean)}

## Each member of the full suite

{markdown_table(member_rows(full))}
## By background (full suite)

{background_section(full)}"""
