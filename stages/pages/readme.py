"""The summary block of reports/README.md (and of README.md, `rpod report --sync-readme`): this run's
headline results beside the paper's, each row naming the pose model it ran on: the standard model (the paper's
reproduction) or the robust one (the chain that ships)."""

from __future__ import annotations

from typing import Any

from pipeline.guidance.law import DOCKED
from pipeline.stats import percent_of
from stages.pages.paper import ATTITUDE_DEG, DETECTOR_ACCURACY, INTEGRATED, INTEGRATED_EPS, LAB, LAB_EPS, POSITION_M

PAPER_LABEL = " (the paper's reproduction: prediction = truth by construction, no integrity evidence)"

DETECTOR_NAMES = {
    "lstm": "LSTM on SHAP (paper)",
    "mlp": "MLP on SHAP",
    "mahalanobis": "Mahalanobis (GAP)",
    "lid": "LID (GAP)",
    "squeeze": "feature squeezing",
}


def _fmt(x: float | None, decimals: int = 2) -> str:
    return "-" if x is None else f"{x:.{decimals}f}"


def _with_ci(m: dict[str, Any], key: str) -> str:
    """A rate of a metrics dict in percent with its 95% interval (`key_ci95`), e.g. "94.58 [92.40, 96.10]"."""
    from pipeline.stats import percent_ci

    return percent_ci(m[key], m.get(f"{key}_ci95"), 2)


def _eps_keys(d: dict[str, Any]) -> list[str]:
    """eps keys of a per-eps dict, largest first (the paper's column order)."""
    return sorted(d, key=float, reverse=True)


def _sd(spread: dict[str, Any] | None, key: str | None, note: str = "") -> str:
    """The seed spread of one headline number from reports/variance.json: "0.022 (3 seeds)", or "-"."""
    numbers = (spread or {}).get("numbers", {})
    got = numbers.get(key or "")
    if not got or not isinstance(got.get("sd"), (int, float)):
        return "-"
    unit = "runs" if len(set((spread or {}).get("isas") or [])) > 1 else "seeds"
    return f"{got['sd']:.{3 if abs(got['sd']) < 0.1 else 2}f}{note} ({got['runs']} {unit})"


def summary_tables(metrics: dict[str, dict[str, Any]], spread: dict[str, Any] | None = None) -> str:
    """The headline results against the paper, as Markdown (this is what README.md shows), led by the targets
    (`headline`). `spread` (reports/variance.json of the same profile) adds the standard deviation over seeds of
    each number."""
    from pipeline.report.markdown import markdown_table

    ev, gd = metrics["evaluate"], metrics["guidance"]
    rows = [
        *_paper_rows(metrics, spread),
        *_robustness_rows(metrics["robustness"], spread),
        *_integrity_rows(metrics["robustness"], gd, spread),
    ]
    columns = ("result", "this run", "paper", "stage", "sd over seeds")
    table = markdown_table(
        [dict(zip(columns, (r, v, p, f"`{s}`", sd) if spread else (r, v, p, f"`{s}`"))) for r, v, p, s, sd in rows]
    )
    per_eps = (
        "Detection accuracy per eps (correct flags over all frames; 95% intervals by a bootstrap over the "
        "trajectories):"
    )
    return (
        f"{headline(metrics)}{_lead(metrics, spread)}\n\n{table}\n{per_eps}\n\n{markdown_table(_per_eps_rows(ev, metrics['lab']))}"
        + defended_table(ev, gd, spread)
    )


