"""reports/lab.md, the page of `rpod lab`: which models, the range rescaling, pose errors,
FGSM errors and integrated detection on the lab sequences, beside the paper's numbers."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from stages.artifacts.paths import LAB as OUT
from stages.artifacts.paths import TRAIN_METRICS
from stages.config.evaluation import DomainShift, Lab
from stages.config.schema import Params
from stages.pages.evaluate import rates_section
from stages.pages.paper import LAB, LAB_ATTACK_LENGTH, LAB_EPS, LAB_RANGES, by_eps, frames_note

if TYPE_CHECKING:
    from pipeline.evaluation.sequences import Sequence


def models_section(p: Params, m: dict[str, Any]) -> str:
    """The report's paragraph on which pose model and detector were used, and why."""
    lab, r = p.lab, p.render
    if m["reused_models"]:
        return f"""## Models: reused

The pose model and the detector of the tables below (the paper's reproduction) are the main standard ones,
`{m["models"]["pose"]}` (hash `{m["model_hash"]}`) and `{m["models"]["detector"]}` (`lab.retrain: {lab.retrain}`); the
chain that ships has its own section at the end: the lab mock-up is the main target mesh at
1/{lab.scale:g} scale and K_blender has the lab images' 16:9 aspect, so a synthetic-lab training set
would repeat the main one. `lab.retrain: always` (the paper profile), or another mock-up mesh in `lab.mesh`,
trains a synthetic-lab pose model and detector instead.
"""
    s = m["synthetic_lab"]
    t = s["train_test"]
    mesh = "(the procedural Jason-1-like target)" if s["mesh"] is None else f"`{s['mesh']}`"
    return f"""## Models: retrained on a synthetic-lab set

Retrained because {s["reason"]}. The pose model and the detector used below are
`{s["pose"]}` (hash `{m["model_hash"]}`) and `{s["detector"]}`, not the main models/pose.pt and
models/detector.pt.

- Synthetic-lab set: {s["images"]} images at {s["size"][0]}x{s["size"][1]} with the main camera K_blender (the lab
  images' 16:9 aspect), the 13 approach sequences ({s["frames_per_sequence"]} frames each, 60 to 10 m,
  base seed {s["seed"]}), the mock-up {mesh} rendered at {lab.scale:g} x its size ({s["mesh_scale"]:g} m per mesh
  unit) so the ranges are preserved; sun and render settings of `render`.
- Pose model: the main recipe (`rpod train` with the `train` params, width {p.train.width}, input
  {r.width}x{r.height}): {s["epochs_run"]} epochs, best epoch {s["best_epoch"]}; synthetic-lab test split
  ({t["n"]} images): {t["pos_mean_m"]:.3f} m and {t["att_mean_deg"]:.2f} deg mean error.
- SHAP (`rpod shap`, `shap` params) of {s["shap_samples"]} clean and FGSM samples with this model, and the LSTM
  detector (`rpod detect`, `detect` params, no baselines) trained on them: test accuracy
  {100 * s["detector_test_accuracy"]:.2f}%.

Everything is in `{s["folder"]}/` (its own params.yaml, datasets/, models/, reports/pose.md, reports/detector.md);
the time of each step is in reports/metrics/lab.json (`synthetic_lab.seconds`).
"""


def paper_ranges(K_syn: Any, K_zed: Any, scale: float, factor: float) -> str:
    """The paper's representative-range table beside ours, and why they differ (Markdown)."""
    from pipeline.evaluation.lab import paper_lab_factor
    from pipeline.report.markdown import markdown_table

    k_paper = paper_lab_factor(K_syn, K_zed, scale)
    z_ref, printed = next(iter(LAB_RANGES.items()))
    rows = [
        {
            "lab z (m)": f"{z:g}",
            "ours (m)": z * factor,
            "paper's equation as printed (m)": z / k_paper,
            "its reciprocal (m)": z * k_paper,
            "paper, as printed (m)": LAB_RANGES.get(z, "-"),
        }
        for z in (3.122, 3.0, 2.5, 2.0, 1.5, 1.0)
    ]
    return f"""Representative ranges beside the paper's. The paper takes the 1920 -> 480 resize as
cx_zed / cx_blender = {K_zed.cx:g} / {K_syn.cx:g} = {K_zed.cx / K_syn.cx:.4f} instead of the exact
{K_zed.width}/{K_syn.width} = {K_zed.width / K_syn.width:g}, so its factor is {k_paper:.3f} against our {factor:.3f} and
its synthetic ranges are {100 * (factor / k_paper - 1):.2f}% shorter. Its rescaling equation as printed divides
the lab range by that factor: applied to {z_ref:g} m it gives {z_ref / k_paper:.2f} m; only its reciprocal,
z_syn = {k_paper:.3f} x z_lab, gives {z_ref * k_paper:.2f} m, the printed {printed:g} m up to rounding. The paper's table
prints all three ranges; the one quoted here (stages/pages/paper.py) is the {z_ref:g} m row, and the other rows
apply the reciprocal of its equation.

{markdown_table(rows, decimals=2)}"""


