"""Figures for the results page: plain arrays and dicts in, matplotlib Figures out (no files here).

Every function returns a `matplotlib.figure.Figure` built without pyplot's global state, so the
caller decides where to save it and nothing leaks between figures.
"""
from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np
from matplotlib.figure import Figure

from pipeline.schedule import bursts

OUTPUT_NAMES = ("tx", "ty", "tz", "r0", "r1", "r2", "r3", "r4", "r5")


def pose_error_bars(bins: Mapping[str, Sequence[Mapping[str, float]]]) -> Figure:
    """Mean position (m) and attitude (deg) error per range bin, one bar group per split.

    `bins` maps a split name ("train", "test") to rows with `range_m` (label), `pos_mean_m`,
    `att_mean_deg`, in the order the bars are drawn (far to near).
    """
    fig = Figure(figsize=(9, 3.4), layout="constrained")
    axes = fig.subplots(1, 2)
    labels = sorted({str(r["range_m"]) for rows in bins.values() for r in rows}, key=_far_first)
    x = np.arange(len(labels))
    width = 0.8 / max(1, len(bins))
    for k, (split, rows) in enumerate(bins.items()):
        offset = (k - (len(bins) - 1) / 2) * width
        by_label = {str(r["range_m"]): r for r in rows}
        for ax, key in ((axes[0], "pos_mean_m"), (axes[1], "att_mean_deg")):
            ax.bar(x + offset, [by_label[b][key] if b in by_label else np.nan for b in labels], width, label=split)
    for ax, ylabel in zip(axes, ("mean position error (m)", "mean attitude error (deg)")):
        ax.set_xticks(x, labels)
        ax.set_xlabel("range (m)")
        ax.set_ylabel(ylabel)
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend()
    return fig


def _far_first(label: str) -> float:
    """Sort key for range-bin labels such as ">60", "60-45", "20-10", "<10": farthest first."""
    numbers = [float(v) for v in label.lstrip("<>").split("-") if v]
    if label.startswith(">"):
        return -np.inf
    return -(max(numbers) - (0.5 if label.startswith("<") else 0.0))


def error_vs_eps(eps: Sequence[float], position_m: Sequence[float], attitude_deg: Sequence[float],
                 clean_position_m: float, clean_attitude_deg: float) -> Figure:
    """Mean pose error under attack against eps (log axis), with the clean error as a dashed line."""
    fig = Figure(figsize=(9, 3.4), layout="constrained")
    axes = fig.subplots(1, 2)
    order = np.argsort(eps)
    e = np.asarray(eps, dtype=float)[order]
    for ax, values, clean, ylabel in ((axes[0], position_m, clean_position_m, "mean position error (m)"),
                                      (axes[1], attitude_deg, clean_attitude_deg, "mean attitude error (deg)")):
        ax.plot(e, np.asarray(values, dtype=float)[order], "o-", label="FGSM")
        ax.axhline(clean, color="grey", linestyle="--", label="clean")
        ax.set_xscale("log")
        ax.set_xlabel("eps (L-inf, pixels in [0, 1])")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    axes[0].legend()
    return fig


def shap_heatmaps(mean_abs: Mapping[str, np.ndarray], outputs: Sequence[str] = OUTPUT_NAMES) -> Figure:
    """Mean |SHAP| per (output, GAP feature) for each group (e.g. normal, adversarial), one shared scale.

    Features are sorted by their mean |phi| over all groups and outputs, so the columns line up
    between panels and the strongest features sit on the left.
    """
    arrays = {k: np.asarray(v, dtype=float) for k, v in mean_abs.items()}
    order = np.argsort(-sum(arrays.values()).sum(axis=0))
    vmax = max(float(a.max()) for a in arrays.values()) or 1.0
    fig = Figure(figsize=(10, 1.2 + 1.3 * len(arrays)), layout="constrained")
    axes = np.atleast_1d(fig.subplots(len(arrays), 1, sharex=True))
    for ax, (name, a) in zip(axes, arrays.items()):
        im = ax.imshow(a[:, order], aspect="auto", cmap="magma", vmin=0.0, vmax=vmax, interpolation="nearest")
        ax.set_yticks(range(len(outputs)), outputs)
        ax.set_title(f"{name}: mean |phi|", fontsize=10, loc="left")
    axes[-1].set_xlabel("GAP feature (sorted by mean |phi| over all panels)")
    fig.colorbar(im, ax=list(axes), shrink=0.9, label="mean |phi|")
    return fig