def _paper_rows(
    metrics: dict[str, dict[str, Any]], spread: dict[str, Any] | None
) -> list[tuple[str, str, str, str, str]]:
    """The rows beside the paper's numbers: pose, attacks, the paper's closed loop (`_detection_rows`: detectors,
    integrated and lab detection) as (result, this run, paper, stage, sd over seeds)."""
    from pipeline.stats import wilson

    tr, at, gd = (metrics[k] for k in ("train", "attack", "guidance"))
    eps_at = _eps_keys(at["eps"])
    runs = [r for r in gd["runs"] if r.get("attacked_frames", 1) > 0]
    broken = sum(r["outcome"] != DOCKED for r in runs)
    return [
        (
            "pose, test mean position error (m), standard model",
            _fmt(tr["test"]["pos_mean_m"]),
            _fmt(POSITION_M),
            "train",
            _sd(spread, "pose.standard_position_m"),
        ),
        (
            "pose, test mean attitude error (deg), standard model",
            _fmt(tr["test"]["att_mean_deg"]),
            _fmt(ATTITUDE_DEG),
            "train",
            _sd(spread, "pose.standard_attitude_deg"),
        ),
        *_robust_rows(metrics.get("robust"), spread),
        (
            "FGSM mean position error (m) at eps " + " / ".join(eps_at) + ", standard model",
            " / ".join(_fmt(at["eps"][e]["position_mean_m"], 1) for e in eps_at),
            "-",
            "attack",
            _sd(spread, "fgsm_position_m_0.05", " at eps 0.05"),
        ),
        (
            "closed loop, no attack, standard model",
            f"{gd['baseline']['outcome']} (miss {_fmt(gd['baseline']['miss_m'])} m)",
            "reaches the target",
            "guidance",
            "-",
        ),
        (
            "closed loop, attacked runs that did not dock (undefended, standard model)",
            f"{broken} of {len(runs)} ({wilson(broken, len(runs)).pct()} %)",
            "-",
            "guidance",
            _sd(spread, "undefended_not_docked_pct", " %"),
        ),
        *_detection_rows(metrics, spread),
    ]


def _detection_rows(
    metrics: dict[str, dict[str, Any]], spread: dict[str, Any] | None
) -> list[tuple[str, str, str, str, str]]:
    """The detector rows beside the paper's: the paper's LSTM, the shipped one, the best baseline, integrated and
    lab detection."""
    de, ev, lab = (metrics[k] for k in ("detect", "evaluate", "lab"))
    dets = de["detectors"]
    best_base = max((k for k in dets if k != "lstm"), key=lambda k: dets[k]["all"]["accuracy"])
    return [
        (
            "(paper's view) LSTM detector accuracy, SHAP test split (%), standard model",
            _with_ci(dets["lstm"]["all"], "accuracy"),
            _fmt(100 * DETECTOR_ACCURACY),
            "detect",
            _sd(spread, "detector.standard_accuracy_pct"),
        ),
        *_shipped_detector_rows(metrics.get("detect_robust"), lab, spread),
        (
            f"best baseline detector accuracy (%), standard model: {DETECTOR_NAMES.get(best_base, best_base)}",
            _with_ci(dets[best_base]["all"], "accuracy"),
            "-",
            "detect",
            "-",
        ),
        (
            "(paper's view) integrated per-frame detection accuracy, mean over eps (%; per eps below), standard model",
            _fmt(100 * ev["accuracy_mean"]),
            _fmt(INTEGRATED),
            "evaluate",
            _sd(spread, "integrated.standard_accuracy_pct"),
        ),
        (
            "(paper's view) lab detection accuracy, mean over eps (%): synthetic lab-like render, "
            + ("same mesh, reused standard models" if lab.get("reused_models", True) else "retrained models"),
            _fmt(100 * lab["accuracy_mean"]),
            _fmt(LAB),
            "lab",
            _sd(spread, "lab.standard_accuracy_pct"),
        ),
    ]


def _per_eps_rows(ev: dict[str, Any], lab: dict[str, Any]) -> list[dict[str, str]]:
    """Detection accuracy per eps, integrated and lab, beside the paper's."""
    eps_rows = []
    for e in sorted(set(ev["per_eps"]) | set(lab["per_eps"]), key=float, reverse=True):
        get = lambda m, k: _with_ci(m["per_eps"][e], "accuracy") if e in m["per_eps"] else "-"  # noqa: E731, B023
        eps_rows.append(
            {
                "eps": e,
                "integrated (%)": get(ev, e),
                "paper, integrated (%)": _fmt(INTEGRATED_EPS.get(e)),
                "lab, 10-frame attacks (%)": get(lab, e),
                "paper, lab (%)": _fmt(LAB_EPS.get(e)),
            }
        )
    return eps_rows


