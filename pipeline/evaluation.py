"""Integrated evaluation of the safety chain on image sequences (SPEC 8, and the lab domain of SPEC 9).

A sequence is a dict {"name", "images" (N, H, W, 3) uint8, "targets" (N, 9: metres in the camera
frame, then 6-D), "attacked" (N,) bool}. `evaluate_sequences` runs each sequence clean and at every
eps through the chain (FGSM on the attacked frames, stored as 8-bit images), `per_eps_summary`
averages the per-sequence rows, and `accuracy_table` / `detail_table` lay them out for a report.
`nan_to_none` makes the results JSON-safe.
"""
from __future__ import annotations

from typing import Any, Iterable, Iterator

import numpy as np
import pandas as pd
import torch

from pipeline.attacks import stored_attack
from pipeline.chain import SafetyChain, run_sequence
from pipeline.schedule import detection_metrics, mean_over, schedule_bursts, undetected_mask
from pipeline.training import pose_errors


def _bar_iter(it: Iterable[Any], bar: Any) -> Iterator[Any]:
    """Yield from `it`, advancing a tqdm bar per item."""
    for item in it:
        yield item
        bar.update(1)


def evaluate_sequences(chain: SafetyChain, loss_fn: Any, sequences: list[dict[str, Any]], eps_list: list[float],
                       attack_length: int, batch_size: int, desc: str) -> dict[str, Any]:
    """Run every sequence clean and at every eps through the chain; per-row metrics and per-frame traces.

    Returns {"rows": [one dict per (eps, sequence)], "traces": {(eps, name): {prob, flag,
    position_error (m), estimate_z (m)}}, "clean": {name: {fpr, position_mean_m, attitude_mean_deg}}}.
    """
    from tqdm import tqdm

    rows, traces, clean = [], {}, {}
    total = sum(-(-len(s["images"]) // batch_size) for s in sequences) * (len(eps_list) + 1)
    bar = tqdm(total=total, desc=desc, unit="batch", dynamic_ncols=True)

    def progress(it: Iterable[int]) -> Iterator[int]:
        return _bar_iter(it, bar)

    for s in sequences:
        res = run_sequence(chain, s["images"], s["targets"], np.zeros(len(s["images"]), bool), None, batch_size,
                           progress)
        pos, att = pose_errors(res.pose, s["targets"])
        clean[s["name"]] = {"fpr": float(res.flag.mean()), "position_mean_m": float(pos.mean()),
                            "attitude_mean_deg": float(att.mean())}
    for eps in eps_list:
        attack = stored_attack(chain.model, loss_fn, eps)
        for s in sequences:
            res = run_sequence(chain, s["images"], s["targets"], s["attacked"], attack, batch_size, progress)
            pos, att = pose_errors(res.pose, s["targets"])
            m = detection_metrics(s["attacked"], res.flag, schedule_bursts(s["attacked"], attack_length))
            und = undetected_mask(s["attacked"], res.flag)
            rows.append({"eps": eps, "sequence": s["name"], **m.as_dict(),
                         "undetected_frames": int(und.sum()),
                         "undetected_position_m": mean_over(pos, und), "undetected_attitude_deg": mean_over(att, und),
                         "attacked_position_m": mean_over(pos, s["attacked"]),
                         "attacked_attitude_deg": mean_over(att, s["attacked"]),
                         "clean_position_m": mean_over(pos, ~s["attacked"])})
            traces[(eps, s["name"])] = {"prob": res.prob, "flag": res.flag, "position_error": pos,
                                        "estimate_z": res.pose[:, 2]}
    bar.close()
    return {"rows": rows, "traces": traces, "clean": clean}


def pose_errors_under_fgsm(chain: SafetyChain, loss_fn: Any, sequence: dict[str, Any], eps_list: list[float],
                           batch_size: int) -> list[dict[str, Any]]:
    """Mean pose errors of one sequence clean and under FGSM at every eps (every frame attacked).

    One row per case: {"sequence", "eps" ("clean" or the eps), "position_m", "relative_position"
    (error / true range), "attitude_deg"}.
    """
    x = torch.from_numpy(sequence["images"]).permute(0, 3, 1, 2).float() / 255.0
    y = torch.from_numpy(sequence["targets"])
    preds = {"clean": np.concatenate([chain.pose_only(x[i:i + batch_size]).numpy()
                                      for i in range(0, len(x), batch_size)])}
    for eps in eps_list:
        attack = stored_attack(chain.model, loss_fn, eps)
        preds[eps] = np.concatenate([chain.pose_only(attack(x[i:i + batch_size], y[i:i + batch_size])).numpy()
                                     for i in range(0, len(x), batch_size)])
    rows = []
    for key, pred in preds.items():
        pos, att = pose_errors(pred, sequence["targets"])
        rows.append({"sequence": sequence["name"], "eps": key, "position_m": float(pos.mean()),
                     "relative_position": float(np.mean(pos / np.linalg.norm(sequence["targets"][:, :3], axis=1))),
                     "attitude_deg": float(att.mean())})
    return rows


def per_eps_summary(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Average over the sequences of each eps (accuracy etc. as plain means of the per-sequence values)."""
    df = pd.DataFrame(rows)
    out = []
    for eps, g in df.groupby("eps", sort=False):
        und = g["undetected_frames"].to_numpy()
        w_pos = g["undetected_position_m"].to_numpy()
        out.append({"eps": float(eps), "accuracy": float(g["accuracy"].mean()), "tpr": float(g["tpr"].mean()),
                    "fpr": float(g["fpr"].mean()), "mean_delay": float(np.nanmean(g["mean_delay"]))
                    if g["mean_delay"].notna().any() else float("nan"),
                    "missed_bursts": int(g["missed_bursts"].sum()), "bursts": int(g["bursts"].sum()),
                    "undetected_frames": int(und.sum()),
                    "undetected_position_m": float(np.nansum(w_pos * und) / und.sum()) if und.sum() else float("nan"),
                    "attacked_position_m": float(g["attacked_position_m"].mean())})
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


def accuracy_table(rows: list[dict[str, Any]], summary: list[dict[str, Any]], names: list[str],
                   paper: dict[float, float]) -> list[dict[str, Any]]:
    """Rows eps x (accuracy per sequence, average, paper) in %, and a final 'average' row."""
    table = []
    for s in summary:
        r = {"eps": f"{s['eps']:g}"}
        for name in names:
            r[name] = pct(next(x["accuracy"] for x in rows if x["eps"] == s["eps"] and x["sequence"] == name))
        r["average"] = pct(s["accuracy"])
        r["paper (average)"] = paper.get(s["eps"], "-")
        table.append(r)
    avg = {"eps": "average"}
    for name in names:
        avg[name] = pct(float(np.mean([x["accuracy"] for x in rows if x["sequence"] == name])))
    avg["average"] = pct(float(np.mean([s["accuracy"] for s in summary])))
    avg["paper (average)"] = "-"
    return table + [avg]


def detail_table(summary: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per eps: TPR, FPR (%), detection delay (frames), missed attacks, undetected frames and their pose error (m)."""
    return [{"eps": f"{s['eps']:g}", "TPR %": pct(s["tpr"]), "FPR %": pct(s["fpr"]),
             "mean delay (frames)": dash(s["mean_delay"]), "missed attacks": f"{s['missed_bursts']} / {s['bursts']}",
             "undetected attacked frames": s["undetected_frames"],
             "pose error, undetected (m)": dash(s["undetected_position_m"]),
             "pose error, all attacked (m)": dash(s["attacked_position_m"])} for s in summary]
