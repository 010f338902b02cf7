"""`rpod evaluate`: the whole safety chain on fresh trajectories, frame by frame (SPEC 8).

Two DVC stages use this command:
- `rpod evaluate --render-only` (stage `eval_render`) renders `evaluate.trajectories` fresh
  projectile-shaped approaches (own seed `evaluate.seed`) with one Blender scene into
  datasets/eval_render/ (images.zarr, poses.parquet, meta.json), so changing eps never re-renders.
- `rpod evaluate` (stage `evaluate`) runs, per eps and trajectory, every frame through
  image -> (FGSM against that frame's true label when the schedule says so) -> pose -> exact SHAP
  -> detector flag, and writes reports/integrated.md, reports/figures/timeline.png and
  reports/metrics/evaluate.json.
"""
from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import typer

from stages import params as params_mod
from stages.io import StageError, atomic_dir, atomic_write_text, file_hash, open_zarr, read_json, read_parquet, write_json, write_metrics

RENDER_OUT = Path("datasets/eval_render")
MODEL = Path("models/pose.pt")
REPORT = Path("reports/integrated.md")
FIGURE = Path("reports/figures/timeline.png")
METRICS = Path("reports/metrics/evaluate.json")
SCHEDULE_SEED_OFFSET = 17
TARGET = ["tx", "ty", "tz", "r0", "r1", "r2", "r3", "r4", "r5"]
# The paper's integrated detection accuracy (%), averaged over its three trajectories, per eps.
PAPER_ACCURACY = {0.5: 100.0, 0.3: 99.99, 0.1: 99.97, 0.05: 99.99, 0.01: 97.67}
PAPER_OVERALL = 99.21


def check_params(e: dict[str, Any]) -> None:
    """Clear one-line errors for evaluate params that would fail deep inside the run."""
    if int(e["trajectories"]) < 1 or int(e["frames"]) < 2:
        raise StageError(f"params.yaml evaluate: need trajectories >= 1 and frames >= 2, "
                         f"got {e['trajectories']} and {e['frames']}")
    lo, hi = (float(v) for v in e["lateral_range"])
    if not 0 <= lo <= hi:
        raise StageError(f"params.yaml evaluate.lateral_range must be [low, high] with 0 <= low <= high, got {e['lateral_range']}")
    if not 0 <= float(e["p_start"]) <= 1 or int(e["attack_length"]) < 1:
        raise StageError(f"params.yaml evaluate: p_start must be in [0, 1] and attack_length >= 1, "
                         f"got {e['p_start']} and {e['attack_length']}")
    bad = [x for x in e["eps"] if not 0 < float(x) <= 1]
    if bad or not e["eps"]:
        raise StageError(f"params.yaml evaluate.eps must be a non-empty list of values in (0, 1], got {e['eps']}")
    if int(e["batch_size"]) < 1:
        raise StageError(f"params.yaml evaluate.batch_size must be >= 1, got {e['batch_size']}")


def trajectories(p: dict[str, Any]) -> list[Any]:
    """The fresh SPEC 8 approaches: lateral start offsets |x|, |y| uniform in lateral_range, random signs."""
    from pipeline.trajectories import projectile_trajectory

    e, r = p["evaluate"], p["render"]
    rng = np.random.default_rng(int(e["seed"]))
    lo, hi = (float(v) for v in e["lateral_range"])
    out = []
    for i in range(int(e["trajectories"])):
        xy = rng.uniform(lo, hi, 2) * rng.choice([-1.0, 1.0], 2)
        out.append(projectile_trajectory(int(e["frames"]), (float(xy[0]), float(xy[1])), float(r["start_range"]),
                                         float(r["end_range"]), seed=int(e["seed"]) + 1 + i,
                                         jitter_deg=float(r["pointing_jitter_deg"]), max_rot_deg=0.0, sequence=i))
    return out


def render_fingerprint(p: dict[str, Any]) -> str:
    """Hash of everything that decides the evaluation images."""
    e = p["evaluate"]
    key = {"seed": p["seed"], "camera": p["camera"], "render": p["render"],
           "evaluate": {k: e[k] for k in ("trajectories", "frames", "lateral_range", "seed")}}
    return hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:16]