def _lead(metrics: dict[str, dict[str, Any]], spread: dict[str, Any] | None) -> str:
    """The sentence above the table: the profile, the paper's scale, and what the sd column is."""
    profiles = sorted({m.get("profile", "unknown") for m in metrics.values()})
    head = (
        f"Profile `{'`, `'.join(profiles)}`. Paper: 480x270 images, full-width network, "
        "50 epochs, 32,500 images; each stage's section of the results page says what differs and why."
    )
    if spread:
        isas = sorted(set(spread.get("isas") or []))
        seeds = ", ".join(sorted(set(spread["seeds"]), key=str))
        what = (
            f"differ only in `seed` ({seeds}) and in torch's CPU kernels ({', '.join(isas)})"
            if len(isas) > 1
            else "differ only in `seed`"
        )
        counts = sorted({n["runs"] for n in spread["numbers"].values()}) or [len(spread["seeds"])]
        runs = f"{counts[0]}" if len(counts) == 1 else f"{counts[0]} to {counts[-1]}"
        head += (
            f" The last column is the standard deviation of the number over the {runs} runs that {what} "
            "(each cell says how many; reports/variance.md); a difference smaller than about twice it is noise."
        )
    return head


def _robust_rows(rb: dict[str, Any] | None, spread: dict[str, Any] | None) -> list[tuple[str, str, str, str, str]]:
    """The robust model's rows (reports/metrics/robust.json): clean test errors, and the strongest-attack suite's
    worst-case position and attitude errors of both models at eps 0.01 and 0.05 (none when the metrics are
    missing)."""
    if not rb:
        return []
    t = rb["robust"]["test"]

    def worst(model: str, key: str) -> str:
        got = {f"{a['eps']:g}": a[key] for a in rb[model]["suite"]["rows"] if a["attack"] == "suite"}
        return " / ".join(_fmt(got.get(e), 2 if key == "pos_m" else 1) for e in ("0.01", "0.05"))

    return [
        (
            "pose, test mean position error (m), robust model (ships)",
            _fmt(t["pos_mean_m"]),
            "-",
            "robust",
            _sd(spread, "pose.shipped_position_m"),
        ),
        (
            "pose, test mean attitude error (deg), robust model (ships)",
            _fmt(t["att_mean_deg"]),
            "-",
            "robust",
            _sd(spread, "pose.shipped_attitude_deg"),
        ),
        *(
            (
                f"attack-suite worst-case mean {what} at eps 0.01 / 0.05: robust model (ships) vs standard",
                f"{worst('robust', key)} vs {worst('standard', key)}",
                "-",
                "robust",
                "-",
            )
            for what, key in (("position error (m)", "pos_m"), ("attitude error (deg)", "att_deg"))
        ),
    ]


def _shipped_detector_rows(
    dr: dict[str, Any] | None, lab: dict[str, Any], spread: dict[str, Any] | None
) -> list[tuple[str, str, str, str, str]]:
    """The shipped chain's detector (robust model): its SHAP test accuracy, and the chain's clean false alarms on the
    lab-like frames at its calibrated threshold (rows left out when not measured)."""
    from pipeline.stats import percent_ci

    out = []
    if dr:
        out.append(
            (
                "shipped chain's LSTM detector accuracy, SHAP test split (%), robust model",
                _with_ci(dr["detectors"]["lstm"]["all"], "accuracy"),
                "-",
                "detect_robust",
                _sd(spread, "detector.shipped_accuracy_pct"),
            )
        )
    s = lab.get("shipped")
    if s:
        out.append(
            (
                "shipped chain (robust model): detector false alarms on clean lab-like frames (%)",
                f"{percent_ci(s['rate'], s['rate_ci95'], 2)} ({s['false_alarms']}/{s['frames']})",
                "-",
                "lab",
                _sd(spread, "lab.shipped_clean_false_alarm_pct"),
            )
        )
    return out


def judge(value: float | None, target: str) -> str:
    """Whether `value` meets a target written ">= 99.5" or "<= 1" (same unit): "met", "**missed**", or "not shown"
    when there is no value. The point estimate is judged; its interval stands beside it."""
    if value is None or value != value:
        return "not shown"
    op, bound = target.split()
    return "met" if (value >= float(bound) if op == ">=" else value <= float(bound)) else "**missed**"


