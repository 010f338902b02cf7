"""reports/attitude.md, the page of `rpod attitude`: issue 38's attitude decomposition (the standard model beside the
pose trials' models, per split and target-attitude group, and each trial's measured contribution to the gap)."""

from __future__ import annotations

from typing import Any

from stages.pages.paper import ATTITUDE_DEG

GROUPS = {"fixed": "fixed (sequences 0-4)", "rotating": "rotating (sequences 5-12)"}


def ci(v: list[float] | tuple[float, float, float], digits: int = 2, sign: bool = False) -> str:
    """(value, lo, hi) as "v [lo, hi]"; `sign`: with a sign, as a difference."""
    f = f"{{:+.{digits}f}}" if sign else f"{{:.{digits}f}}"
    return f"{f.format(v[0])} [{f.format(v[1])}, {f.format(v[2])}]"


def _model_rows(metrics: dict[str, Any], split: str) -> list[dict[str, Any]]:
    """Per model (and the standard model on a trial's frames), overall and per group."""
    rows = []
    runs = [(name, "its own", m[split], m["size"]) for name, m in metrics["models"].items()]
    runs += [
        ("standard", f"{v}'s", c[split], metrics["models"]["standard"]["size"]) for v, c in metrics["cross"].items()
    ]
    for name, frames, s, size in runs:
        for group, g in [("all", s), *((GROUPS.get(k, k), x) for k, x in s["groups"].items())]:
            rows.append(
                {
                    "model": name,
                    "frames of": frames,
                    "input": f"{size[0]}x{size[1]}",
                    "group": group,
                    "frames": g["frames"],
                    "attitude (deg)": ci(g["attitude_deg"]),
                    "tilt (deg)": ci(g["tilt_deg"]),
                    "roll (deg)": ci(g["roll_deg"]),
                    "position (m)": ci(g["position_m"], 3),
                }
            )
    return rows


def _contribution_rows(metrics: dict[str, Any], changes: dict[str, str]) -> list[dict[str, Any]]:
    rows = []
    for v, per in metrics["contributions"].items():
        for split, c in per.items():
            rows.append(
                {
                    "trial": v,
                    "what it changes": changes.get(v, v),
                    "split": split,
                    "attitude: standard - trial (deg)": ci(c["attitude_deg"], sign=True),
                    "... the frames' part (deg)": ci(c["frames_part_deg"], sign=True)
                    if "frames_part_deg" in c
                    else "-",
                    "... the training's part (deg)": ci(c["training_part_deg"], sign=True)
                    if "training_part_deg" in c
                    else "-",
                    "position: standard - trial (m)": ci(c["position_m"], 3, sign=True),
                }
            )
    return rows


def _additivity(metrics: dict[str, Any]) -> str:
    """Whether the causes add: each combined trial against its two parts (or, without one, that this is unmeasured)."""
    inter = metrics.get("interactions", {})
    if not inter:
        return "Each was measured alone from our setting; adding them assumes they do\nnot interact, which was not measured."
    lines = []
    for v, x in inter.items():
        a, b = x["of"]
        per = "; ".join(
            f"{split}: together {ci(metrics['contributions'][v][split]['attitude_deg'], sign=True)} deg, "
            f"{a} and {b} alone add to {ci(x[split]['alone_sum_deg'], sign=True)} deg, interaction "
            f"{ci(x[split]['interaction_deg'], sign=True)} deg"
            for split in ("validation", "test")
        )
        lines.append(
            f"Whether they add ({v}: {a} and {b} at once; interaction = together - the sum alone, paired by "
            f"sequence over the four models; < 0: they overlap, > 0: together they remove more): {per}."
        )
    return "\n".join(lines)


def attitude_page(metrics: dict[str, Any], changes: dict[str, str]) -> str:
    """reports/attitude.md from reports/metrics/attitude.json's content; `changes`: each trial's change in words."""
    from pipeline.report.markdown import markdown_table

    std = metrics["models"]["standard"]
    test, val = std["test"]["attitude_deg"], std["validation"]["attitude_deg"]
    gap = test[0] - ATTITUDE_DEG
    parts = [(v, c["validation"]["attitude_deg"]) for v, c in metrics["contributions"].items()]
    measured = "; ".join(f"{v} {ci(d, sign=True)} deg" for v, d in parts) or "none"
    return f"""# Attitude: the gap to the paper decomposed

The standard model's mean test attitude error is {ci(test)} deg (validation {ci(val)} deg) against the paper's
{ATTITUDE_DEG} deg: a gap of {gap:.2f} deg. Pose trials (`rpod pose_trial VARIANT`, optional/dvc.yaml) retrain the
standard recipe (same seed, frame count, epochs) on one variant of the data set each; `rpod attitude` compares them
with the committed standard model (models/pose.pt). A trial's contribution is the standard model's mean attitude
error minus the trial model's, each on its own frames of the same split (the same frame indices; the variant's
images), paired by sequence. Brackets: 95% percentile bootstrap intervals over the 13 sequences (5 fixed, 8
rotating: coarse, as they should be). The validation split is the one the checkpoints were chosen on, the test
split a measurement only (no choice was made on it).

## Contributions

{markdown_table(_contribution_rows(metrics, changes))}
Measured on the validation split: {measured}. {_additivity(metrics)} "The frames' part": the standard model itself on the trial's frames (possible
where they have its input size); "the training's part": what training on them adds.

## Errors per split and target-attitude group

Validation:

{markdown_table(_model_rows(metrics, "validation"))}
Test (a measurement only):

{markdown_table(_model_rows(metrics, "test"))}
Metrics: reports/metrics/attitude.json (`rpod attitude`, optional/dvc.yaml).
"""