def _loader_note(m: dict[str, Any], lab: Lab) -> str:
    """The loader round trip's largest label errors (mm, deg), or "" when it was not measured."""
    if not m["loader_error"]:
        return ""
    worst_p = max(v["position_max_m"] for v in m["loader_error"].values())
    worst_a = max(v["attitude_max_deg"] for v in m["loader_error"].values())
    return (
        f"\nLoader round trip: the labels recovered from mocap.csv/camera.csv ({lab.match} matching, "
        f"max gap {lab.max_gap_s} s) differ from the exact render poses by at most "
        f"{1000 * worst_p:.2f} mm (lab units) and {worst_a:.4f} deg.\n"
    )


def _error_tables(m: dict[str, Any]) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Rows of the clean pose errors per sequence and of the mean errors, clean then per FGSM eps."""
    import pandas as pd

    clean = pd.DataFrame(m["clean"])
    clean_table = [
        {
            "sequence": c["sequence"],
            "position (m)": c["position_m"],
            "relative position": c["relative_position"],
            "attitude (deg)": c["attitude_deg"],
        }
        for c in m["clean"]
    ]
    fg = pd.DataFrame(m["fgsm"])
    fgsm_table = [
        {
            "eps": "clean",
            "position (m)": float(clean["position_m"].mean()),
            "relative position": float(clean["relative_position"].mean()),
            "attitude (deg)": float(clean["attitude_deg"].mean()),
        }
    ]
    for eps, g in fg.groupby("eps", sort=False):
        fgsm_table.append(
            {
                "eps": f"{eps:g}",
                "position (m)": float(g["position_m"].mean()),
                "relative position": float(g["relative_position"].mean()),
                "attitude (deg)": float(g["attitude_deg"].mean()),
            }
        )
    return clean_table, fgsm_table


def _synthetic_note(m: dict[str, Any], train_metrics: dict[str, Any] | None) -> str:
    """The synthetic test error of the pose model used, for comparison."""
    synth = "not available (run `rpod train`)"
    test = (train_metrics or {}).get("test", {})
    if "pos_mean_m" in test and "att_mean_deg" in test:
        synth = f"{test['pos_mean_m']:.3f} m and {test['att_mean_deg']:.2f} deg mean error"
    which = (
        f"the main model, `{TRAIN_METRICS}`"
        if m["reused_models"]
        else f"the synthetic-lab model, `{m['synthetic_lab']['folder']}/{TRAIN_METRICS}`"
    )
    return f"Synthetic test split ({which}): {synth}."


def lab_page(
    p: Params,
    m: dict[str, Any],
    rows: list[dict[str, Any]],
    summary: list[dict[str, Any]],
    names: list[str],
    train_metrics: dict[str, Any] | None,
    K_syn: Any,
    K_zed: Any,
    sequences: list[Sequence],
) -> str:
    """reports/lab.md: models, range rescaling, loader round trip, pose and FGSM errors, integrated detection."""
    lab, ds = p.lab, p.lab.domain_shift
    f_eff = K_zed.fx * K_syn.width / K_zed.width
    src = (
        f"synthetic lab sequences rendered by this stage and read back through the real-data loader (`{OUT}/`)"
        if m["synthetic"]
        else f"the real lab recording in `{m['source']}`"
    )
    clean_table, fgsm_table = _error_tables(m)
    att_frac = np.mean([s.attacked.mean() for s in sequences])
    mean_acc = 100 * m["accuracy_mean"]
    return (
        _rescaling_text(p, m, lab, src, K_syn, K_zed, f_eff)
        + _errors_text(p, m, lab, ds, train_metrics, clean_table, fgsm_table)
        + _detection_text(p, m, rows, summary, names, att_frac, mean_acc)
    )


def _rescaling_text(p: Params, m: dict[str, Any], lab: Lab, src: str, K_syn: Any, K_zed: Any, f_eff: float) -> str:
    """The page's title, source and models, the range rescaling (lab to synthetic metres, `f_eff` in px) beside the
    paper's, and the loader round trip."""
    from pipeline.report.markdown import markdown_table

    return f"""# Lab domain

Source: {src}.

{models_section(p, m)}

## Range rescaling

Apparent size s = f L / z (pixels). The lab image ({K_zed.width}x{K_zed.height}, fx = {K_zed.fx:g}) resized to
{K_syn.width}x{K_syn.height} has fx_lab_eff = {K_zed.fx:g} x {K_syn.width}/{K_zed.width} = {f_eff:.2f} px; the
mock-up is L/{lab.scale:g}; the synthetic camera has fx = {K_syn.fx:g} px. Equal size gives
z_syn = z_lab x {lab.scale:g} x {K_syn.fx:g} / {f_eff:.2f} = **{m["factor"]:.3f} x z_lab**
(`rpod lab rescale --z 3.122` -> {3.122 * m["factor"]:.2f} m). Lateral label coordinates keep the target's
pixel position. The match is on the horizontal size; K_blender has fy/fx = {K_syn.fy / K_syn.fx:.4g}
(camera.fy), so the target is {K_syn.fy / K_syn.fx:.3f}x as tall in the synthetic image as in the resized lab image.

{paper_ranges(K_syn, K_zed, float(lab.scale), m["factor"])}

{markdown_table(m["ranges"], decimals=2)}
{_loader_note(m, lab)}
"""