def _pct_value(r: dict[str, Any] | None) -> float | None:
    """A metrics rate ({"value", "n", ...}) in percent, None where it has no samples."""
    return None if not r or not r.get("n") or r["value"] is None else 100 * r["value"]


# The detection and closed-loop targets of the defended chain (`defended_table` rows; key in fused per_eps)
DETECTION_TARGETS = {"accuracy": ">= 99.5", "harmful_flagged": ">= 99.5", "harmful_undetected": "<= 1", "fpr": "<= 0.5"}
CLEAN_ALARMS_TARGET, DOCKED_TARGET = "<= 0.5", ">= 95"


def _docked_counts(variants: dict[str, Any], variant: str, key: str = "docked") -> tuple[int, int] | None:
    """(docked, attacked runs that met the attack) of one closed-loop variant (`key` "denied": (runs the attack
    kept from docking, met)), None where it was not flown or does not record them."""
    if variant not in variants or key not in variants[variant]:
        return None
    k, n = (sum(v[i] for v in variants[variant][key].values()) for i in (0, 1))
    return k, n


def _not_denied_pct(variants: dict[str, Any]) -> float | None:
    """Detect-and-recover's attacked runs that the attack did not keep from docking (%): what the rendezvous
    target judges."""
    denied = _docked_counts(variants, "recover", "denied")
    return None if not denied or not denied[1] else 100 * (denied[1] - denied[0]) / denied[1]


def _grid_outcomes(closed_loop: dict[str, Any] | None, dyn: str) -> str:
    """How detect-and-recover's attacked grid runs of `dyn` that met the attack ended by the docking measure
    (pipeline/evaluation/measures.py: docked, held, timed out, failed), "" without the closed-loop table."""
    from pipeline.evaluation.measures import HELD, TIMED_OUT

    runs = [
        r
        for r in (closed_loop or {}).get("runs", [])
        if r["dynamics"] == dyn and r["defense"] == "recover" and r["attack"].startswith("grid") and r["met"]
    ]
    if not runs:
        return ""
    held, timed_out = (sum(r["outcome"] == o for r in runs) for o in (HELD, TIMED_OUT))
    failed = sum(r["failed"] for r in runs)
    return f"; by the docking measure {held} held, {timed_out} timed out, {failed} failed the mission"


def shipped_targets(metrics: dict[str, dict[str, Any]]) -> list[tuple[str, str, str]]:
    """Every target the shipped chain is held to, judged on this run: the integrity targets (open loop), the docking
    targets (closed loop), and the detection and rendezvous targets of the defended chain -> (target, verdict,
    evidence), in that order; a stage that did not run adds none."""
    from pipeline.stats import wilson
    from stages.pages.guidance import docking_targets
    from stages.pages.integrity import targets

    out: list[tuple[str, str, str]] = []
    integrity = metrics.get("robustness", {}).get("integrity")
    if integrity and "chains" in integrity:
        out += targets(integrity)
    gd = metrics.get("guidance", {})
    if "closed_loop" in gd:
        out += docking_targets(gd["closed_loop"])
    fused = metrics.get("evaluate", {}).get("fused")
    if fused and fused["per_eps"]:
        e = min(fused["per_eps"], key=float)
        ours = fused["per_eps"][e]
        names = {
            "accuracy": "integrated accuracy",
            "harmful_flagged": "harmful frames flagged",
            "harmful_undetected": "harmful and undetected",
            "fpr": "false alarms between attacks",
        }
        for key, target in DETECTION_TARGETS.items():
            out.append(
                (
                    f"{names[key]} at eps {e} {target}%",
                    judge(_pct_value(ours[key]), target),
                    f"{percent_of(ours[key], 2)}%",
                )
            )
        clean = ours["fpr_clean"]
        out.append(
            (
                f"false alarms on attack-free runs {CLEAN_ALARMS_TARGET}%",
                judge(_pct_value(clean), CLEAN_ALARMS_TARGET),
                f"{percent_of(clean, 2)}%",
            )
        )
    for dyn, variants in gd.get("defended", {}).get("dynamics", {}).items():
        counts, denied = _docked_counts(variants, "recover"), _docked_counts(variants, "recover", "denied")
        if counts is not None and denied is not None:
            out.append(
                (
                    f"closed loop, {dyn} dynamics{PAPER_LABEL if dyn == 'paper' else ''}: attacked runs the attack "
                    "did not keep from docking, "
                    f"detect-and-recover {DOCKED_TARGET}%",
                    judge(_not_denied_pct(variants), DOCKED_TARGET),
                    f"{denied[0]} of {denied[1]} kept from docking by the attack, {wilson(*denied).pct()}% "
                    f"({counts[0]} docked{_grid_outcomes(gd.get('closed_loop'), dyn)})",
                )
            )
    return out