def roc_curves(curves: Mapping[str, tuple[np.ndarray, np.ndarray, float]]) -> Figure:
    """ROC curves: name -> (fpr, tpr, auc); the chance diagonal dashed."""
    fig = Figure(figsize=(4.8, 4.4), layout="constrained")
    ax = fig.subplots()
    for name, (fpr, tpr, auc) in curves.items():
        ax.plot(fpr, tpr, label=f"{name} (AUC {auc:.3f})")
    ax.plot([0, 1], [0, 1], color="grey", linestyle="--", linewidth=0.8)
    ax.set_xlabel("false-positive rate")
    ax.set_ylabel("true-positive rate")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1.01)
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
    return fig


def attack_example(clean: np.ndarray, adv: Mapping[float, np.ndarray], t_gt: np.ndarray,
                   pred: Mapping[Any, np.ndarray], method: str) -> Figure:
    """Per eps: the clean uint8 image, the stored perturbation scaled to fill [0, 1], the adversarial image.

    `t_gt` is the true position (m, camera frame); `pred` maps "clean" and each eps to the 9 outputs.
    """
    eps_list = list(adv)
    fig = Figure(figsize=(9, 1.9 * len(eps_list) + 0.4))
    axes = fig.subplots(len(eps_list), 3, squeeze=False)
    c = clean.astype(np.float64) / 255
    err = {k: float(np.linalg.norm(v[:3] - t_gt)) for k, v in pred.items()}
    for row, e in zip(axes, eps_list):
        a = adv[e].astype(np.float64) / 255
        delta = a - c
        scale = max(float(np.abs(delta).max()), 1e-12)
        row[0].imshow(clean)
        row[0].set_title(f"original (pos. error {err['clean']:.2f} m)", fontsize=8)
        row[1].imshow(np.clip(0.5 + 0.5 * delta / scale, 0, 1))
        row[1].set_title(f"perturbation eps={e:g} (shown x{0.5 / scale:.2g})", fontsize=8)
        row[2].imshow(adv[e])
        row[2].set_title(f"adversarial (pos. error {err[e]:.2f} m)", fontsize=8)
        for ax in row:
            ax.set_axis_off()
    fig.suptitle(f"{method.upper()} example, target at range {t_gt[2]:.1f} m", fontsize=9)
    fig.tight_layout()
    return fig


def guidance_trajectories(baseline: Any, runs: Sequence[tuple[float, int, Any]], eps: float | None,
                          goal: Sequence[float]) -> Figure:
    """True trajectories (m) of the no-attack run and of the runs (S, K, RendezvousResult) of one eps:
    lateral x and y against z, and z against the step; dots mark attacked frames."""
    import matplotlib

    fig = Figure(figsize=(15, 4.2))
    axes = fig.subplots(1, 3)
    cmap = matplotlib.colormaps["viridis"]
    curves = [("no attack", baseline, "black", 2.0)] + [
        (f"S={s:g} m, K={k}: {r.outcome}", r, cmap(j / max(len(runs) - 1, 1)), 1.0) for j, (s, k, r) in enumerate(runs)]
    for label, r, color, lw in curves:
        hit = np.flatnonzero(r.attacked)
        for ax, (h, v) in zip(axes, ((r.positions[:, 2], r.positions[:, 0]), (r.positions[:, 2], r.positions[:, 1]),
                                     (np.arange(len(r.positions)), r.positions[:, 2]))):
            ax.plot(h, v, "-", color=color, lw=lw, label=label)
            ax.plot(h[hit], v[hit], "o", color=color, ms=3)
    for ax, (h, v) in zip(axes, ((goal[2], goal[0]), (goal[2], goal[1]))):
        ax.plot(h, v, "r*", ms=12, label="target point")
        ax.invert_xaxis()
        ax.set_xlabel("z (m, along the approach)")
    axes[2].axhline(goal[2], color="r", ls="--", lw=1)
    axes[2].set_xlabel("step")
    for ax, title, ylabel in zip(axes, ("z vs x", "z vs y", "z vs step"), ("x (m)", "y (m)", "z (m)")):
        ax.set_title(title)
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    axes[1].legend(fontsize=7, loc="best")
    fig.suptitle("True position of the target relative to the chaser" + (f", eps = {eps:g}" if eps is not None else "")
                 + " (dots: attacked frames)", fontsize=10)
    fig.tight_layout()
    return fig