def render_trajectories(p: dict[str, Any]) -> None:
    """Render the evaluation trajectories with one Blender scene into datasets/eval_render (atomic)."""
    import pandas as pd
    import zarr
    from tqdm import tqdm

    from pipeline.rotations import matrix_to_6d, matrix_to_quat
    from pipeline.scene import Renderer
    from stages.render import intrinsics, scene_settings

    K = intrinsics(p)
    seqs = trajectories(p)
    n = sum(len(s) for s in seqs)
    t0 = time.perf_counter()
    with atomic_dir(RENDER_OUT) as tmp:
        store = zarr.open_group(str(tmp / "images.zarr"), mode="w")
        images = store.create_array("images", shape=(n, K.height, K.width, 3),
                                    chunks=(min(n, 100), K.height, K.width, 3), dtype="uint8")
        try:
            renderer = Renderer(K, scene_settings(p["render"]))
        except ValueError as err:
            raise StageError(f"params.yaml render: {err}") from None
        rows, k = [], 0
        try:
            with tqdm(total=n, desc="eval_render", unit="img", dynamic_ncols=True) as bar:
                for s in seqs:
                    buf = np.stack([renderer.render(s.R[i], s.t[i]) for i in bar_iter(range(len(s)), bar)])
                    images[k:k + len(s)] = buf
                    q, r6 = matrix_to_quat(s.R), matrix_to_6d(s.R)
                    rows.append(pd.DataFrame({
                        "index": np.arange(k, k + len(s)), "trajectory": s.sequence, "frame": s.frame,
                        "tx": s.t[:, 0], "ty": s.t[:, 1], "tz": s.t[:, 2],
                        "qw": q[:, 0], "qx": q[:, 1], "qy": q[:, 2], "qz": q[:, 3],
                        **{f"r{j}": r6[:, j] for j in range(6)}, "range": np.linalg.norm(s.t, axis=1)}))
                    k += len(s)
        finally:
            renderer.close()
        pd.concat(rows, ignore_index=True).to_parquet(tmp / "poses.parquet", index=False)
        seconds = time.perf_counter() - t0
        write_json(tmp / "meta.json", {"complete": True, "fingerprint": render_fingerprint(p), "frames": n,
                                       "trajectories": len(seqs), "width": K.width, "height": K.height, "K": K.K,
                                       "seconds": seconds, "seconds_per_image": seconds / n,
                                       "start_xy": [s.rel[0, :2].tolist() for s in seqs]})
    typer.echo(f"eval_render: {n} images ({len(seqs)} trajectories) in {seconds:.0f} s -> {RENDER_OUT}")


def bar_iter(it: Any, bar: Any) -> Any:
    """Yield from `it`, advancing a tqdm bar per item."""
    for item in it:
        yield item
        bar.update(1)


def read_eval_render(p: dict[str, Any]) -> tuple[np.ndarray, Any, dict[str, Any]]:
    """(images (N, H, W, 3) uint8, poses table, meta), checked against the current params."""
    meta = read_json(RENDER_OUT / "meta.json")
    if not meta.get("complete") or meta.get("fingerprint") != render_fingerprint(p):
        raise StageError(f"{RENDER_OUT} was rendered with other params (or is incomplete); "
                         f"run `rpod evaluate --render-only` (dvc repro eval_render)")
    images = open_zarr(RENDER_OUT / "images.zarr", "evaluation renders")["images"][:]
    poses = read_parquet(RENDER_OUT / "poses.parquet", "evaluation poses")
    if len(images) != len(poses) or len(poses) != meta["frames"]:
        raise StageError(f"{RENDER_OUT} is inconsistent; delete it and run `rpod evaluate --render-only`")
    return images, poses, meta


def load_chain(p: dict[str, Any]) -> tuple[Any, Any, str]:
    """(SafetyChain, attack loss function, pose model hash) from models/pose.pt and models/detector.pt."""
    from pipeline.attacks import attack_loss
    from pipeline.chain import SafetyChain
    from stages.checkpoint import load_pose_loss, load_pose_model
    from stages.detect import load_detector

    model = load_pose_model(MODEL, p)
    model_hash = file_hash(MODEL)
    detector, ckpt = load_detector(model_hash=model_hash)
    try:
        chain = SafetyChain.from_model(model, np.asarray(ckpt["background_mean"]), detector,
                                       threshold=float(ckpt["threshold"]))
    except ValueError as err:
        raise StageError(f"{MODEL}: {err}") from None
    return chain, attack_loss(p["attack"]["loss"], load_pose_loss(MODEL, p)), model_hash


def fgsm_attack(model: Any, loss_fn: Any, eps: float) -> Any:
    """FGSM at `eps` against the given labels, stored as an 8-bit camera image would be."""
    from pipeline.attacks import fgsm, quantize

    def attack(x: Any, y: Any) -> Any:
        return quantize(fgsm(model, x, y, eps, loss_fn), x).float() / 255.0

    return attack