def headline(metrics: dict[str, dict[str, Any]]) -> str:
    """The results' lead: what holds and what does not (each target of `shipped_targets`, met or missed), what the
    safety numbers rest on, and the targets table."""
    from pipeline.report.markdown import markdown_table

    verdicts = shipped_targets(metrics)
    if not verdicts:
        return ""
    met = [t for t, v, _ in verdicts if v == "met"]
    missed = [t for t, v, _ in verdicts if v == "**missed**"]
    text = f"**{len(met)} of {len(verdicts)} targets met** (the table below gives the evidence). Met: "
    text += ("; ".join(met) or "none") + ". **Missed**: " + ("; ".join(missed) or "nothing") + "."
    chains = metrics.get("robustness", {}).get("integrity", {}).get("chains", {})
    if "robust" in chains:
        text += (
            f" The open-loop safety numbers come from {chains['robust']['trajectories']} evaluation trajectories per "
            "chain: a worst HMI of 0 with a 95% interval up to tens of percent says no attacker we built broke the "
            "chain there, not that none can; the breaking points, and the controls that do break, are the evidence "
            "that can fail."
        )
    table = markdown_table([{"target (shipped chain)": t, "verdict": v, "this run": e} for t, v, e in verdicts])
    return f"{text}\n\n{table}\n\n"


def defended_table(ev: dict[str, Any], gd: dict[str, Any], spread: dict[str, Any] | None = None) -> str:
    """The defended chain beside the paper's detector: integrated detection at the smallest
    eps, harmful-undetected, false alarms, and closed-loop runs docked per variant (Markdown)."""
    from pipeline.report.markdown import markdown_table

    fused = ev.get("fused")
    if not fused or not fused["per_eps"]:
        return ""
    e = "0.01" if "0.01" in fused["per_eps"] else min(fused["per_eps"], key=float)
    paper, ours = fused["paper_per_eps"][e], fused["per_eps"][e]
    rows = _defended_rows(fused, e)
    sd_column = {"sd over seeds, defended": None} if spread else {}
    standard = fused.get("standard_per_eps", {}).get(e)
    ours_col, std_col = (
        f"defended chain ({fused['fusion']}), robust model (ships)",
        f"defended ({fused['fusion']}), standard model",
    )
    table = [
        {
            "result": name,
            "paper's detector, standard model (this run)": percent_of(paper[key], 2),
            std_col: percent_of(standard[key], 2) if standard else "-",
            ours_col: percent_of(ours[key], 2),
            "paper": p,
            "target": t if t == "-" else f"{t} ({judge(_pct_value(ours[key]), t)})",
            **{c: _sd(spread, sd) for c in sd_column},
        }
        for name, key, p, t, sd in rows
    ]
    for dyn, variants in gd.get("defended", {}).get("dynamics", {}).items():
        table.append(_docked_row(dyn, variants, ours_col, std_col, spread))
    return (
        "\n\nThe defended chains (motion check fused with the detector, recovery and hold) beside the "
        "paper's detector, on the same trajectories and attack schedule, each on its own model's frames (FGSM "
        "crafted on that model; 95% intervals); the per-frame rows are the paper's view (the raw estimate of each "
        "frame against a fixed threshold), the closed-loop rows count only the runs that met the attack; each "
        "target is judged on the shipped chain's point estimate:\n\n" + markdown_table(table)
    )


