"""Figures for the results page: plain arrays and dicts in, matplotlib Figures out (no files here).

Every function returns a `matplotlib.figure.Figure` built without pyplot's global state, so the
caller decides where to save it and nothing leaks between figures. Figures are at most WIDTH_IN wide
with text of at least 8.5 pt, so they are shown unscaled and readable in a rendered Markdown page
(about 880 pixels wide: 8 in at the 110 dpi of pipeline.io.atomic.save_figure); legends sit outside the data.
"""

from __future__ import annotations

import functools
from typing import Any, Callable, Mapping, Sequence

import matplotlib
import numpy as np
from matplotlib.figure import Figure

from pipeline.attacks.schedule import bursts
from pipeline.geometry.labels import TARGET

WIDTH_IN = 8.0  # figure width (in)
TICK_PT = 9.0  # tick label size (pt)
STYLE = {
    "font.size": 10,
    "axes.titlesize": 10,
    "axes.labelsize": 10,
    "legend.fontsize": 8.5,
    "figure.titlesize": 10.5,
    "xtick.labelsize": TICK_PT,
    "ytick.labelsize": TICK_PT,
}
LATERAL_VISIBLE_M = 0.01  # guidance figures draw the lateral offset only when a run leaves the axis by more (m)


def _readable(build: Callable[..., Figure]) -> Callable[..., Figure]:
    """Build a figure with STYLE's font sizes (tick labels are made when the figure is drawn, after
    the style is gone, so their size is set on every axes)."""

    @functools.wraps(build)
    def wrapper(*args: Any, **kwargs: Any) -> Figure:
        with matplotlib.rc_context(STYLE):
            fig = build(*args, **kwargs)
        for ax in fig.axes:
            ax.tick_params(labelsize=TICK_PT)
        return fig

    return wrapper


@_readable
def pose_error_bars(bins: Mapping[str, Sequence[Mapping[str, float]]]) -> Figure:
    """Mean position (m) and attitude (deg) error per range bin, one bar group per split.

    `bins` maps a split name ("train", "test") to rows with `range_m` (label), `pos_mean_m`,
    `att_mean_deg`, in the order the bars are drawn (far to near).
    """
    fig = Figure(figsize=(WIDTH_IN, 3.4), layout="constrained")
    axes = fig.subplots(1, 2)
    labels = sorted({str(r["range_m"]) for rows in bins.values() for r in rows}, key=_far_first)
    x = np.arange(len(labels))
    width = 0.8 / max(1, len(bins))
    for k, (split, rows) in enumerate(bins.items()):
        offset = (k - (len(bins) - 1) / 2) * width
        by_label = {str(r["range_m"]): r for r in rows}
        for ax, key in ((axes[0], "pos_mean_m"), (axes[1], "att_mean_deg")):
            # a range bin without frames (n = 0, e.g. an imported SPEED set) has no error: no bar
            ax.bar(x + offset, [by_label.get(b, {}).get(key, np.nan) for b in labels], width, label=split)
    for ax, ylabel in zip(axes, ("mean position error (m)", "mean attitude error (deg)")):
        ax.set_xticks(x, labels)
        ax.set_xlabel("range (m)")
        ax.set_ylabel(ylabel)
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(title="split")
    fig.suptitle("Pose error of the trained model per range bin")
    return fig


def _far_first(label: str) -> float:
    """Sort key for range-bin labels such as ">60", "60-45", "20-10", "<10": farthest first."""
    numbers = [float(v) for v in label.lstrip("<>").split("-") if v]
    if label.startswith(">"):
        return -np.inf
    return -(max(numbers) - (0.5 if label.startswith("<") else 0.0))


@_readable
def error_vs_eps(
    eps: Sequence[float],
    position_m: Sequence[float],
    attitude_deg: Sequence[float],
    clean_position_m: float,
    clean_attitude_deg: float,
    method: str = "fgsm",
) -> Figure:
    """Mean pose error under the attack `method` against eps (log axis), the clean error dashed."""
    fig = Figure(figsize=(WIDTH_IN, 3.4), layout="constrained")
    axes = fig.subplots(1, 2)
    order = np.argsort(eps)
    e = np.asarray(eps, dtype=float)[order]
    for ax, values, clean, ylabel in (
        (axes[0], position_m, clean_position_m, "mean position error (m)"),
        (axes[1], attitude_deg, clean_attitude_deg, "mean attitude error (deg)"),
    ):
        ax.plot(e, np.asarray(values, dtype=float)[order], "o-", label=method.upper())
        ax.axhline(clean, color="grey", linestyle="--", label="clean")
        ax.set_xscale("log")
        ax.set_xlabel("eps (L-inf, pixels in [0, 1])")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    axes[0].legend()
    fig.suptitle(f"Pose error on the test images under {method.upper()}")
    return fig


