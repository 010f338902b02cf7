"""Paper-profile cost model: per-unit rates measured on this machine -> predicted wall time per stage.

Measures a few repeats of each unit of work (a 480x270 Cycles frame at the paper's samples, a training
image at width 1, a batched and a batch-1 pose forward, an input gradient, a detector sample-epoch),
counts the units each stage of the paper profile needs (conf/config.yaml + conf/profile/paper.yaml),
and predicts the paper profile's wall time per stage on this machine. Counts that depend on the
data (early stopping, the guidance stage's render cache, attacked frames) are stated assumptions.
Then prints what one GPU box would need to reach the 2-hour target: a requirement, not a measurement.
Writes the `## Paper-profile cost model` section of reports/benchmarks.md (`## Paper-profile cost model on a
GPU` with --device cuda; other sections are kept).

Usage: .venv/bin/python benchmarks/cost_model.py [--device cpu|cuda] [--repeats 2] [--render-rate R] [--no-write]
--render-rate: frames/s of the Cycles unit, given instead of measured (a GPU box whose Python has no bpy).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from typing import Any, Callable

import numpy as np

TARGET_S = 2 * 3600  # the target: paper profile end to end in under 2 hours
TARGET_CORES = 16  # ... on one H100-class GPU with 16 cores
BATCHES = {"cpu": (4, 8), "cuda": (32, 64)}  # (training / gradient batch, forward batch): seconds per unit here
UNITS = {
    "render": "one 480x270 Cycles frame (paper samples)",
    "train": "one training image: forward + backward + Adam (width 1, 480x270)",
    "forward": "one pose forward in a batch (inference)",
    "forward1": "one pose forward at batch 1 (closed loop)",
    "gradient": "one input gradient (forward + backward w.r.t. the image)",
    "lstm": "one detector training sample-epoch (9 x 1000 SHAP values)",
}


# ----------------------------------------------------------------------------- counts (pure arithmetic)
def attacked_fraction(p_start: float, length: int) -> float:
    """Expected fraction of attacked frames when an attack of `length` frames starts with probability
    `p_start` on each clean frame (clean gaps of mean 1 / p_start frames)."""
    return length / (length + 1 / p_start) if p_start > 0 else 0.0


def training_counts(n_images: int, p: dict[str, Any], epochs: int) -> dict[str, float]:
    """Units of one pose-model training on `n_images` labelled frames: every epoch trains on the training
    part and predicts the validation part; at the end every frame is predicted once."""
    n_train = n_images * (1 - p["label"]["test_fraction"])
    n_val = n_train * p["train"]["val_fraction"]
    return {"train": epochs * (n_train - n_val), "forward": epochs * n_val + n_images}


def detector_counts(p: dict[str, Any]) -> dict[str, float]:
    """The detector split's renders (whole shap.frames trajectories for the SHAP sources), SHAP forwards,
    the FGSM gradients of the attacked samples and LSTM sample-epochs (at most detect.epochs: early
    stopping ends sooner)."""
    s, d = p["shap"], p["detect"]
    attacked = s["per_eps"] * len(s["eps"])
    samples = s["normal"] + attacked
    fit = samples * (1 - d["test_fraction"])
    return {
        "render": -(-max(s["normal"], attacked) // s["frames"]) * s["frames"],
        "gradient": attacked,
        "shap_forward": s["background"] + samples,
        "lstm": d["epochs"] * fit,
        "squeeze_forward": 2 * samples * ("squeeze" in d["baselines"]),
    }


def guidance_counts(p: dict[str, Any], renders_per_step: float) -> dict[str, float]:
    """Closed-loop steps: the paper grid plus the defended grid (per dynamics, undefended and each
    defense), each run about max_steps / 2 + slack_steps steps (the baseline's arrival at the nominal
    speed plus the slack); renders = steps x `renders_per_step` (the stage caches repeated views)."""
    g = p["guidance"]
    grid = len(g["eps"]) * len(g["start_ranges"]) * len(g["lengths"])
    runs = (grid + 1) * (1 + len(g["dynamics"]) * (1 + len(g["defenses"])))
    steps = runs * (g["max_steps"] / 2 + g["slack_steps"])
    attacked = grid * (1 + len(g["dynamics"]) * (1 + len(g["defenses"]))) * float(np.mean(g["lengths"]))
    return {"render": steps * renders_per_step, "forward1": steps, "gradient": attacked}


def robustness_gradients_per_frame(p: dict[str, Any]) -> float:
    """Input gradients per held-out frame: FGSM at eps and unseen_eps, the transfer attacks (PGD: steps,
    MI-FGSM: attack.steps, FGSM variants: 1), the adaptive PGD per lambda (lambda 0 = the plain PGD)
    and the surrogate attacks, each at every robustness.eps."""
    r = p["robustness"]
    cost = {"fgsm": 1, "pgd": r["steps"], "mifgsm": p["attack"]["steps"]}
    transfer = sum(cost[name.partition("/")[0]] for name in r["transfer"])
    adaptive = r["steps"] * len([v for v in r["lambdas"] if v > 0 or "pgd" not in r["transfer"]])
    surrogate = sum(cost[name.partition("/")[0]] for name in r["surrogate_attacks"])
    return len(r["eps"]) * (1 + transfer + adaptive + surrogate) + len(r["unseen_eps"])


def robustness_rows(p: dict[str, Any]) -> int:
    """Per-frame rows of the robustness stage (each a chain forward of every held-out frame): attacks
    per eps, unseen-eps FGSM and the benign corruptions (the fused-chain burst rows are left out)."""
    r = p["robustness"]
    per_eps = 1 + len(r["transfer"]) + len(r["lambdas"]) + len(r["surrogate_attacks"])
    return len(r["eps"]) * per_eps + len(r["unseen_eps"]) + sum(len(v) for v in r["corruptions"].values()) + 1


def paper_counts(p: dict[str, Any], renders_per_step: float = 1.0) -> dict[str, dict[str, float]]:
    """Units of work per stage of the profile in params `p` (stage -> unit -> count)."""
    r, e, d, lab, a = p["render"], p["evaluate"], p["defense"], p["lab"], p["attack"]
    n = 13 * r["frames_per_sequence"]
    n_test = n * p["label"]["test_fraction"] if a["max_images"] is None else min(a["max_images"], n)
    eval_frames = e["trajectories"] * e["frames"]
    val_frames = d["val_trajectories"] * e["frames"]
    frac = attacked_fraction(e["p_start"], e["attack_length"])
    det = detector_counts(p)
    lab_frames = len(lab["sequences"]) * lab["frames"]
    counts = {
        "render": {"render": n},
        "train": training_counts(n, p, p["train"]["epochs"]),
        "attack": {"gradient": n_test * len(a["eps"]), "forward": n_test * (1 + 2 * len(a["eps"]))},
        "detect_render": {"render": det["render"]},
        "shap": {"forward": det["shap_forward"], "gradient": det["gradient"]},
        "detect": {"lstm": det["lstm"], "forward": det["squeeze_forward"] + eval_frames},
        "guidance": guidance_counts(p, renders_per_step),
        # evaluation, validation and envelope-validation trajectories; both chains' calibrations read the last two
        "eval_render": {"render": eval_frames + 2 * val_frames},
        "calibrate": {"forward": 2 * 2 * val_frames},
        "evaluate": {"forward": eval_frames * (1 + len(e["eps"])), "gradient": eval_frames * len(e["eps"]) * frac},
        "surrogate": training_counts(n, p, p["robustness"]["surrogate_epochs"]),
        "robustness": {
            "gradient": p["robustness"]["frames"] * robustness_gradients_per_frame(p),
            "forward": p["robustness"]["frames"] * robustness_rows(p),
        },
        "lab": {
            "render": lab_frames,
            "forward": lab_frames * (1 + len(a["eps"])),
            "gradient": lab_frames * len(a["eps"]) * attacked_fraction(e["p_start"], lab["attack_length"]),
        },
    }
    if lab["retrain"] == "always":  # the synthetic-lab sub-pipeline: render, train, shap, detect again
        sub = training_counts(n, p, p["train"]["epochs"])
        counts["lab_models"] = {
            "render": n + det["render"],
            "train": sub["train"],
            "gradient": det["gradient"],
            "forward": sub["forward"] + det["shap_forward"],
            "lstm": det["lstm"],
        }
    return counts


def predict(counts: dict[str, dict[str, float]], seconds: dict[str, float]) -> list[dict[str, Any]]:
    """One row per (stage, unit): count, measured rate (units/s) and predicted seconds = count x s/unit."""
    return [
        {"stage": stage, "unit": unit, "count": count, "rate": 1 / seconds[unit], "seconds": count * seconds[unit]}
        for stage, units in counts.items()
        for unit, count in units.items()
        if count > 0
    ]


def stage_totals(rows: list[dict[str, Any]]) -> dict[str, float]:
    """Predicted seconds per stage (sum over its units), largest first."""
    out: dict[str, float] = {}
    for row in rows:
        out[row["stage"]] = out.get(row["stage"], 0.0) + row["seconds"]
    return dict(sorted(out.items(), key=lambda kv: -kv[1]))


def required_rates(rows: list[dict[str, Any]], budget_s: float) -> dict[str, float]:
    """Units/s each unit must reach for the whole profile to fit in `budget_s`, when every unit gets the
    share of the budget that it has of the predicted time (a uniform speed-up of every unit)."""
    total = sum(r["seconds"] for r in rows)
    per_unit: dict[str, list[float]] = {}
    for r in rows:
        per_unit.setdefault(r["unit"], [0.0, 0.0])
        per_unit[r["unit"]][0] += r["count"]
        per_unit[r["unit"]][1] += r["seconds"]
    return {unit: count / (budget_s * secs / total) for unit, (count, secs) in per_unit.items()}


# ----------------------------------------------------------------------------- measurements
def timed(fn: Callable[[], Any], repeats: int, sync: Callable[[], None]) -> tuple[float, float]:
    """(median wall seconds, mean process CPU seconds) of `repeats` calls after one warm-up."""
    fn()
    sync()
    times = []
    c0 = time.process_time()
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        sync()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), (time.process_time() - c0) / repeats


def per(value: tuple[float, float], n: int) -> tuple[float, float]:
    return value[0] / n, value[1] / n


def measure_torch(device: str, amp: bool, repeats: int, hw: tuple[int, int]) -> dict[str, tuple[float, float]]:
    """(wall, CPU) seconds per unit of the torch units on `device` (width-1 PoseNet at `hw`, small batches)."""
    import torch

    from pipeline.attacks.gradient import fgsm
    from pipeline.pose.loss import PoseLoss
    from pipeline.pose.model import PoseNet

    torch.manual_seed(0)
    sync = torch.cuda.synchronize if device.startswith("cuda") else (lambda: None)
    model = PoseNet(1.0).place(device, amp)
    loss = PoseLoss().to(device)
    opt = torch.optim.Adam([*model.parameters(), *loss.parameters()], lr=1e-5)
    bt, bf = BATCHES["cpu" if device == "cpu" else "cuda"]
    x, y = torch.rand(bf, 3, *hw, device=device), torch.rand(bf, 9, device=device)

    def step() -> None:
        opt.zero_grad()
        loss(model(x[:bt]), y[:bt]).backward()
        opt.step()

    out = {"train": per(timed(step, repeats, sync), bt)}
    model.eval()
    with torch.inference_mode():
        out["forward"] = per(timed(lambda: model(x), repeats, sync), bf)
        out["forward1"] = timed(lambda: model(x[:1]), repeats, sync)
    out["gradient"] = per(timed(lambda: fgsm(model, x[:bt], y[:bt], 0.01, loss), repeats, sync), bt)
    out["lstm"] = measure_lstm(repeats)
    return out


def measure_lstm(repeats: int, n: int = 256) -> tuple[float, float]:
    """(wall, CPU) seconds per sample-epoch of the detector's training (pipeline.detectors.lstm, CPU)."""
    from pipeline.detectors.lstm import LSTMConfig, train_lstm

    rng = np.random.default_rng(0)
    x = rng.normal(size=(n, 9, 1000)).astype(np.float32)
    y = (rng.random(n) < 0.5).astype(np.float32)
    epochs = max(1, repeats)

    def fit() -> Any:
        return train_lstm(
            x[: n * 3 // 4], y[: n * 3 // 4], x[n * 3 // 4 :], y[n * 3 // 4 :], LSTMConfig(), epochs=epochs
        )

    return per(timed(fit, 1, lambda: None), epochs * n)


def measure_render(p: dict[str, Any], repeats: int) -> tuple[float, float]:
    """(wall, CPU) seconds per frame of the Cycles render at the paper size and samples (approach poses)."""
    from pipeline.render.scene import Renderer
    from stages.config.build import intrinsics, scene_settings
    from stages.config.schema import build
    from stages.render import frames

    typed = build(p)
    _, _, R, t = frames(typed)
    idx = np.linspace(0, len(t) - 1, repeats + 1).round().astype(int)
    poses = iter(idx)  # the warm-up and each timed call render a pose of their own
    with Renderer(intrinsics(typed), scene_settings(typed.render)) as r:

        def one() -> None:
            i = next(poses)
            r.render(R[i], t[i])

        return timed(one, repeats, lambda: None)


# ----------------------------------------------------------------------------- report
def renders_per_step() -> tuple[float, str]:
    """Renders per closed-loop step of the last guidance run (reports/metrics/guidance.json), else 1."""
    import json
    from pathlib import Path

    path = Path("reports/metrics/guidance.json")
    if not path.exists():
        return 1.0, "no guidance metrics: every step renders"
    m = json.loads(path.read_text())
    renders, steps = m["renders"] + m["defended"]["renders"], m["steps"] + m["defended"]["steps"]
    return renders / steps, (
        f"{renders / steps:.2f} renders per step, as in the last guidance run "
        f"({m.get('profile', 'default')} profile, reports/metrics/guidance.json)"
    )


def unit_totals(rows: list[dict[str, Any]]) -> dict[str, float]:
    """Count of each unit over all stages."""
    out: dict[str, float] = {}
    for row in rows:
        out[row["unit"]] = out.get(row["unit"], 0.0) + row["count"]
    return out


def _unit_table(rows: list[dict[str, Any]], idle: list[dict[str, Any]]) -> str:
    """Markdown table: per (stage, unit) its count, measured rate (units/s) and both predicted times (h)."""
    from pipeline.report.markdown import markdown_table

    return markdown_table(
        [
            {
                "stage": r["stage"],
                "unit": r["unit"],
                "count": f"{r['count']:,.0f}",
                "measured rate (units/s)": f"{r['rate']:.3g}",
                "predicted time (h)": f"{r['seconds'] / 3600:.2f}",
                "idle-machine estimate (h)": f"{q['seconds'] / 3600:.2f}",
            }
            for r, q in zip(rows, idle)
        ]
    )


def _stage_table(totals: dict[str, float], idle_totals: dict[str, float], total: float) -> str:
    """Markdown table: per stage its predicted times (h) and share of the measured `total` (s)."""
    from pipeline.report.markdown import markdown_table

    return markdown_table(
        [
            {
                "stage": k,
                "predicted time (h)": f"{v / 3600:.1f}",
                "idle-machine estimate (h)": f"{idle_totals[k] / 3600:.1f}",
                "share": f"{v / total:.1%}",
            }
            for k, v in totals.items()
        ]
    )


def _requirement_table(rows: list[dict[str, Any]], idle: list[dict[str, Any]], rate: dict[str, float]) -> str:
    """Markdown table: per unit its count, idle-machine `rate` here and the rates (units/s) the 2-hour target
    requires (alone, and at its share of the idle prediction)."""
    from pipeline.report.markdown import markdown_table

    need = required_rates(idle, TARGET_S)
    return markdown_table(
        [
            {
                "unit": u,
                "what": UNITS[u],
                "count": f"{n:,.0f}",
                "idle-machine rate here (units/s)": f"{rate[u]:.3g}",
                "REQUIRED floor: alone in 2 h (units/s)": f"{n / TARGET_S:.3g}",
                "REQUIRED at its share of 2 h (units/s)": f"{need[u]:.3g}",
            }
            for u, n in unit_totals(rows).items()
        ]
    )


def _notes(rows: list[dict[str, Any]], total: float, facts: dict[str, Any]) -> tuple[str, str, str]:
    """(what dominates the measured `total` (s), the note on a given Cycles rate, the note on the GPU path)."""
    rendering = sum(r["seconds"] for r in rows if r["unit"] == "render")
    dominant = (
        f"The Cycles renders dominate ({rendering / 3600:,.1f} h); every torch unit together takes "
        f"{(total - rendering) / 3600:,.2f} h."
        if rendering > total / 2
        else f"Three trainings of the width-1 network at 480x270 (train, surrogate and the synthetic-lab retraining "
        f"of lab_models, 50 epochs each) and the robustness stage's "
        f"{robustness_gradients_per_frame(facts['params']):.0f} input gradients per held-out frame dominate."
    )
    given = facts["render_given"]
    render_note = (
        ""
        if given is None
        else f" The Cycles frame was not rendered here (this Python has no bpy): its rate, {given:g} frames/s at "
        f"{facts['render_threads']} threads, is given (--render-rate), as measured on the 2-core CPU machine."
    )
    gpu_note = (
        f"The torch units above ran on {facts['gpu']} (CUDA, bf16 autocast, channels_last); the LSTM's "
        f"training runs on the CPU."
        if facts["gpu"]
        else "The CUDA path of the torch stages is written (device param, bf16 autocast, channels_last, pinned "
        "uint8 batches, NCCL under torchrun); its rates are measured with `--device cuda` on a GPU box "
        '(section "Paper-profile cost model on a GPU", when one was run).'
    )
    return dominant, render_note, gpu_note


def body(rows: list[dict[str, Any]], idle: list[dict[str, Any]], facts: dict[str, Any]) -> str:
    """The Markdown of the `## Paper-profile cost model` section: `rows` predicted from the measured wall
    rates, `idle` from the CPU time per unit over the threads (what an otherwise idle machine would take)."""
    totals, idle_totals = stage_totals(rows), stage_totals(idle)
    total, idle_total = sum(totals.values()), sum(idle_totals.values())
    table = _unit_table(rows, idle)
    stages = _stage_table(totals, idle_totals, total)
    rate = {r["unit"]: r["rate"] for r in idle}
    req = _requirement_table(rows, idle, rate)
    top = ", ".join(f"{k} {v / total:.0%}" for k, v in list(totals.items())[:4])
    renders = unit_totals(rows)["render"]
    on = f"one {facts['gpu']} and " if facts["gpu"] else ""
    dominant, render_note, gpu_note = _notes(rows, total, facts)
    return (
        f"`benchmarks/cost_model.py --device {facts['device']}` on {on}{platform.machine()}, "
        f"{os.cpu_count()} cores, torch {facts['torch']}, {facts['threads']} threads, AMP "
        f"{'bf16' if facts['amp'] else 'off (CPU)'}; median of {facts['repeats']} repeats after a warm-up per "
        f"unit (training and gradients at batch {facts['batches'][0]}, batched forwards at batch "
        f"{facts['batches'][1]}: small batches keep the measurement to seconds); load average "
        f"{facts['load'][0]:.1f} at the start, {facts['load'][1]:.1f} at the end (other jobs were not "
        f"stopped, so the wall rates are pessimistic; the idle-machine estimate is CPU time per unit over the "
        f"threads). Counts from conf/config.yaml + conf/profile/paper.yaml (`paper_counts`); guidance: "
        f"{facts['rps_note']}; detect: every one of detect.epochs (early stopping ends sooner: an upper "
        f"bound); evaluate and lab: the expected attacked fraction of the schedule. Label and report are "
        f"left out (seconds).{render_note}\n\n{table}\n"
        f"Predicted per stage on this machine: **{total / 3600:,.0f} h** as measured, **{idle_total / 3600:,.0f} "
        f"h** idle (largest: {top}). {dominant}\n\n"
        f"{stages}\n"
        f"**Requirement, not a measurement.** The target is the paper profile end to end in under 2 h "
        f"on one H100-class GPU with {TARGET_CORES} cores: {idle_total / TARGET_S:,.0f}x this machine's idle "
        f"estimate. The floor is the rate a unit needs even if it had the whole 2 h; at its share, every unit "
        f"keeps the share of the time it has here:\n\n{req}\n"
        f"Rendering stays on the CPU (Cycles, pipeline/render/scene.py): at {TARGET_CORES} instead of "
        f"{facts['render_threads']} threads, with linear scaling, the {renders:,.0f} renders would take "
        f"{renders / (rate['render'] * TARGET_CORES / facts['render_threads']) / 60:.0f} min of the 120, so the "
        f"target also needs Cycles on the GPU or more render machines (Ray). {gpu_note}"
    )


def main() -> None:
    import torch

    from stages.config import params as params_mod
    from stages.report import write_benchmark

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu", help="cpu, cuda or cuda:N (torch units; rendering is Cycles on the CPU)")
    ap.add_argument("--repeats", type=int, default=2, help="timed repeats per unit (after one warm-up)")
    ap.add_argument("--threads", type=int, default=os.cpu_count() or 1, help="torch CPU threads")
    ap.add_argument(
        "--render-rate",
        type=float,
        default=None,
        help="frames/s of the 480x270 Cycles frame measured elsewhere (where this Python has no bpy)",
    )
    ap.add_argument("--no-write", action="store_true", help="print only; leave reports/benchmarks.md alone")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    p = params_mod.compose("paper")
    load0 = os.getloadavg()[0]
    amp = args.device.startswith("cuda")
    measured = measure_torch(args.device, amp, args.repeats, (p["render"]["height"], p["render"]["width"]))
    threads = {u: args.threads for u in measured} | {"render": p["render"]["threads"]}
    if args.render_rate is None:
        measured["render"] = measure_render(p, args.repeats)
    elif not args.render_rate > 0:
        raise SystemExit(f"--render-rate must be frames/s > 0, got {args.render_rate}")
    else:  # wall and CPU of an idle machine at render.threads
        measured["render"] = (1 / args.render_rate, threads["render"] / args.render_rate)
    rps, note = renders_per_step()
    counts = paper_counts(p, rps)
    rows = predict(counts, {u: wall for u, (wall, _) in measured.items()})
    idle = rows if amp else predict(counts, {u: cpu / threads[u] for u, (_, cpu) in measured.items()})
    facts = {
        "device": args.device,
        "torch": torch.__version__,
        "threads": args.threads,
        "amp": amp,
        "repeats": args.repeats,
        "batches": BATCHES["cpu" if args.device == "cpu" else "cuda"],
        "load": (load0, os.getloadavg()[0]),
        "rps_note": note,
        "params": p,
        "render_threads": threads["render"],
        "render_given": args.render_rate,
        "gpu": torch.cuda.get_device_name(args.device) if args.device.startswith("cuda") else None,
    }
    text = body(rows, idle, facts)
    print(text)
    section = "Paper-profile cost model" + (" on a GPU" if facts["gpu"] else "")
    if not args.no_write:
        print(f"-> {write_benchmark(section, text)} (## {section})")


if __name__ == "__main__":
    main()