def _defended_rows(fused: dict[str, Any], e: str) -> list[tuple[str, str, str, str, str | None]]:
    """`defended_table`'s per-frame rows at eps `e`: (result, key in the fused per-eps rates, paper, target, the
    headline key of its sd over seeds)."""
    return [
        (
            f"integrated accuracy at eps {e} (%)",
            "accuracy",
            _fmt(INTEGRATED_EPS.get(e)),
            DETECTION_TARGETS["accuracy"],
            "defended.shipped_accuracy_min_eps_pct" if e == min(fused["per_eps"], key=float) else None,
        ),  # its key
        (f"attacked frames flagged at eps {e} (TPR, %)", "tpr", "-", "-", None),
        (
            f"harmful frames (error > {fused['harm_m']:g} m) flagged at eps {e} (%)",
            "harmful_flagged",
            "-",
            DETECTION_TARGETS["harmful_flagged"],
            None,
        ),
        (
            f"harmful and undetected, of the attacked frames at eps {e} (%)",
            "harmful_undetected",
            "-",
            DETECTION_TARGETS["harmful_undetected"],
            None,
        ),
        (f"false alarms on clean frames between attacks at eps {e} (%)", "fpr", "-", DETECTION_TARGETS["fpr"], None),
        (
            "false alarms on attack-free runs (%)",
            "fpr_clean",
            "-",
            CLEAN_ALARMS_TARGET,
            "defended.shipped_clean_false_alarm_pct",
        ),
    ]


def _docked_row(
    dyn: str, variants: dict[str, Any], ours_col: str, std_col: str, spread: dict[str, Any] | None
) -> dict[str, str]:
    """`defended_table`'s closed-loop row of one dynamics: attacked runs docked per variant, the runs the attack
    kept from docking with detect-and-recover, and its target (judged on the runs the attack did not keep from
    docking)."""
    from pipeline.stats import wilson

    def docked(variant: str) -> str:
        counts = _docked_counts(variants, variant)
        return "-" if counts is None else f"{wilson(*counts).pct()} ({counts[0]}/{counts[1]})"

    denied = _docked_counts(variants, "recover", "denied")
    return {
        "result": f"closed loop, attacked runs docked (%), {dyn} dynamics, detect-and-recover (robust "
        f"model: undefended {docked('undefended')}, detect-and-hold {docked('hold')}); the target counts the "
        "runs the attack did not keep from docking (a safe abort counts as kept)",
        "paper's detector, standard model (this run)": "-",
        std_col: "-",
        ours_col: docked("recover")
        + (
            ""
            if denied is None
            else f"; kept from docking by the attack {wilson(*denied).pct()} ({denied[0]}/{denied[1]})"
        ),
        "paper": "-",
        "target": f"{DOCKED_TARGET} ({judge(_not_denied_pct(variants), DOCKED_TARGET)})",
        **(
            {"sd over seeds, defended": _sd(spread, "recover_docked_pct" if dyn == "paper" else None, " %")}
            if spread
            else {}
        ),
    }


def _robustness_rows(m: dict[str, Any], spread: dict[str, Any] | None) -> list[tuple[str, str, str, str, str]]:
    """Summary rows at eps 0.05 and 0.01: the worst harmful-undetected rate against the chain that ships
    (the fused chain, adaptive attack over bursts), and beside it against the paper's detector alone
    (LSTM, any robustness attack incl. adaptive); percent with the 95% interval, "-" where not run."""
    from pipeline.stats import percent_ci

    out = []
    for key, what, short in (
        ("worst_harmful_undetected_fused", "fused chain (ships, robust model), nested burst attack", "fused"),
        (
            "worst_harmful_undetected",
            "the shipped chain's LSTM detector alone (robust model), any attack incl. adaptive",
            "lstm",
        ),
    ):
        for e in ("0.05", "0.01"):
            w = m.get(key, {}).get(e)
            value = "-"
            if w is not None:
                value = f"{percent_ci(w['harmful_undetected_rate'], w['ci95_harmful_undetected'])} ({w['attack']})"
            out.append(
                (
                    f"(paper's view, per frame) worst harmful-undetected rate (%) at eps {e}, {what}",
                    value,
                    "-",
                    "robustness",
                    _sd(spread, f"{short}_hu_{e}_pct"),
                )
            )
    return out


