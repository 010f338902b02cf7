"""Integrated evaluation of the safety chain on image sequences (evaluation trajectories and the lab domain).

A sequence is a `Sequence` (name, images, targets, attack schedule; the evaluation trajectories add
the chaser's motion for the defense). `evaluate_sequences` runs each sequence clean and at every
eps through the chain (FGSM on the attacked frames, stored as 8-bit images), `per_eps_summary`
averages the per-sequence rows, and `accuracy_table` / `detail_table` lay them out for a report.
`defended_summary` runs the recorded frames through the defense (pipeline/defense/fusion.py) and gives the
fused chain's per-eps rates with 95% intervals (bootstrap over the sequences); `defense_table` lays
them out. `nan_to_none` makes the results JSON-safe.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Iterable, Iterator

import numpy as np
import pandas as pd
import torch

from pipeline.attacks.gradient import stored_attack
from pipeline.attacks.schedule import schedule_bursts
from pipeline.defense.chain import OnboardChain, run_sequence
from pipeline.defense.fusion import run_defense
from pipeline.defense.gate import MotionSettings
from pipeline.defense.noise import NoiseModel
from pipeline.defense.settings import DefenseSettings
from pipeline.detectors.metrics import detection_delays, frame_metrics, mean_over, undetected_mask
from pipeline.geometry.rotations import sixd_to_matrix
from pipeline.pose.metrics import pose_errors
from pipeline.stats import Rate, bootstrap_rate


@dataclass(frozen=True, eq=False)
class Sequence:
    """One image sequence through the safety chain: N frames with their labels and attack schedule."""

    name: str  # "T1".. (evaluation trajectory) or the recording's folder name
    images: np.ndarray  # (N, H, W, 3) uint8 frames
    targets: np.ndarray  # (N, 9) float32: target position in the camera frame (m), then 6-D rotation
    attacked: np.ndarray  # (N,) bool: the frames the schedule attacks
    rel: np.ndarray | None = None  # (N, 3) float64 true target position relative to the chaser, world frame (m)
    R_cam: np.ndarray | None = None  # (N, 3, 3) camera -> world rotation per frame
    u: np.ndarray | None = None  # (N, 3) the chaser's displacement of rel per frame, world frame (m)
    poses: pd.DataFrame | None = None  # the trajectory's label rows (tz: range in metres), for the timeline figure


@dataclass(frozen=True, eq=False)
class Trace:
    """One sequence's run through the chain (clean or at one eps), frame by frame."""

    prob: np.ndarray  # (N,) the detector's probability that the frame is attacked
    flag: np.ndarray  # (N,) bool: the detector's flags
    position_error: np.ndarray  # (N,) distance of the estimated to the true target position (m)
    estimate_z: np.ndarray  # (N,) estimated range t_z, camera frame (m)
    pose: np.ndarray  # (N, 9) pose outputs: position in the camera frame (m), then 6-D rotation


@dataclass(frozen=True, eq=False)
class Evaluation:
    """What `evaluate_sequences` measured."""

    rows: list[dict[str, Any]]  # one per (eps, sequence): detection metrics, pose errors (m, deg)
    traces: dict[tuple[float, str], Trace]  # (eps, sequence name) -> its trace; eps 0.0 for the clean runs
    clean: dict[str, dict[str, float]]  # sequence name -> {fpr, position_mean_m, attitude_mean_deg}, clean


def _trace(res: Any, pos: np.ndarray) -> Trace:
    """The trace of one `run_sequence` result whose position errors (m) are `pos`."""
    return Trace(prob=res.prob, flag=res.flag, position_error=pos, estimate_z=res.pose[:, 2], pose=res.pose)


def _bar_iter(it: Iterable[Any], bar: Any) -> Iterator[Any]:
    """Yield from `it`, advancing a tqdm bar per item."""
    for item in it:
        yield item
        bar.update(1)