def detection_timeline(true_z: np.ndarray, attacked: np.ndarray, trace: Mapping[str, np.ndarray], threshold: float,
                       title: str) -> Figure:
    """One trajectory frame by frame: true and estimated range t_z (m), attacked frames, the detector's
    probability and flags, and the position error (m); `trace` holds estimate_z, prob, flag, position_error."""
    frames = np.arange(len(attacked))
    fig = Figure(figsize=(9, 7))
    axes = fig.subplots(3, 1, sharex=True)

    def shade(ax: Any, label: bool = False) -> None:
        for k, (a, b) in enumerate(bursts(attacked)):
            ax.axvspan(a - 0.5, b - 0.5, color="tab:red", alpha=0.15, lw=0,
                       label="attacked frames" if label and k == 0 else None)

    ax = axes[0]
    shade(ax, label=True)
    ax.plot(frames, true_z, "k-", lw=1.2, label="true t_z")
    ax.plot(frames, trace["estimate_z"], ".", ms=2.5, color="tab:blue", label="estimated t_z")
    ax.set_ylabel("range t_z (m)")
    ax.legend(loc="upper right", fontsize=8)
    ax = axes[1]
    shade(ax)
    ax.plot(frames, trace["prob"], "-", lw=0.8, color="tab:purple", label="detector probability")
    ax.axhline(threshold, color="gray", ls="--", lw=0.8, label=f"threshold {threshold:.2f}")
    f = trace["flag"]
    ax.plot(frames[f], np.full(f.sum(), 1.05), "|", color="tab:orange", ms=6, label="flag")
    ax.set_ylim(-0.05, 1.12)
    ax.set_ylabel("P(attacked)")
    ax.legend(loc="lower right", fontsize=8)
    ax = axes[2]
    shade(ax)
    err = trace["position_error"]
    miss = attacked & ~f
    ax.semilogy(frames, np.maximum(err, 1e-3), "-", lw=0.8, color="tab:blue", label="position error")
    ax.semilogy(frames[miss], np.maximum(err[miss], 1e-3), "x", color="tab:red", ms=5, label="attacked, not flagged")
    ax.set_ylabel("error (m)")
    ax.set_xlabel("frame")
    ax.legend(loc="upper right", fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig


def guidance_variants(runs: Sequence[tuple[str, Any]], goal: Sequence[float], title: str) -> Figure:
    """True trajectories (m) of one attacked cell flown by each variant (label, RendezvousResult):
    lateral x against z and z against the step; dots mark attacked frames, crosses flagged ones."""
    fig = Figure(figsize=(11, 4.2))
    axes = fig.subplots(1, 2)
    for j, (label, r) in enumerate(runs):
        color = f"C{j}"
        hit = np.flatnonzero(r.attacked)
        flagged = np.array([], int) if r.flags is None else np.flatnonzero(r.flags)
        for ax, (h, v) in zip(axes, ((r.positions[:, 2], r.positions[:, 0]),
                                     (np.arange(len(r.positions)), r.positions[:, 2]))):
            ax.plot(h, v, "-", color=color, lw=1.2, label=f"{label}: {r.outcome}")
            ax.plot(h[hit], v[hit], "o", color=color, ms=3)
            ax.plot(h[flagged + 1], v[flagged + 1], "x", color=color, ms=5)
    axes[0].plot(goal[2], goal[0], "r*", ms=12, label="target point")
    axes[0].invert_xaxis()
    axes[1].axhline(goal[2], color="r", ls="--", lw=1)
    for ax, xlabel, ylabel in zip(axes, ("z (m, along the approach)", "step"), ("x (m)", "z (m)")):
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, loc="best")
    fig.suptitle(f"One attacked run per variant ({title}); dots: attacked frames, crosses: flagged", fontsize=10)
    fig.tight_layout()
    return fig


def robustness_vs_eps(rows: Sequence[Mapping[str, object]]) -> Figure:
    """Detection rate and harmful-undetected rate (%) against eps (log axis), one line per attack.

    `rows`: the robustness stage's attack rows (`attack`, `eps`, `detection_rate`,
    `harmful_undetected_rate`, `ci95_detection`, `ci95_harmful_undetected`); error bars are the
    95% Wilson intervals.
    """
    fig = Figure(figsize=(10, 3.8), layout="constrained")
    axes = fig.subplots(1, 2, sharex=True)
    names = list(dict.fromkeys(str(r["attack"]) for r in rows))
    ticks = sorted({float(r["eps"]) for r in rows})
    for k, name in enumerate(names):
        pts = sorted((r for r in rows if r["attack"] == name), key=lambda r: float(r["eps"]))
        # attacks at the same eps are dodged sideways by a few percent so their intervals stay apart
        e = np.array([float(r["eps"]) for r in pts]) * 1.04 ** (k - (len(names) - 1) / 2)
        for ax, key, ci in ((axes[0], "detection_rate", "ci95_detection"),
                            (axes[1], "harmful_undetected_rate", "ci95_harmful_undetected")):
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
    axes[1].legend(fontsize=7, loc="best")
    return fig