def _integrity_rows(
    rb: dict[str, Any], gd: dict[str, Any], spread: dict[str, Any] | None
) -> list[tuple[str, str, str, str, str]]:
    """The integrity headline rows, the evidence that can fail first: the breaking point per chain (shipped, standard,
    undefended robust control), the shipped chain's largest error / AL at eps 0.05, its docking miss in the closed
    loop (detect-and-recover, true-state dynamics) without attack and at eps 0.05; then the worst HMI a chain-level
    attack caused on the shipped chain (descriptive) and on the standard one, availability without attack, and the
    in-loop attacker's collisions per variant on the shipped chain ("-" where not run) and on the standard chain."""
    integrity = rb.get("integrity", {})
    return [
        *_breaking_rows(integrity, spread),
        *_docking_rows(gd, spread),
        *_hmi_rows(integrity, spread),
        _in_loop_row(gd, spread),
        *_standard_in_loop_rows(gd),
    ]


def _breaking_rows(integrity: dict[str, Any], spread: dict[str, Any] | None) -> list[tuple[str, str, str, str, str]]:
    """The breaking point per chain and the shipped chain's largest error / AL at eps 0.05."""
    chains, out = integrity.get("chains", {}), []
    names = {
        "robust": "shipped chain (robust model)",
        "standard": "standard model's chain",
        "control": "undefended robust control",
    }
    for key, what in names.items():
        b = integrity.get("breaking_eps", {}).get(key)
        value = "-" if key not in chains else ("none in the grid" if b is None else f"{b:g}")
        out.append(
            (
                f"integrity: breaking eps (smallest eps at which an attacker fails a trajectory: error / AL > 1 on "
                f"an available frame), {what}",
                value,
                "-",
                "robustness",
                _sd(spread, f"integrity.{'shipped' if key == 'robust' else key}_breaking_eps"),
            )
        )
    at = chains.get("robust", {}).get("summary", {}).get("per_eps", {}).get("0.05")
    out.append(
        (
            "integrity: largest trusted error / AL at eps 0.05, worst over attackers and trajectories, shipped "
            "chain (robust model)",
            "-" if at is None or at["max_error_al"] is None else _fmt(at["max_error_al"]),
            "-",
            "robustness",
            _sd(spread, "integrity.shipped_error_al_0_05_ratio"),
        )
    )
    return out


def _docking_rows(gd: dict[str, Any], spread: dict[str, Any] | None) -> list[tuple[str, str, str, str, str]]:
    """The shipped chain's docking miss in the closed loop (detect-and-recover, true-state dynamics), without
    attack and the largest at eps 0.05."""
    out = []
    recover = gd.get("closed_loop", {}).get("variants", {}).get("true_state", {}).get("recover")  # "-": not flown
    worst = None if recover is None else recover["per_eps"].get("0.05")
    where = "shipped chain (detect-and-recover, true-state dynamics, execution error)"
    out.append(
        (
            f"closed loop: docking miss (m) without attack, {where}",
            "-" if recover is None else f"{_fmt(recover['clean']['miss'])} ({recover['clean']['outcome']})",
            "-",
            "guidance",
            _sd(spread, "closed_loop.recover_docking_miss_m"),
        )
    )
    out.append(
        (
            f"closed loop: largest docking miss (m) of the attacked runs at eps 0.05, {where}",
            "-" if worst is None else _fmt(worst["largest_miss_m"]),
            "-",
            "guidance",
            _sd(spread, "closed_loop.recover_miss_0_05_m"),
        )
    )
    return out


def _hmi_trajectories(chain: dict[str, Any], e: str) -> str:
    """ "; k of n trajectories: rate [CI]%": a chain's trajectories with an HMI frame at eps `e`, worst over its
    attackers (its safety summary's Clopper-Pearson count); "" where the chain did not fly `e`."""
    r = chain.get("summary", {}).get("per_eps", {}).get(e, {}).get("hmi_trajectories")
    if r is None or not r.get("n"):
        return ""
    return f"; {round(r['value'] * r['n'])} of {r['n']} trajectories: {percent_of(r, 1)}%"