def evaluate_sequences(chain: Any, loss_fn: Any, sequences: list[dict[str, Any]], eps_list: list[float],
                       attack_length: int, batch_size: int, desc: str) -> dict[str, Any]:
    """Run every sequence at every eps through the chain; per-row metrics and per-frame traces.

    A sequence is {"name", "images" (N,H,W,3) uint8, "targets" (N, 9), "attacked" (N,) bool}.
    Returns {"rows": [...], "traces": {(eps, name): {...}}, "clean": {name: {...}}}.
    """
    from tqdm import tqdm

    from pipeline.chain import run_sequence
    from pipeline.schedule import detection_metrics, mean_over, schedule_bursts, undetected_mask
    from pipeline.training import pose_errors

    rows, traces, clean = [], {}, {}
    total = sum(-(-len(s["images"]) // batch_size) for s in sequences) * (len(eps_list) + 1)
    bar = tqdm(total=total, desc=desc, unit="batch", dynamic_ncols=True)

    def progress(it: Any) -> Any:
        return bar_iter(it, bar)

    for s in sequences:
        res = run_sequence(chain, s["images"], s["targets"], np.zeros(len(s["images"]), bool), None, batch_size,
                           progress)
        pos, att = pose_errors(res.pose, s["targets"])
        clean[s["name"]] = {"fpr": float(res.flag.mean()), "position_mean_m": float(pos.mean()),
                            "attitude_mean_deg": float(att.mean())}
    for eps in eps_list:
        attack = fgsm_attack(chain.model, loss_fn, eps)
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


def per_eps_summary(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Average over the sequences of each eps (accuracy etc. as plain means of the per-sequence values)."""
    import pandas as pd

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
    """NaN -> None, recursively (JSON has no NaN)."""
    if isinstance(obj, dict):
        return {k: nan_to_none(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [nan_to_none(v) for v in obj]
    if isinstance(obj, float) and np.isnan(obj):
        return None
    return obj


def timeline_figure(poses: Any, attacked: np.ndarray, trace: dict[str, Any], threshold: float, title: str,
                    path: Path) -> None:
    """Range, attacked frames, detector probability and flags, pose error for one trajectory."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from stages.attack import save_figure

    frames = np.arange(len(attacked))
    fig, axes = plt.subplots(3, 1, figsize=(9, 7), sharex=True)

    def shade(ax: Any, label: bool = False) -> None:
        from pipeline.schedule import bursts

        for k, (a, b) in enumerate(bursts(attacked)):
            ax.axvspan(a - 0.5, b - 0.5, color="tab:red", alpha=0.15, lw=0,
                       label="attacked frames" if label and k == 0 else None)

    ax = axes[0]
    shade(ax, label=True)
    ax.plot(frames, poses["tz"].to_numpy(), "k-", lw=1.2, label="true t_z")
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
    save_figure(fig, path)


def main(render_only: bool = typer.Option(False, "--render-only",
                                          help="Only render the evaluation trajectories into datasets/eval_render "
                                               "(the `eval_render` stage).")) -> None:
    """Detect FGSM attacks frame by frame on fresh trajectories with the whole safety chain (SPEC 8).

    Params: `evaluate` (trajectories, frames, lateral_range, p_start, attack_length, eps, seed,
    batch_size), plus `render`/`camera` for the images and `attack.loss` for the FGSM loss.
    """
    p = params_mod.load()
    e = p["evaluate"]
    check_params(e)
    if render_only:
        render_trajectories(p)
        return
    import torch

    from pipeline.schedule import attack_schedule

    torch.set_num_threads(2)
    images, poses, meta = read_eval_render(p)
    chain, loss_fn, model_hash = load_chain(p)
    eps_list = [float(x) for x in e["eps"]]
    length = int(e["attack_length"])
    sequences = []
    for tr, g in poses.groupby("trajectory", sort=True):
        idx = g["index"].to_numpy()
        sequences.append({"name": f"T{int(tr) + 1}", "images": images[idx], "poses": g.reset_index(drop=True),
                          "targets": g[TARGET].to_numpy(np.float32),
                          "attacked": attack_schedule(len(idx), float(e["p_start"]), length,
                                                      int(e["seed"]) + SCHEDULE_SEED_OFFSET + int(tr))})
    t0 = time.perf_counter()
    res = evaluate_sequences(chain, loss_fn, sequences, eps_list, length, int(e["batch_size"]), "evaluate")
    seconds = time.perf_counter() - t0
    summary = per_eps_summary(res["rows"])
    eps_fig = min(eps_list)
    s0 = sequences[0]
    timeline_figure(s0["poses"], s0["attacked"], res["traces"][(eps_fig, s0["name"])], chain.threshold,
                    f"{s0['name']}: FGSM eps={eps_fig:g} on {int(s0['attacked'].sum())} of {len(s0['attacked'])} "
                    f"frames ({length}-frame attacks, p_start={float(e['p_start']):g})", FIGURE)
    metrics = {"model_hash": model_hash, "frames_per_trajectory": int(e["frames"]), "trajectories": len(sequences),
               "p_start": float(e["p_start"]), "attack_length": length, "threshold": chain.threshold,
               "seconds": seconds, "accuracy_mean": float(np.mean([r["accuracy"] for r in summary])),
               "per_eps": {f"{r['eps']:g}": r for r in summary},
               "rows": res["rows"], "clean": res["clean"],
               "attacked_fraction": {s["name"]: float(s["attacked"].mean()) for s in sequences},
               "start_xy": meta["start_xy"]}
    write_metrics(METRICS, nan_to_none(metrics), p)
    atomic_write_text(REPORT, report(res["rows"], summary, res["clean"], sequences, e, meta, chain.threshold,
                                     eps_fig, str(p.get("profile_name", "?"))))
    typer.echo(f"evaluate: {len(sequences)} trajectories x {len(eps_list)} eps in {seconds:.0f} s; mean accuracy "
               f"{100 * metrics['accuracy_mean']:.2f}% -> {REPORT}, {FIGURE}")


def pct(v: float) -> float | str:
    return "-" if v is None or (isinstance(v, float) and np.isnan(v)) else 100.0 * v


def dash(v: float) -> float | str:
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
    return [{"eps": f"{s['eps']:g}", "TPR %": pct(s["tpr"]), "FPR %": pct(s["fpr"]),
             "mean delay (frames)": dash(s["mean_delay"]), "missed attacks": f"{s['missed_bursts']} / {s['bursts']}",
             "undetected attacked frames": s["undetected_frames"],
             "pose error, undetected (m)": dash(s["undetected_position_m"]),
             "pose error, all attacked (m)": dash(s["attacked_position_m"])} for s in summary]


def report(rows: list[dict[str, Any]], summary: list[dict[str, Any]], clean: dict[str, dict[str, float]],
           sequences: list[dict[str, Any]], e: dict[str, Any], meta: dict[str, Any], threshold: float,
           eps_fig: float, profile: str) -> str:
    from pipeline.report import markdown_table

    names = [s["name"] for s in sequences]
    att_frac = np.mean([s["attacked"].mean() for s in sequences])
    mean_acc = 100 * np.mean([s["accuracy"] for s in summary])
    starts = ", ".join(f"{n} ({x:+.1f}, {y:+.1f}) m" for n, (x, y) in zip(names, meta["start_xy"]))
    clean_rows = [{"trajectory": n, "FPR % (no attack)": pct(c["fpr"]), "position error (m)": c["position_mean_m"],
                   "attitude error (deg)": c["attitude_mean_deg"]} for n, c in clean.items()]
    clean_rows.append({"trajectory": "all (equal frames each)",
                       "FPR % (no attack)": pct(float(np.mean([c["fpr"] for c in clean.values()]))),
                       "position error (m)": float(np.mean([c["position_mean_m"] for c in clean.values()])),
                       "attitude error (deg)": float(np.mean([c["attitude_mean_deg"] for c in clean.values()]))})
    return f"""# Integrated evaluation: the safety chain frame by frame

{len(names)} fresh trajectories (never seen in training; seed {e['seed']}), {e['frames']} frames each, from 60 m
with lateral start offsets {starts} along a projectile-shaped path to (0, 0, 10) m. Every frame goes
through the chain as onboard: image -> (FGSM against that frame's true label, stored as an 8-bit
image, when the schedule attacks it) -> pose -> exact SHAP of the GAP features -> LSTM detector
(threshold {threshold:.3f}). A frame outside an attack starts one with probability {e['p_start']:g};
each attack lasts {e['attack_length']} frames, so {100 * att_frac:.1f}% of the frames are attacked
(the same schedule for every eps). Accuracy counts frames, as the paper does: correctly classified
frames / all frames (time: reports/metrics/evaluate.json).

## Detection accuracy (%)

{markdown_table(accuracy_table(rows, summary, names, PAPER_ACCURACY), decimals=2)}
Mean over eps: **{mean_acc:.2f}%** (paper: {PAPER_OVERALL}% overall, from 2,500-frame trajectories at
480x270 with the full-width network; ours: the {profile} profile's {e['frames']} frames at
{meta['width']}x{meta['height']}).

## What the paper did not report

Rates averaged over the trajectories; the delay is the number of frames from an attack's first
frame to its first flag (0 = flagged at once), over the attacks flagged at all; a missed attack
has no flag in any of its frames. The pose errors are position errors on the attacked frames the
detector let through (the ones guidance would act on), and on all attacked frames.

{markdown_table(detail_table(summary), decimals=2)}
Without any attack (the same frames, clean). The trajectories are whole sequences never rendered
for training, so these pose errors are the **held-out-trajectory** errors, beside the per-frame test
split's (reports/pose.md, whose test frames lie between training frames of the same sequences):

{markdown_table(clean_rows, decimals=2)}
![timeline](figures/timeline.png)

Timeline of {names[0]} at eps = {eps_fig:g}: true and estimated range, the detector's probability and
flags, and the position error (red crosses: attacked frames that were not flagged).
"""