def _errors_text(
    p: Params,
    m: dict[str, Any],
    lab: Lab,
    ds: DomainShift,
    train_metrics: dict[str, Any] | None,
    clean_table: list[dict[str, Any]],
    fgsm_table: list[dict[str, Any]],
) -> str:
    """The page's sections on the lab frames' pose errors (m, deg), clean per sequence and under FGSM per eps;
    `ds` is the lab's domain shift (`lab.domain_shift`)."""
    from pipeline.report.markdown import markdown_table

    return f"""## Pose error

Lab frames: {lab.frames} per sequence at {lab.fps} fps, mocap at {lab.mocap_hz} Hz, rendered with the
ZED geometry (fx scaled by 1 + {ds.calib_error:g}: a calibration error), sun direction {ds.sun_direction}
at strength {ds.sun_strength}, blur sigma {ds.blur_sigma} px, noise std {ds.noise_std}, then
segmented (masks/) and resized to {p.render.width}x{p.render.height}. Errors are in the equivalent
synthetic frame (metres x {m["factor"]:.2f} of lab metres).

{_synthetic_note(m, train_metrics)}

{markdown_table(clean_table, decimals=3)}
## FGSM on the lab sequences

Mean error over all lab frames (attack.eps, loss `{p.attack.loss}`, 8-bit images).

{markdown_table(fgsm_table, decimals=3)}
"""


def _detection_text(
    p: Params,
    m: dict[str, Any],
    rows: list[dict[str, Any]],
    summary: list[dict[str, Any]],
    names: list[str],
    att_frac: float,
    mean_acc: float,
) -> str:
    """The page's sections on integrated detection (accuracy in %, `att_frac` the attacked fraction of the frames)
    and on the chain that ships."""
    from pipeline.evaluation.sequences import accuracy_table, detail_table
    from pipeline.report.markdown import markdown_table

    return f"""## Integrated detection, {m["attack_length"]}-frame attacks

Start probability {p.evaluate.p_start:g} per frame, {100 * att_frac:.1f}% of the frames attacked;
accuracy = correctly classified frames / all frames (%).

{markdown_table(accuracy_table(rows, summary, names, by_eps(LAB_EPS)), decimals=2)}
Mean over eps: **{mean_acc:.2f}%** (paper: {LAB}% average). {frames_note()}

{markdown_table(detail_table(summary), decimals=2)}
{rates_section(rows, LAB_ATTACK_LENGTH, by_eps(LAB_EPS), "sequences")}
{shipped_section(m["shipped"])}"""


def shipped_section(s: dict[str, Any]) -> str:
    """The chain that ships (robust model) on the clean lab frames: false alarms, pose error, the clamp."""
    from pipeline.stats import percent_ci

    per = ", ".join(f"{k}: {v}" for k, v in s["per_sequence"].items())
    erased = "-" if s["clamp_erased"] is None else f"{100 * s['clamp_erased']:.2f}%"
    return f"""
## The chain that ships, clean lab frames

Every table above is the paper's reproduction (the standard model, or the synthetic-lab one). The chain that
ships is the robust model (`models/pose_robust.pt`, hash `{s["model_hash"]}`) behind its black-level clamp
(t = {s["black_level"]:g}: channel values below it go to 0) with its own detector at the threshold `rpod calibrate`
chose on clean validation trajectories ({s["threshold"]:.4f}, models/defense.json). On the same lab frames without
any attack it flags **{s["false_alarms"]} of {s["frames"]} frames, {percent_ci(s["rate"], s["rate_ci95"], 2)}%** (Wilson
interval over frames, optimistic: frames of a sequence are correlated; per sequence: {per}); the detector's
probability on these frames has median {s["probability_median"]:.3f} and maximum {s["probability_max"]:.4f}, against the
threshold {s["threshold"]:.4f} (a count of 0 with a wide margin is a result; at a narrow one it is luck). Its mean pose error
is {s["position_m"]:.3f} m and {s["attitude_deg"]:.2f} deg. The clamp erases {erased} of these frames' non-zero
channel values (the loader's segmentation sets the background to 0 before resizing, so these are the target's
dark pixels and its edges blended by the resize). The motion filter needs the chaser's commanded motion, which the lab recordings do not carry, so this is
the detector's share of the false alarms only.
"""
