"""The text of `rpod calibrate` (stages/calibrate.py): its one-line refusals and summary, and the banner the
reports that use a defense calibrated with unmet shares (defense.allow_unmet) open with."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

SETTING = {
    "detector": "threshold {:.4g}",
    "attitude gate": "attitude noise inflation x{:g}",
    "gate": "position noise inflation x{:g}",
    "sequential test": "CUSUM threshold h = {:g}",
    "protection level": "correlated share of the measurement variance {:g}",
}


def unmet_line(
    check: Any, frames: int, reached: float | None = None, target: float | None = None, tightened: int = 0
) -> str:
    """One line: `check` (a pipeline.defense.calibration.CheckResult; None: the fused chain, which
    `reached` a rate above `target` after its shares were tightened `tightened` times) could not meet its
    share on `frames` clean validation frames."""
    if check is None:
        return (
            f"calibrate: the fused chain flags {100 * reached:.3f}% of {frames} clean validation frames, above "
            f"defense.target_false_alarm {100 * target:g}%, although each check met its share (tightened "
            f"{tightened} times); set defense.allow_unmet: true to continue anyway"
        )
    best = min(check.rates.values())
    if check.share == 0.0:  # the protection level's coverage (pipeline/defense/calibration.py)
        return (
            f"calibrate: the {check.check} cannot cover the clean validation errors: on {frames} clean validation "
            f"frames {100 * best:.3f}% of those with a PL have a larger error at best "
            f"({SETTING[check.check].format(check.setting)}); set defense.allow_unmet: true to continue anyway"
        )
    return (
        f"calibrate: the {check.check} cannot meet its share {100 * check.share:.3f}% of "
        f"defense.target_false_alarm on {frames} clean validation frames: it flags {100 * best:.3f}% at best "
        f"({SETTING[check.check].format(check.setting)}); set defense.allow_unmet: true to continue anyway"
    )


def summary_line(cal: dict[str, Any], path: Path) -> str:
    """What `rpod calibrate` prints when it is done."""
    v = cal["validation"]
    fa = v["false_alarms"]
    unmet = f"; UNMET (defense.allow_unmet): {len(cal['unmet'])} check(s)" if cal["unmet"] else ""
    if "tightened" in cal:
        unmet += f"; shares tightened x{cal['tightened']['shares_scale']:.3g} (the fused chain overshot at x1)"
    return (
        f"calibrate: {v['frames']} clean validation frames; detector threshold {cal['threshold']:.4g}, noise x"
        f"{cal['inflation']:g} (attitude x{cal['attitude_inflation']:g}), CUSUM h {cal['cusum_threshold']:g}; false alarms detector {fa['detector']['pct']:.3f}%, "
        f"gate {fa['gate']['pct']:.3f}%, sequential {fa['sequential']['pct']:.3f}%, fused {fa['fused']['pct']:.3f}% "
        f"(detector on {v['envelope']['frames']} envelope frames {v['envelope']['detector_pct']:.3f}%) "
        f"(target {v['target_pct']:g}%); availability {v['availability']['pct']:.2f}%, PL correlated share "
        f"{cal['settings'].get('correlated_error', 0.0):g} (error > PL on {v['mi']['pct']:.3f}%){unmet} -> {path}"
    )


def unmet_banner(unmet: Sequence[str], model: Any = None) -> str:
    """The first line of a report that uses a defense: empty when every check met its share (its defense file's
    `unmet` lines), else a warning naming what was not met (then a blank line); `model`
    (stages.artifacts.paths.Model) names a defense other than the shipped chain's."""
    if not unmet:
        return ""
    which = "the defense" if model is None else f"the {model.value} model's defense"
    return (
        f"> **Warning: {which} was calibrated with unmet false-alarm shares (defense.allow_unmet)**: "
        + " | ".join(line.removeprefix("calibrate: ").split("; set defense.allow_unmet")[0] for line in unmet)
        + "\n\n"
    )