@_readable
def shap_heatmaps(mean_abs: Mapping[str, np.ndarray], outputs: Sequence[str] = tuple(TARGET)) -> Figure:
    """Mean |SHAP| per (output, GAP feature) for each group (e.g. normal, adversarial), one shared scale.

    Features are sorted by their mean |phi| over all groups and outputs, so the columns line up
    between panels and the strongest features sit on the left.
    """
    arrays = {k: np.asarray(v, dtype=float) for k, v in mean_abs.items()}
    order = np.argsort(-sum(arrays.values()).sum(axis=0))
    vmax = max(float(a.max()) for a in arrays.values()) or 1.0
    fig = Figure(figsize=(WIDTH_IN, 1.2 + 1.3 * len(arrays)), layout="constrained")
    axes = np.atleast_1d(fig.subplots(len(arrays), 1, sharex=True))
    for ax, (name, a) in zip(axes, arrays.items()):
        im = ax.imshow(a[:, order], aspect="auto", cmap="magma", vmin=0.0, vmax=vmax, interpolation="nearest")
        ax.set_yticks(range(len(outputs)), outputs)
        ax.set_title(f"{name}: mean |phi|", loc="left")
    axes[-1].set_xlabel("GAP feature (sorted by mean |phi| over all panels)")
    fig.colorbar(im, ax=list(axes), shrink=0.9, label="mean |phi|")
    return fig


@_readable
def roc_curves(curves: Mapping[str, tuple[np.ndarray, np.ndarray, float]], highlight: str | None = None) -> Figure:
    """ROC curves, name -> (fpr, tpr, auc): on linear axes, and with a log false-positive axis where
    the good detectors differ (their curves overlap in the top-left corner). `highlight` (the
    detector the page is about) is drawn last, thick and black, so no other curve hides it."""
    fig = Figure(figsize=(WIDTH_IN, 4.2), layout="constrained")
    axes = fig.subplots(1, 2)
    names = [n for n in curves if n != highlight] + ([highlight] if highlight in curves else [])
    smallest = min((float(np.min(f[f > 0])) for f, _, _ in curves.values() if np.any(f > 0)), default=1e-3)
    for ax, log in zip(axes, (False, True)):
        for j, name in enumerate(names):
            fpr, tpr, auc = curves[name]
            top = name == highlight
            ax.plot(
                fpr,
                tpr,
                color="black" if top else f"C{j}",
                lw=2.4 if top else 1.2,
                zorder=3 if top else 2,
                label=f"{name} (AUC {auc:.3f})",
            )
        chance = np.logspace(np.log10(smallest / 1.5), 0, 50)  # many points: a straight line on either axis
        ax.plot(chance, chance, color="grey", linestyle="--", linewidth=0.8, label="chance")
        ax.set_xlabel("false-positive rate" + (" (log axis)" if log else ""))
        ax.set_ylabel("true-positive rate")
        ax.set_ylim(0, 1.01)
        ax.grid(alpha=0.3)
        if log:
            ax.set_xscale("log")
            ax.set_xlim(smallest / 1.5, 1)
        else:
            ax.set_xlim(0, 1)
    axes[0].set_title("linear axes")
    axes[1].set_title("low false-positive rates")
    fig.legend(*axes[0].get_legend_handles_labels(), loc="outside lower center", ncols=2)
    fig.suptitle("ROC of the attack detectors on the SHAP test split")
    return fig