def _hmi_rows(integrity: dict[str, Any], spread: dict[str, Any] | None) -> list[tuple[str, str, str, str, str]]:
    """The worst HMI a chain-level attack caused on the shipped and the standard chain, and the shipped chain's
    availability without attack."""
    from stages.pages.integrity import attacker_names

    chains, out = integrity.get("chains", {}), []
    for e in ("0.01", "0.05"):
        w = integrity.get("worst_hmi", {}).get(e)
        value = (
            "-"
            if w is None
            else f"{percent_of(w['hmi'], 2)} ({attacker_names(w['attacker'])})"
            + _hmi_trajectories(chains.get("robust", {}), e)
        )
        out.append(
            (
                f"integrity: worst HMI (%) a chain-level attack caused at eps {e} (trusted error > AL, "
                f"available), shipped chain (robust model; {chains.get('robust', {}).get('trajectories', '-')} "
                "trajectories: the interval's upper end is all this run rules out); of the frames, then the "
                "trajectories with an HMI frame (Clopper-Pearson)",
                value,
                "-",
                "robustness",
                _sd(spread, f"integrity.shipped_hmi_eps_{e.replace('.', '_')}_pct"),
            )
        )
    std = chains.get("standard", {})
    for e in ("0.01", "0.05"):  # "-" where the standard chain was not flown (as the breaking points above)
        w = std.get("worst_hmi", {}).get(e)
        out.append(
            (
                f"integrity: worst HMI (%) at eps {e}, standard model's chain ({std.get('trajectories', '-')} "
                "trajectories: the interval's upper end is all this run rules out); of the frames, then the "
                "trajectories with an HMI frame (Clopper-Pearson)",
                "-" if w is None else percent_of(w["hmi"], 2) + _hmi_trajectories(std, e),
                "-",
                "robustness",
                _sd(spread, f"integrity.standard_hmi_eps_{e.replace('.', '_')}_pct"),
            )
        )
    clean = integrity.get("clean")
    out.append(
        (
            "integrity: availability of the trusted estimate without attack (%), shipped chain (robust model)",
            "-" if clean is None else percent_of(clean["availability"], 2),
            "-",
            "robustness",
            _sd(spread, "integrity.shipped_clean_availability_pct"),
        )
    )
    return out


def _in_loop_eps(gd: dict[str, Any]) -> str:
    return " and ".join(sorted({f"{r['eps']:g}" for r in gd.get("in_loop", {}).get("runs", [])}))


def _standard_in_loop_rows(gd: dict[str, Any]) -> list[tuple[str, str, str, str, str]]:
    """The in-loop attacker's collisions and docking misses on the standard chain per variant flown (none: no row)."""
    from pipeline.stats import wilson

    counts, rows = gd.get("in_loop", {}).get("counts", {}), []
    for variant in ("standard hold", "standard recover"):
        c = [v for d in counts.values() for v in d.get(variant, {}).values()]
        if not c:
            continue
        col, lost, n = (sum(x[i] for x in c) for i in (0, 1, 3))
        rows.append(
            (
                f"closed loop, in-loop attacker at eps {_in_loop_eps(gd)}: collisions / not docked without a collision "
                f"of attacked runs (%), standard chain (standard model, its detector and defense), "
                f"{variant.split()[1].replace('hold', 'detect-and-hold').replace('recover', 'detect-and-recover')}",
                f"{wilson(col, n).pct()} ({col}/{n}) / {wilson(lost, n).pct()} ({lost}/{n})",
                "-",
                "guidance",
                "-",
            )
        )
    return rows


def _in_loop_row(gd: dict[str, Any], spread: dict[str, Any] | None) -> tuple[str, str, str, str, str]:
    """The in-loop attacker's collisions per variant on the shipped chain."""
    from pipeline.stats import wilson

    counts = gd.get("in_loop", {}).get("counts", {})
    cells = []
    for variant in ("undefended", "hold", "recover"):
        c = [v for d in counts.values() for v in d.get(variant, {}).values()]
        k, n = sum(x[0] for x in c), sum(x[3] for x in c)
        cells.append("-" if not c else f"{wilson(k, n).pct()} ({k}/{n})")
    return (
        f"closed loop, in-loop attacker at eps {_in_loop_eps(gd)}"
        + ": collisions of attacked runs (%), shipped chain (robust "
        "model), undefended / detect-and-hold / detect-and-recover",
        " / ".join(cells),
        "-",
        "guidance",
        _sd(spread, "in_loop.shipped_recover_collisions_pct"),
    )