def evaluate_sequences(
    chain: OnboardChain,
    loss_fn: Any,
    sequences: list[Sequence],
    eps_list: list[float],
    attack_length: int,
    batch_size: int,
    desc: str,
) -> Evaluation:
    """Run every sequence clean and at every eps through the chain -> per-row metrics, per-frame traces
    and the clean runs' rates and errors (`Evaluation`)."""
    from tqdm import tqdm

    rows, traces, clean = [], {}, {}
    total = sum(-(-len(s.images) // batch_size) for s in sequences) * (len(eps_list) + 1)
    bar = tqdm(total=total, desc=desc, unit="batch", dynamic_ncols=True)

    def progress(it: Iterable[int]) -> Iterator[int]:
        return _bar_iter(it, bar)

    for s in sequences:
        res = run_sequence(chain, s.images, s.targets, np.zeros(len(s.images), bool), None, batch_size, progress)
        pos, att = pose_errors(res.pose, s.targets)
        clean[s.name] = {
            "fpr": float(res.flag.mean()),
            "position_mean_m": float(pos.mean()),
            "attitude_mean_deg": float(att.mean()),
        }
        traces[(0.0, s.name)] = _trace(res, pos)
    for eps in eps_list:
        attack = stored_attack(chain.model, loss_fn, eps)
        for s in sequences:
            res = run_sequence(chain, s.images, s.targets, s.attacked, attack, batch_size, progress)
            pos, att = pose_errors(res.pose, s.targets)
            m = frame_metrics(s.attacked, res.flag, schedule_bursts(s.attacked, attack_length))
            und = undetected_mask(s.attacked, res.flag)
            rows.append(
                {
                    "eps": eps,
                    "sequence": s.name,
                    **m.as_dict(),
                    "frames": len(res.flag),
                    "correct": int((res.flag == s.attacked).sum()),
                    "attacked_frames": int(s.attacked.sum()),
                    "flagged_attacked": int((res.flag & s.attacked).sum()),
                    "clean_frames": int((~s.attacked).sum()),
                    "flagged_clean": int((res.flag & ~s.attacked).sum()),
                    "undetected_frames": int(und.sum()),
                    "undetected_position_m": mean_over(pos, und),
                    "undetected_attitude_deg": mean_over(att, und),
                    "attacked_position_m": mean_over(pos, s.attacked),
                    "attacked_attitude_deg": mean_over(att, s.attacked),
                    "clean_position_m": mean_over(pos, ~s.attacked),
                }
            )
            traces[(eps, s.name)] = _trace(res, pos)
    bar.close()
    return Evaluation(rows=rows, traces=traces, clean=clean)


def pose_errors_under_fgsm(
    chain: OnboardChain, loss_fn: Any, sequence: Sequence, eps_list: list[float], batch_size: int
) -> list[dict[str, Any]]:
    """Mean pose errors of one sequence clean and under FGSM at every eps (every frame attacked).

    One row per case: {"sequence", "eps" ("clean" or the eps), "position_m", "relative_position"
    (error / true range), "attitude_deg"}.
    """
    x = torch.from_numpy(sequence.images).permute(0, 3, 1, 2).float() / 255.0
    y = torch.from_numpy(sequence.targets)
    preds = {
        "clean": np.concatenate([chain.pose_only(x[i : i + batch_size]).numpy() for i in range(0, len(x), batch_size)])
    }
    for eps in eps_list:
        attack = stored_attack(chain.model, loss_fn, eps)
        preds[eps] = np.concatenate(
            [
                chain.pose_only(attack(x[i : i + batch_size], y[i : i + batch_size])).numpy()
                for i in range(0, len(x), batch_size)
            ]
        )
    rows = []
    for key, pred in preds.items():
        pos, att = pose_errors(pred, sequence.targets)
        rows.append(
            {
                "sequence": sequence.name,
                "eps": key,
                "position_m": float(pos.mean()),
                "relative_position": float(np.mean(pos / np.linalg.norm(sequence.targets[:, :3], axis=1))),
                "attitude_deg": float(att.mean()),
            }
        )
    return rows


def fgsm_error_table(
    chain: OnboardChain, loss_fn: Any, sequences: list[Sequence], eps_list: list[float], batch_size: int
) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """`pose_errors_under_fgsm` over every sequence, split into (clean rows, FGSM rows)."""
    clean, fgsm = [], []
    for s in sequences:
        for row in pose_errors_under_fgsm(chain, loss_fn, s, eps_list, batch_size):
            (clean if row["eps"] == "clean" else fgsm).append(row)
    return clean, fgsm


def _pooled(k: np.ndarray, n: np.ndarray) -> list[float | None]:
    """95% interval of sum(k) / sum(n) by a bootstrap over the sequences (k of n frames each): frames
    of one sequence are correlated, so sequences are resampled whole. Coarse with few sequences."""
    k, n = np.asarray(k, int), np.asarray(n, int)
    hits = np.concatenate([np.r_[np.ones(a, bool), np.zeros(b - a, bool)] for a, b in zip(k, n)])
    return bootstrap_rate(hits, np.repeat(np.arange(len(n)), n)).ci()


def per_eps_summary(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Average over the sequences of each eps (accuracy etc. as plain means of the per-sequence values),
    with 95% intervals (`*_ci95`) of accuracy, TPR and FPR by a bootstrap over the sequences."""
    df = pd.DataFrame(rows)
    out = []
    for eps, g in df.groupby("eps", sort=False):
        und = g["undetected_frames"].to_numpy()
        w_pos = g["undetected_position_m"].to_numpy()
        out.append(
            {
                "eps": float(eps),
                "accuracy": float(g["accuracy"].mean()),
                "tpr": float(g["tpr"].mean()),
                "accuracy_ci95": _pooled(g["correct"], g["frames"]),
                "tpr_ci95": _pooled(g["flagged_attacked"], g["attacked_frames"]),
                "fpr_ci95": _pooled(g["flagged_clean"], g["clean_frames"]),
                "fpr": float(g["fpr"].mean()),
                "mean_delay": float(np.nanmean(g["mean_delay"])) if g["mean_delay"].notna().any() else float("nan"),
                "missed_bursts": int(g["missed_bursts"].sum()),
                "bursts": int(g["bursts"].sum()),
                "undetected_frames": int(und.sum()),
                "undetected_position_m": float(np.nansum(w_pos * und) / und.sum()) if und.sum() else float("nan"),
                "attacked_position_m": float(g["attacked_position_m"].mean()),
            }
        )
    return out


def nan_to_none(obj: Any) -> Any:
    """NaN -> None, recursively through dicts and lists (JSON has no NaN)."""
    if isinstance(obj, dict):
        return {k: nan_to_none(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [nan_to_none(v) for v in obj]
    if isinstance(obj, float) and np.isnan(obj):
        return None
    return obj


def pct(v: float | None) -> float | str:
    """A rate in [0, 1] as a percentage, "-" when missing or NaN."""
    return "-" if v is None or (isinstance(v, float) and np.isnan(v)) else 100.0 * v


def dash(v: float | None) -> float | str:
    """The value, "-" when missing or NaN."""
    return "-" if v is None or (isinstance(v, float) and np.isnan(v)) else v


def accuracy_table(
    rows: list[dict[str, Any]], summary: list[dict[str, Any]], names: list[str], paper: dict[float, float]
) -> list[dict[str, Any]]:
    """Rows eps x (accuracy per sequence, average, paper) in %, and a final 'average' row."""
    table = []
    for s in summary:
        r = {"eps": f"{s['eps']:g}"}
        for name in names:
            r[name] = pct(next(x["accuracy"] for x in rows if x["eps"] == s["eps"] and x["sequence"] == name))
        r["average"] = pct(s["accuracy"])
        r["95% interval"] = _interval(s.get("accuracy_ci95"))
        r["paper (average)"] = paper.get(s["eps"], "-")
        table.append(r)
    avg = {"eps": "average"}
    for name in names:
        avg[name] = pct(float(np.mean([x["accuracy"] for x in rows if x["sequence"] == name])))
    avg["average"] = pct(float(np.mean([s["accuracy"] for s in summary])))
    avg["95% interval"] = "-"
    avg["paper (average)"] = "-"
    return table + [avg]


def _interval(ci: list[float | None] | None) -> str:
    """ "[lo, hi]" in percent, "-" when missing."""
    return "-" if not ci or ci[0] is None else f"[{100 * ci[0]:.1f}, {100 * ci[1]:.1f}]"


def detail_table(summary: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per eps: TPR, FPR (%) with 95% intervals, detection delay (frames), missed attacks, undetected frames
    and their pose error (m)."""
    return [
        {
            "eps": f"{s['eps']:g}",
            "TPR %": pct(s["tpr"]),
            "TPR 95% interval": _interval(s.get("tpr_ci95")),
            "FPR %": pct(s["fpr"]),
            "FPR 95% interval": _interval(s.get("fpr_ci95")),
            "mean delay (frames)": dash(s["mean_delay"]),
            "missed attacks": f"{s['missed_bursts']} / {s['bursts']}",
            "undetected attacked frames": s["undetected_frames"],
            "pose error, undetected (m)": dash(s["undetected_position_m"]),
            "pose error, all attacked (m)": dash(s["attacked_position_m"]),
        }
        for s in summary
    ]


def defend_trace(
    settings: DefenseSettings,
    motion: MotionSettings,
    noise: NoiseModel,
    pose: np.ndarray,
    prob: np.ndarray,
    R_cam: np.ndarray,
    u: np.ndarray,
) -> Any:
    """One recorded sequence (pose outputs (N, 9) and detector probabilities (N,), e.g. of a `Trace`)
    through a fresh defense, open loop: R_cam (N, 3, 3) camera -> world, u (N, 3) the chaser's
    displacement of rel per frame (world, m)."""
    pose = np.asarray(pose, np.float64)
    return run_defense(settings, motion, noise, pose[:, :3], prob, R_cam, u, sixd_to_matrix(pose[:, 3:9]))


def defended_summary(
    traces: dict[tuple[float, str], Trace],
    sequences: list[Sequence],
    eps_list: list[float],
    settings: DefenseSettings,
    motion: MotionSettings,
    noise: NoiseModel,
    attack_length: int,
    harm_m: float,
) -> list[dict[str, Any]]:
    """The defended chain per eps, frames pooled over the sequences, every rate a `pipeline.stats.Rate`
    (bootstrap over sequences, whose frames are correlated).

    Each sequence needs its motion: rel, R_cam and u (see `Sequence` and `defend_trace`). Per eps:
    accuracy (the paper's: correct frames / all frames), tpr, fpr (clean frames between attacks),
    fpr_clean (the attack-free run), harmful_flagged (attacked frames with position error > harm_m that
    were flagged), harmful_undetected (harmful and not flagged, over the attacked frames), mean_delay
    (frames from an attack's start to its first flag, over the flagged attacks), trusted_error_m /
    trusted_error_attacked_m (mean distance of the trusted estimate to the truth over all / the attacked
    frames, m).
    """
    fpr_clean = _clean_fpr(traces, sequences, settings, motion, noise)
    out = []
    for eps in eps_list:
        cols: dict[str, list[np.ndarray]] = {k: [] for k in ("flag", "attacked", "harm", "group", "err")}
        delays = []
        for g, s in enumerate(sequences):
            tr = traces[(eps, s.name)]
            d = defend_trace(settings, motion, noise, tr.pose, tr.prob, s.R_cam, s.u)
            att = np.asarray(s.attacked, bool)
            cols["flag"].append(d.flag)
            cols["attacked"].append(att)
            cols["harm"].append(att & (tr.position_error > harm_m))
            cols["group"].append(np.full(len(att), g))
            cols["err"].append(np.linalg.norm(d.trusted - s.rel, axis=1))
            delays.append(detection_delays(schedule_bursts(att, attack_length), d.flag))
        flag, att, harm, group, err = (np.concatenate(cols[k]) for k in ("flag", "attacked", "harm", "group", "err"))
        delay = np.concatenate(delays) if delays else np.zeros(0)
        hit = delay[~np.isnan(delay)]
        ok = np.isfinite(err)
        out.append(
            {
                "eps": float(eps),
                "accuracy": bootstrap_rate(flag == att, group),
                "tpr": bootstrap_rate(flag[att], group[att]),
                "fpr": bootstrap_rate(flag[~att], group[~att]),
                "fpr_clean": fpr_clean,
                "harmful_frames": int(harm.sum()),
                "harmful_flagged": bootstrap_rate(flag[harm], group[harm]),
                "harmful_undetected": bootstrap_rate((harm & ~flag)[att], group[att]),
                "mean_delay": float(hit.mean()) if len(hit) else float("nan"),
                "missed_bursts": int(np.isnan(delay).sum()),
                "bursts": int(len(delay)),
                "trusted_error_m": float(err[ok].mean()) if ok.any() else float("nan"),
                "trusted_error_attacked_m": float(err[ok & att].mean()) if (ok & att).any() else float("nan"),
            }
        )
    return out


def _clean_fpr(
    traces: dict[tuple[float, str], Trace],
    sequences: list[Sequence],
    settings: DefenseSettings,
    motion: MotionSettings,
    noise: NoiseModel,
) -> Rate:
    """The defended chain's false-alarm rate on the attack-free runs (eps 0) of the sequences, frames pooled
    (bootstrap over sequences)."""
    clean_flags, clean_groups = [], []
    for g, s in enumerate(sequences):
        clean = traces[(0.0, s.name)]
        d = defend_trace(settings, motion, noise, clean.pose, clean.prob, s.R_cam, s.u)
        clean_flags.append(d.flag)
        clean_groups.append(np.full(len(d.flag), g))
    return bootstrap_rate(np.concatenate(clean_flags), np.concatenate(clean_groups))


def rates_json(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """`defended_summary` rows for JSON: every Rate as {"value", "ci": [lo, hi], "n"}."""

    def conv(v: Any) -> Any:
        if hasattr(v, "ci") and hasattr(v, "n"):
            return {"value": float(v.value), "ci": v.ci(), "n": int(v.n)}
        return v

    return [{k: conv(v) for k, v in r.items()} for r in rows]


def defense_table(chains: dict[str, list[dict[str, Any]]]) -> list[dict[str, Any]]:
    """Rows (eps, chain) of `defended_summary` results: rates in % with 95% intervals."""
    table = []
    eps_order = list(dict.fromkeys(r["eps"] for rows in chains.values() for r in rows))
    for eps in eps_order:
        for name, rows in chains.items():
            r = next(x for x in rows if x["eps"] == eps)
            table.append(
                {
                    "eps": f"{eps:g}",
                    "chain": name,
                    "accuracy %": r["accuracy"].pct(2),
                    "TPR %": r["tpr"].pct(),
                    "FPR % between attacks": r["fpr"].pct(),
                    "FPR % attack-free": r["fpr_clean"].pct(),
                    "harmful flagged %": f"{r['harmful_flagged'].pct()} of {r['harmful_frames']}",
                    "harmful undetected %": r["harmful_undetected"].pct(),
                    "mean delay (frames)": dash(r["mean_delay"]),
                    "trusted error (m)": dash(r["trusted_error_m"]),
                    "trusted error, attacked (m)": dash(r["trusted_error_attacked_m"]),
                }
            )
    return table