@_readable
def attack_example(
    clean: np.ndarray, adv: Mapping[float, np.ndarray], t_gt: np.ndarray, pred: Mapping[Any, np.ndarray], method: str
) -> Figure:
    """The clean uint8 image, the stored adversarial image per eps (ascending), and the perturbation of
    the smallest eps amplified to fill the grey range (mid-grey = unchanged), in rows of at most 4.

    `t_gt` is the true position (m, camera frame); `pred` maps "clean" and each eps to the 9 outputs;
    titles give the position error of each estimate (m).
    """
    eps_list = sorted(adv, key=float)
    err = {k: float(np.linalg.norm(v[:3] - t_gt)) for k, v in pred.items()}
    delta = adv[eps_list[0]].astype(np.float64) / 255 - clean.astype(np.float64) / 255
    gain = 0.5 / max(float(np.abs(delta).max()), 1e-12)
    panels = (
        [(f"original\nerror {err['clean']:.2f} m", clean)]
        + [(f"eps = {e:g}\nerror {err[e]:.1f} m", adv[e]) for e in eps_list]
        + [(f"perturbation at eps = {eps_list[0]:g}\namplified x{gain:.3g}", np.clip(0.5 + gain * delta, 0, 1))]
    )
    cols = min(4, len(panels))
    rows = -(-len(panels) // cols)
    h, w = clean.shape[:2]
    fig = Figure(figsize=(WIDTH_IN, rows * (WIDTH_IN / cols * h / w + 0.5) + 0.4), layout="constrained")
    axes = fig.subplots(rows, cols, squeeze=False).ravel()
    for ax in axes:
        ax.set_axis_off()
    for ax, (title, image) in zip(axes, panels):
        ax.imshow(image, interpolation="nearest")
        ax.set_title(title)
    fig.suptitle(
        f"{method.upper()} on one test image (target at {t_gt[2]:.1f} m): stored 8-bit attacks and the "
        f"position error of the estimate"
    )
    return fig


def _lateral(r: Any) -> np.ndarray:
    """Distance (m) of a run's true positions from the approach axis, sqrt(x^2 + y^2), per step."""
    return np.hypot(r.positions[:, 0], r.positions[:, 1])


def _estimate_error(r: Any) -> np.ndarray:
    """Position error (m) of each step's estimate against the true position it was taken at."""
    return np.linalg.norm(r.estimates - r.positions[: len(r.estimates)], axis=1)


@_readable
def guidance_trajectories(
    baseline: Any, runs: Sequence[tuple[float, int, Any]], eps: float | None, goal: Sequence[float]
) -> Figure:
    """The no-attack run and the attacked runs (S, K, RendezvousResult) of one eps, step by step: the
    true range z (m) with the goal dashed, and the error of the position estimate (m, log axis); dots
    mark attacked frames. A third panel, the distance from the approach axis (m), is drawn only when
    a run leaves it by more than LATERAL_VISIBLE_M (under the paper's dynamics it stays exactly 0)."""
    import matplotlib

    cmap = matplotlib.colormaps["viridis"]
    curves = [("no attack", baseline, "black", 2.0)] + [
        (f"S={s:g} m, K={k}: {r.outcome}", r, cmap(j / max(len(runs) - 1, 1)), 1.2) for j, (s, k, r) in enumerate(runs)
    ]
    lateral = max(float(_lateral(r).max()) for _, r, _, _ in curves) > LATERAL_VISIBLE_M
    fig = Figure(figsize=(WIDTH_IN, 5.4), layout="constrained")
    axes = fig.subplots(1, 3 if lateral else 2, sharex=True)
    for label, r, color, lw in curves:
        hit = np.flatnonzero(r.attacked)
        panels = [(r.positions[:, 2], False), (_estimate_error(r), True)] + ([(_lateral(r), False)] if lateral else [])
        for ax, (v, log) in zip(axes, panels):
            steps = np.arange(len(v))
            (ax.semilogy if log else ax.plot)(steps, v, "-", color=color, lw=lw, label=label)
            ax.plot(steps[hit], v[hit], "o", color=color, ms=3.5)
    axes[0].axhline(goal[2], color="r", ls="--", lw=1, label="target point")
    titles = ["true range", "estimate error", "distance from the axis"]
    ylabels = ["range z (m)", "position error of the estimate (m)", "sqrt(x^2 + y^2) (m)"]
    for ax, title, ylabel in zip(axes, titles, ylabels):
        ax.set_title(title)
        ax.set_xlabel("guidance step")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    if runs:  # the no-attack run may fly longer than the attacked runs are judged
        axes[0].set_xlim(-1, max(len(r.positions) for _, _, r in runs) + 1)
    fig.legend(*axes[0].get_legend_handles_labels(), loc="outside lower center", ncols=3)
    note = "" if lateral else "\nevery run stays on the approach axis (x = y = 0 m): lateral positions not drawn"
    fig.suptitle(
        "Closed-loop approach"
        + (f" under attack, eps = {eps:g}" if eps is not None else "")
        + f"; dots: attacked frames{note}"
    )
    return fig


@_readable
def detection_timeline(true_z: np.ndarray, attacked: np.ndarray, trace: Any, threshold: float, title: str) -> Figure:
    """One trajectory frame by frame: true and estimated range t_z (m), attacked frames, the detector's
    probability and flags, and the position error (m), from its `Trace` (pipeline/evaluation/sequences.py)."""
    frames = np.arange(len(attacked))
    fig = Figure(figsize=(WIDTH_IN, 7.4), layout="constrained")
    axes = fig.subplots(3, 1, sharex=True)

    def shade(ax: Any, label: bool = False) -> None:
        for k, (a, b) in enumerate(bursts(attacked)):
            ax.axvspan(
                a - 0.5,
                b - 0.5,
                color="tab:red",
                alpha=0.15,
                lw=0,
                label="attacked frames" if label and k == 0 else None,
            )

    ax = axes[0]
    shade(ax, label=True)
    ax.plot(frames, true_z, "k-", lw=1.2, label="true t_z")
    ax.plot(frames, trace.estimate_z, ".", ms=2.5, color="tab:blue", label="estimated t_z")
    ax.set_ylabel("range t_z (m)")
    ax = axes[1]
    shade(ax)
    ax.plot(frames, trace.prob, "-", lw=0.8, color="tab:purple", label="detector probability")
    ax.axhline(threshold, color="gray", ls="--", lw=0.8, label=f"threshold {threshold:.2f}")
    f = trace.flag
    ax.plot(frames[f], np.full(f.sum(), 1.05), "|", color="tab:orange", ms=6, label="flag")
    ax.set_ylim(-0.05, 1.12)
    ax.set_ylabel("P(attacked)")
    ax = axes[2]
    shade(ax)
    err = trace.position_error
    miss = attacked & ~f
    ax.semilogy(frames, np.maximum(err, 1e-3), "-", lw=0.8, color="tab:blue", label="position error")
    ax.semilogy(frames[miss], np.maximum(err[miss], 1e-3), "x", color="tab:red", ms=5, label="attacked, not flagged")
    ax.set_ylabel("position error (m)")
    ax.set_xlabel("frame")
    handles, labels = zip(*(hl for a in axes for hl in zip(*a.get_legend_handles_labels())))
    fig.legend(handles, labels, loc="outside lower center", ncols=4)
    fig.suptitle(title)
    return fig


@_readable
def guidance_variants(
    runs: Sequence[tuple[str, Any]], goal: Sequence[float], title: str, tolerance: float | None = None
) -> Figure:
    """One attacked cell flown by each variant (label, RendezvousResult): the distance from the approach
    axis (m) against the range z, and the distance to the target point (m) step by step from a few
    steps before the first attack (before it the variants fly the same path), with `tolerance` (m)
    dashed. Dots mark attacked frames, crosses the frames after a flag."""
    fig = Figure(figsize=(WIDTH_IN, 4.6), layout="constrained")
    axes = fig.subplots(1, 2)
    starts = [r.attack_start for _, r in runs if r.attack_start is not None]
    first = max(0, min(starts) - 5) if starts else 0
    for j, (label, r) in enumerate(runs):
        color = f"C{j}"
        hit = np.flatnonzero(r.attacked)
        flagged = np.array([], int) if r.flags is None else np.flatnonzero(r.flags) + 1
        steps = np.arange(len(r.positions))
        to_goal = np.linalg.norm(r.positions - np.asarray(goal, dtype=np.float64), axis=1)
        shown = steps >= first
        extra = f", {r.attacked_frames} attacked" + ("" if r.flags is None else f", {int(r.flags.sum())} flagged")
        axes[0].plot(r.positions[:, 2], _lateral(r), "-", color=color, lw=1.3, label=f"{label}: {r.outcome}{extra}")
        axes[1].plot(steps[shown], to_goal[shown], "-", color=color, lw=1.3)
        for ax, lo, h, v in ((axes[0], 0, r.positions[:, 2], _lateral(r)), (axes[1], first, steps, to_goal)):
            ax.plot(h[hit[hit >= lo]], v[hit[hit >= lo]], "o", color=color, ms=3.5)
            ax.plot(h[flagged[flagged >= lo]], v[flagged[flagged >= lo]], "x", color=color, ms=5)
    axes[0].invert_xaxis()
    if tolerance is not None:
        axes[1].axhline(tolerance, color="r", ls="--", lw=1, label=f"tolerance ({tolerance:g} m)")
    for ax, sub, xlabel, ylabel in (
        (axes[0], "distance from the axis", "range z (m)", "sqrt(x^2 + y^2) (m)"),
        (axes[1], "distance to the target point", "guidance step", "distance (m)"),
    ):
        ax.set_title(sub)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    more = axes[1].get_legend_handles_labels()
    fig.legend(handles + more[0], labels + more[1], loc="outside lower center", ncols=2)
    fig.suptitle(f"One attacked cell per variant ({title})\ndots: attacked frames, crosses: frames after a flag")
    return fig


@_readable
def robustness_vs_eps(rows: Sequence[Mapping[str, object]]) -> Figure:
    """Detection rate and harmful-undetected rate (%) against eps (log axis), one line per attack.

    `rows`: the robustness stage's attack rows (`attack`, `eps`, `detection_rate`,
    `harmful_undetected_rate`, `ci95_detection`, `ci95_harmful_undetected`); error bars are the
    95% Wilson intervals.
    """
    fig = Figure(figsize=(WIDTH_IN, 4.6), layout="constrained")
    axes = fig.subplots(1, 2, sharex=True)
    names = list(dict.fromkeys(str(r["attack"]) for r in rows))
    ticks = sorted({float(r["eps"]) for r in rows})
    for k, name in enumerate(names):
        pts = sorted((r for r in rows if r["attack"] == name), key=lambda r: float(r["eps"]))
        # attacks at the same eps are dodged sideways by a few percent so their intervals stay apart
        e = np.array([float(r["eps"]) for r in pts]) * 1.04 ** (k - (len(names) - 1) / 2)
        for ax, key, ci in (
            (axes[0], "detection_rate", "ci95_detection"),
            (axes[1], "harmful_undetected_rate", "ci95_harmful_undetected"),
        ):
            v = 100 * np.array([float(r[key]) for r in pts])
            lo = 100 * np.array([float(r[ci][0]) for r in pts])
            hi = 100 * np.array([float(r[ci][1]) for r in pts])
            ax.errorbar(e, v, yerr=[v - lo, hi - v], marker="o", capsize=2, label=name)
    for ax, ylabel in zip(axes, ("detection rate (%)", "harmful and undetected (%)")):
        ax.set_xscale("log")
        ax.set_xticks(ticks, [f"{t:g}" for t in ticks])
        ax.minorticks_off()
        ax.set_xlabel("eps (L-inf, pixels in [0, 1])")
        ax.set_ylabel(ylabel)
        ax.set_ylim(-2, 102)
        ax.grid(alpha=0.3)
    fig.legend(*axes[0].get_legend_handles_labels(), loc="outside lower center", ncols=3)
    fig.suptitle("Detection and harm per attack and eps (95% Wilson intervals)")
    return fig


@_readable
def integrity_diagram(
    points: Mapping[str, Mapping[str, np.ndarray]], series: Mapping[str, np.ndarray], alert: np.ndarray, title: str
) -> Figure:
    """Left, the Stanford diagram: per run label, the trusted estimate's error (m) against the frame's
    bound (`points[label]`: "bound", "error" (n,), "bound_is" "PL" when the chain gives a protection
    level, else "AL"); above the diagonal the error exceeds it (HMI against AL, MI against PL). Right,
    the trusted error (m) of one trajectory per label (`series[label]` (N,)) and its AL (N,) over frames."""
    fig = Figure(figsize=(WIDTH_IN, 4.4), layout="constrained")
    axes = fig.subplots(1, 2)
    names = [str(p.get("bound_is", "AL")) for p in points.values()]
    for j, (label, p) in enumerate(points.items()):
        axes[0].plot(
            np.maximum(p["bound"], 1e-2),
            np.maximum(p["error"], 1e-2),
            ".",
            ms=2.5,
            alpha=0.5,
            color=f"C{j}",
            label=label,
        )
    every = np.concatenate([np.concatenate([p["bound"], p["error"]]) for p in points.values()] + [np.ones(1)])
    lo, top = max(1e-2, 0.5 * float(np.nanmin(every))), 2 * float(np.nanmax(every))
    line = np.array([lo, top])
    axes[0].plot(line, line, "k-", lw=1)
    axes[0].fill_between(line, line, top, color="r", alpha=0.07, label=f"error > {names[0]}")
    axes[0].set(xlim=(lo, top), ylim=(lo, top))
    axes[0].set(
        xscale="log",
        yscale="log",
        xlabel=f"{names[0]} (m)",
        ylabel="trusted error (m)",
        title=f"error against {names[0]}, counted frames",
    )
    for j, err in enumerate(series.values()):
        axes[1].plot(np.arange(len(err)), err, "-", lw=1.1, color=f"C{j}")
    axes[1].plot(np.arange(len(alert)), alert, "k--", lw=1, label="AL")
    axes[1].set(yscale="log", xlabel="frame", ylabel="trusted error (m)", title="one trajectory")
    for ax in axes:
        ax.grid(alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    more = axes[1].get_legend_handles_labels()
    fig.legend(handles + more[0], labels + more[1], loc="outside lower center", ncols=3, markerscale=3)
    fig.suptitle(title)
    return fig
