"""reports/README.md, the page of `rpod report`: its title and summary head, and each stage report as
a section, stamped with the profile it ran on, with the report's own figures at its end."""

from __future__ import annotations

from typing import Any

from stages.artifacts.paths import (
    ATTACK_METRICS,
    ATTACK_REPORT,
    DATASET_CARD,
    DETECT_METRICS,
    DETECT_REPORT,
    DETECT_ROBUST_METRICS,
    DETECT_ROBUST_REPORT,
    EVALUATE_METRICS,
    EVALUATE_REPORT,
    GUIDANCE_METRICS,
    GUIDANCE_REPORT,
    LAB_METRICS,
    LAB_REPORT,
    POSE_REPORT,
    REPORTS,
    ROBUST_METRICS,
    ROBUST_REPORT,
    ROBUSTNESS_METRICS,
    ROBUSTNESS_REPORT,
    TRAIN_METRICS,
)
from stages.config.schema import Params

# (command, report, metrics or None) in pipeline order (stages/artifacts/paths.py); benchmarks.md is the committed
# page that benchmarks/*.py write, read in the working folder like the others.
SECTIONS = [
    ("label", DATASET_CARD, None),
    ("train", POSE_REPORT, TRAIN_METRICS),
    ("train --robust", ROBUST_REPORT, ROBUST_METRICS),
    ("attack", ATTACK_REPORT, ATTACK_METRICS),
    ("guidance", GUIDANCE_REPORT, GUIDANCE_METRICS),
    ("detect", DETECT_REPORT, DETECT_METRICS),
    ("detect --model robust", DETECT_ROBUST_REPORT, DETECT_ROBUST_METRICS),
    ("evaluate", EVALUATE_REPORT, EVALUATE_METRICS),
    ("robustness", ROBUSTNESS_REPORT, ROBUSTNESS_METRICS),
    ("lab", LAB_REPORT, LAB_METRICS),
    ("benchmarks", REPORTS / "benchmarks.md", None),
]


def page_head(metrics: dict[str, dict[str, Any]], params: Params) -> str:
    """Title, where the page comes from, warnings on mixed profiles or pose models, and the summary heading."""
    profiles = {m.get("profile", "unknown") for m in metrics.values()}
    warn = ""
    if len(profiles) > 1:
        warn = (
            f"\n> **Mixed profiles** ({', '.join(sorted(profiles))}): some stages are stale; run `dvc repro` "
            "to bring them all to the current params.yaml.\n"
        )
    for model in ("standard", "robust"):  # the stages' metrics name their pose model (`model`; standard if none)
        hashes = {
            k: m["model_hash"]
            for k, m in metrics.items()
            if "model_hash" in m
            and m.get("model", "standard") == model
            and not (k == "lab" and m.get("reused_models") is False)
        }
        if len(set(hashes.values())) > 1:
            warn += (
                f"\n> **Mixed {model} pose models** ({', '.join(f'{k} {v}' for k, v in sorted(hashes.items()))}): "
                "some stages ran on an older checkpoint.\n"
            )
    return (
        f"# rpodguard results\n\nWritten by `rpod report` from `reports/metrics/*.json` and the stage reports "
        f"beside this file; params profile `{params.profile_name}`. Regenerate with "
        f"`dvc repro`. Every section below is one stage's report, stamped with the profile it ran on (when it ran: `produced` in reports/metrics/<stage>.json)."
        f"\n{warn}\n## Summary against the paper\n"
    )


def section(stage: str, report: str, m: dict[str, Any] | None, body: str, figures: list[tuple[str, str]]) -> str:
    """One stage report (`body`, headings already one level down) under its title with the stamp
    (`m`: its metrics, None for a report without), then its `figures` ((title, file name))."""
    stamp = (
        f"_`rpod {stage}`, profile `{m.get('profile', 'unknown')}`; source [{report}]({report})._"
        if m is not None
        else f"_Source [{report}]({report})._"
    )
    first, _, rest = body.partition("\n")
    out = f"\n{first}\n\n{stamp}\n{rest}\n"
    if figures:
        out += "\n### Figures\n\n" + "\n\n".join(f"{title}:\n\n![{title}](figures/{name})" for title, name in figures)
        out += "\n"
    return out
