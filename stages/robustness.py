"""`rpod robustness`: the shipped safety chain against attacks its detector never saw (SPEC 11).

Reads models/pose.pt, models/detector.pt, models/surrogate.pt (`rpod train --surrogate`) and a
seeded sample of `robustness.frames` held-out test frames; every attacked image is stored as 8-bit
(`pipeline.attacks.quantize`) before it goes through the chain, as in the other stages. Rows:
- seen: FGSM on the training loss at robustness.eps (the attack the detector was trained on);
- transfer: FGSM at robustness.unseen_eps, and robustness.transfer (pgd, mifgsm, fgsm/position,
  fgsm/rotation: method[/loss]) at robustness.eps;
- adaptive: L-inf PGD on pose_loss - lambda * detector logit (pipeline.adaptive) per lambda and eps,
  plus the per-frame worst case over lambda;
- surrogate: robustness.surrogate attacks crafted on the surrogate pose model, evaluated on ours;
- corruptions (not attacks): robustness.corruptions at camera-realistic strengths.
Writes reports/robustness.md, reports/metrics/robustness.json, reports/figures/robustness.png.
"""
from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

from stages import params as params_mod
from stages.io import StageError, atomic_write_text, file_hash, write_metrics

MODEL = Path("models/pose.pt")
SURROGATE = Path("models/surrogate.pt")
REPORT = Path("reports/robustness.md")
METRICS = Path("reports/metrics/robustness.json")
FIGURE = Path("reports/figures/robustness.png")
SEED_OFFSET = 1500
TARGET = ["tx", "ty", "tz", "r0", "r1", "r2", "r3", "r4", "r5"]


def parse_attack(name: str, where: str) -> tuple[str, str | None]:
    """`method[/loss]` -> (method, loss or None = attack.loss), refusing unknown names."""
    from pipeline.attacks import ATTACKS, LOSSES

    method, _, loss = str(name).partition("/")
    if method not in ATTACKS or (loss and loss not in LOSSES):
        raise StageError(f"params.yaml {where}: unknown attack {name!r}; use method[/loss] with method one of "
                         f"{', '.join(ATTACKS)} and loss one of {', '.join(LOSSES)}")
    return method, loss or None


def check_params(r: dict[str, Any]) -> None:
    """One clear error per bad robustness parameter, before any work."""
    from pipeline.adaptive import DEFAULT_STEPS, check_lambdas
    from pipeline.attacks import check_eps
    from pipeline.corruptions import check_strength

    for key in ("eps", "unseen_eps"):
        if not isinstance(r[key], list) or not r[key]:
            raise StageError(f"params.yaml robustness.{key} must be a non-empty list of values in (0, 1]")
        for e in r[key]:
            try:
                check_eps(e)
            except (TypeError, ValueError):
                raise StageError(f"params.yaml robustness.{key}: {e!r} is not in (0, 1] (pixels are in [0, 1])") from None
    try:
        check_lambdas(r["lambdas"])
    except (TypeError, ValueError):
        raise StageError(f"params.yaml robustness.lambdas must be a non-empty list of finite values >= 0, "
                         f"got {r['lambdas']}") from None
    for key in ("transfer", "surrogate_attacks"):
        for name in r[key]:
            parse_attack(name, f"robustness.{key}")
    if int(r["steps"]) < DEFAULT_STEPS:
        raise StageError(f"params.yaml robustness.steps must be >= {DEFAULT_STEPS} (an adaptive attack with fewer "
                         f"steps understates the attacker), got {r['steps']}")
    if not float(r["harm_m"]) > 0:
        raise StageError(f"params.yaml robustness.harm_m must be a positive distance in metres, got {r['harm_m']}")
    if int(r["frames"]) < 1 or int(r["batch_size"]) < 1:
        raise StageError(f"params.yaml robustness.frames and robustness.batch_size must be >= 1, "
                         f"got {r['frames']} and {r['batch_size']}")
    if not isinstance(r["corruptions"], dict):
        raise StageError("params.yaml robustness.corruptions must map a corruption name to a list of strengths")
    for name, strengths in r["corruptions"].items():
        for s in strengths:
            try:
                check_strength(name, s)
            except (TypeError, ValueError) as e:
                raise StageError(f"params.yaml robustness.corruptions.{name}: {e}") from None


def main() -> None:
    """Run every attack and corruption row on held-out test frames; write the report, metrics and figure."""
    import torch
    from tqdm import tqdm

    from pipeline.adaptive import ShapChain, adaptive_pgd
    from pipeline.attacks import attack_loss, get_attack, quantize
    from pipeline.chain import SafetyChain, run_sequence
    from pipeline.corruptions import corrupt
    from pipeline.robustness import attack_row, corruption_row, worst_by_eps, worst_over_lambda
    from pipeline.training import pose_errors
    from pipeline.stats import rate
    from stages.checkpoint import load_pose_loss, load_pose_model, read_pose
    from stages.data import load_split
    from stages.detect import load_detector  # moves to stages/artifacts.py (arch branch)

    p = params_mod.load()
    r, a = p["robustness"], p["attack"]
    check_params(r)
    if not SURROGATE.exists():
        raise StageError(f"{SURROGATE} not found: run `rpod train --surrogate` (dvc repro surrogate) first")
    torch.set_num_threads(2)
    seed = int(p["seed"]) + SEED_OFFSET
    harm, batch, steps = float(r["harm_m"]), int(r["batch_size"]), int(r["steps"])
    eps_list = [float(e) for e in r["eps"]]
    lambdas = [float(v) for v in r["lambdas"]]

    model = load_pose_model(MODEL, p)
    model_hash = file_hash(MODEL)
    detector, ckpt = load_detector(model_hash=model_hash)
    try:
        chain = SafetyChain.from_model(model, np.asarray(ckpt["background_mean"]), detector,
                                       threshold=float(ckpt["threshold"]))
    except ValueError as err:
        raise StageError(f"{MODEL}: {err}") from None
    target = ShapChain(model, chain.weight, chain.background_mean, detector)
    pose_loss = load_pose_loss(MODEL, p)
    surrogate = load_pose_model(SURROGATE, p)
    surrogate_meta = read_pose(SURROGATE)["meta"]
    surrogate_loss = load_pose_loss(SURROGATE, p)

    split = load_split(p, "test")
    n = min(int(r["frames"]), len(split))
    pick = np.sort(np.random.default_rng(seed).choice(len(split), n, replace=False))
    images = np.stack([np.asarray(split.images[int(i)]) for i in pick])
    targets = split.labels[TARGET].to_numpy(np.float32)[pick]

    def cost(method: str) -> int:
        """Gradient evaluations per frame: PGD takes robustness.steps (it is the adaptive attack at
        lambda = 0), MI-FGSM attack.steps as in the attack stage, FGSM one."""
        return {"fgsm": 1, "pgd": steps}.get(method, int(a["steps"]))

    def gen(k: int) -> torch.Generator:
        return torch.Generator().manual_seed(seed + k)

    def bound(method: str, loss: str | None, k: int, net: Any, pl: Any, eps: float) -> Callable[[Any, Any], Any]:
        fn = get_attack(method, steps=cost(method), step_size=None, random_start=True,
                        momentum=float(a["momentum"]), generator=gen(k))
        lf = attack_loss(loss or a["loss"], pl)
        return lambda x, y: fn(net, x, y, eps, lf)

    # (attack, group, eps, lambda or None, x, y -> float adversarial images, gradients per frame); PGD at
    # eps index i uses seed + 100 + i, so plain PGD and the adaptive attack at lambda = 0 are one run
    pgd_is_adaptive = "pgd" in r["transfer"] and 0.0 in lambdas
    specs: list[tuple[str, str, float, float | None, Callable[[Any, Any], Any], int]] = []
    for e in eps_list:
        specs.append(("fgsm", "seen", e, None, bound("fgsm", None, 0, model, pose_loss, e), 1))
    for e in (float(v) for v in r["unseen_eps"]):
        specs.append(("fgsm", "transfer", e, None, bound("fgsm", None, 0, model, pose_loss, e), 1))
    for j, name in enumerate(r["transfer"]):
        method, loss = parse_attack(name, "robustness.transfer")
        for i, e in enumerate(eps_list):
            if name == "pgd" and pgd_is_adaptive:
                continue
            k = 100 + i if name == "pgd" else 200 + 10 * j + i
            specs.append((name, "transfer", e, None, bound(method, loss, k, model, pose_loss, e), cost(method)))
    full = attack_loss(a["loss"], pose_loss)
    for i, e in enumerate(eps_list):
        for lam in lambdas:
            specs.append(("adaptive pgd", "adaptive", e, lam,
                          lambda x, y, e=e, lam=lam, g=gen(100 + i): adaptive_pgd(target, x, y, e, full, lam,
                                                                                  steps=steps, generator=g),
                          steps))
    for j, name in enumerate(r["surrogate_attacks"]):
        method, loss = parse_attack(name, "robustness.surrogate_attacks")
        for i, e in enumerate(eps_list):
            specs.append((f"surrogate {name}", "surrogate", e, None,
                          bound(method, loss, 500 + 10 * j + i, surrogate, surrogate_loss, e), cost(method)))

    n_corr = sum(len(v) for v in r["corruptions"].values())
    total = -(-n // batch) * (len(specs) + n_corr + 1)
    bar = tqdm(total=total, desc="robustness", unit="batch", dynamic_ncols=True)

    def progress(it: Any) -> Any:
        for item in it:
            yield item
            bar.update(1)

    def stored(craft: Callable[[Any, Any], Any]) -> Callable[[Any, Any], Any]:
        return lambda x, y: quantize(craft(x, y), x).float() / 255.0

    t0 = time.perf_counter()
    attacked, none = np.ones(n, bool), np.zeros(n, bool)
    rows: list[dict[str, Any]] = []
    per_lambda: dict[float, list[tuple[np.ndarray, np.ndarray]]] = {e: [] for e in eps_list}
    for name, group, e, lam, craft, _ in specs:
        res = run_sequence(chain, images, targets, attacked, stored(craft), batch, progress)
        pos = pose_errors(res.pose, targets)[0]
        rows.append(attack_row(name, group, e, pos, res.flag, harm, lam))
        if group == "adaptive":
            per_lambda[e].append((pos, res.flag))
            if lam == 0.0 and pgd_is_adaptive:
                rows.append(attack_row("pgd", "transfer", e, pos, res.flag, harm))
    for e in eps_list:
        pos, flag, _ = worst_over_lambda([v[0] for v in per_lambda[e]], [v[1] for v in per_lambda[e]], harm)
        rows.append(attack_row("adaptive pgd, worst over lambda", "adaptive", e, pos, flag, harm))

    clean = run_sequence(chain, images, targets, none, None, batch, progress)
    clean_pos = pose_errors(clean.pose, targets)[0]
    clean_harm = rate(clean_pos > harm)
    corruptions = [corruption_row("none", 0.0, clean_pos, clean.flag)]
    for name, strengths in r["corruptions"].items():
        for s in strengths:
            bad = corrupt(name, s, seed)(images)
            res = run_sequence(chain, bad, targets, none, None, batch, progress)
            corruptions.append(corruption_row(name, s, pose_errors(res.pose, targets)[0], res.flag))
    bar.close()
    seconds = time.perf_counter() - t0

    order = {"seen": 0, "transfer": 1, "adaptive": 2, "surrogate": 3}
    rows.sort(key=lambda row: order[row["group"]])
    metrics = {"rows": rows, "corruptions": corruptions, "frames": n, "test_frames": len(split), "harm_m": harm,
               "steps": steps, "gradients_per_frame": sum(spec[-1] for spec in specs), "lambdas": lambdas,
               "eps": eps_list, "threshold": float(ckpt["threshold"]),
               "clean_harmful_rate": clean_harm.value, "ci95_clean_harmful": clean_harm.ci(),
               "surrogate": {"best_epoch": int(surrogate_meta.get("epoch", 0)),
                             "test_position_m": float(surrogate_meta.get("test_pos_m", float("nan")))},
               "model_hash": model_hash, "surrogate_hash": file_hash(SURROGATE), "seconds": seconds,
               "worst_harmful_undetected": worst_by_eps(rows)}
    write_metrics(METRICS, metrics, p)
    atomic_write_text(REPORT, report(metrics, p))
    save_figure(rows)
    print(f"robustness: {len(rows)} attack rows and {len(corruptions)} corruption rows on {n} test frames in "
          f"{seconds:.0f} s -> {REPORT}, {METRICS}, {FIGURE}")


def save_figure(rows: list[dict[str, Any]]) -> None:
    """reports/figures/robustness.png, written atomically."""
    from pipeline.figures import robustness_vs_eps

    FIGURE.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=FIGURE.parent, prefix=f".{FIGURE.name}.", suffix=".png")
    os.close(fd)
    try:
        robustness_vs_eps([row for row in rows if row["attack"] != "adaptive pgd"]).savefig(tmp, dpi=110)
        os.replace(tmp, FIGURE)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _pct(value: float, ci: list[float | None]) -> str:
    return f"{100 * value:.1f} [{100 * ci[0]:.1f}, {100 * ci[1]:.1f}]"


def _table(rows: list[dict[str, Any]], with_lambda: bool = False) -> str:
    from pipeline.report import markdown_table

    out = []
    for row in rows:
        cells = {"attack": row["attack"], "eps": f"{row['eps']:g}"}
        if with_lambda:
            cells["lambda"] = "-" if row["lambda"] is None else f"{row['lambda']:g}"
        cells |= {"frames": row["n"], "detected (%)": _pct(row["detection_rate"], row["ci95_detection"]),
                  "harmful and undetected (%)": _pct(row["harmful_undetected_rate"], row["ci95_harmful_undetected"]),
                  "position error > harm (%)": _pct(row["harmful_rate"], row["ci95_harmful"]),
                  "mean position error (m)": row["position_error_m"]}
        out.append(cells)
    return markdown_table(out, decimals=2)


def _meaning(rows: list[dict[str, Any]], what: str) -> str:
    """One sentence on the worst row of a section, for a mission planner ("" for an empty section)."""
    if not rows:
        return ""
    w = max(rows, key=lambda row: row["harmful_undetected_rate"])
    hu = 100 * w["harmful_undetected_rate"]
    verdict = ("so the chain would let this attacker steer the chaser unnoticed on a large share of frames"
               if hu >= 10 else "so the chain still catches or shrugs off nearly every harmful frame"
               if hu < 2 else "so a mission would see occasional harmful, unflagged estimates")
    return (f"For a mission: against {what} the worst case is {w['attack']} at eps {w['eps']:g}"
            + (f" (lambda {w['lambda']:g})" if w["lambda"] is not None else "")
            + f", which leaves {hu:.1f}% of frames harmful and undetected, {verdict}.")


def report(m: dict[str, Any], p: dict[str, Any]) -> str:
    """reports/robustness.md: results only (no times)."""
    from pipeline.report import markdown_table
    from pipeline.stats import wilson

    r = p["robustness"]
    rows = m["rows"]
    groups = {g: [row for row in rows if row["group"] == g] for g in ("seen", "transfer", "adaptive", "surrogate")}
    mid = wilson(m["frames"] // 2, m["frames"])
    half = 100 * (mid.hi - mid.lo) / 2
    corr = [{"corruption": c["corruption"], "strength": "-" if c["corruption"] == "none" else f"{c['strength']:g}",
             "frames": c["n"], "false alarms (%)": _pct(c["false_alarm_rate"], c["ci95_false_alarm"]),
             "mean position error (m)": c["position_error_m"]} for c in m["corruptions"]]
    worst_fa = max(m["corruptions"][1:], key=lambda c: c["false_alarm_rate"], default=m["corruptions"][0])
    base = m["corruptions"][0]
    worst_lines = "\n".join(f"- eps {k}: {100 * v['harmful_undetected_rate']:.1f} "
                            f"[{100 * v['ci95_harmful_undetected'][0]:.1f}, {100 * v['ci95_harmful_undetected'][1]:.1f}]% "
                            f"({v['attack']}" + (f", lambda {v['lambda']:g}" if v["lambda"] is not None else "") + ")"
                            for k, v in sorted(m["worst_harmful_undetected"].items(), key=lambda kv: -float(kv[0])))
    return f"""# Robustness of the safety chain (`rpod robustness`)

The shipped chain (pose network -> closed-form SHAP -> LSTM detector, threshold {m['threshold']:.3f} from
validation) on **{m['frames']} held-out test frames** (a seeded sample of the {m['test_frames']} test frames;
every attacked image is stored as 8-bit before the chain reads it). The safety number is the
**harmful-undetected rate**: attacked frames whose position error exceeds **{m['harm_m']:g} m** and that the
chain did not flag. Without any attack, {_pct(m['clean_harmful_rate'], m['ci95_clean_harmful'])}% of these
frames already exceed {m['harm_m']:g} m: that share of every harmful rate below is the pose model's own
error, not the attack's.
Rates are percent with 95% Wilson intervals [lo, hi]; with {m['frames']} frames
(`robustness.frames`) a rate near 50% is known to +-{half:.1f} points, a rate near 0 or 100% much more
tightly. At the default profile the frame count is set by the stage's budget of about 3 minutes on the
2-core CPU: each frame costs {m['gradients_per_frame']} gradient evaluations (every iterative attack takes
{m['steps']} steps, for every eps and lambda), and +-5 points at a 50% rate would need 385 frames.
PGD (plain, adaptive and on the surrogate) takes {m['steps']} steps of 2.5 eps / steps from a random
start; MI-FGSM takes `attack.steps` = {p['attack']['steps']} steps of eps / steps (momentum {p['attack']['momentum']:g}).

Worst harmful-undetected rate over the attacks run at each eps:

{worst_lines}

## The attack the detector was trained on (reference)

FGSM on the training loss at the detector's own eps values.

{_table(groups['seen'])}
{_meaning(groups['seen'], 'the training attack')}

## Transfer to unseen attacks

FGSM at eps the detector never saw ({', '.join(f'{e:g}' for e in r['unseen_eps'])}); PGD and MI-FGSM; FGSM on the
position-only and the rotation-only loss (`method/loss`).

{_table(groups['transfer'])}
{_meaning(groups['transfer'], 'attacks the detector never saw')}

## Adaptive white-box attack

L-inf PGD, {m['steps']} steps, random start, on `pose_loss - lambda * detector_logit` through the whole chain
(pose network, exact SHAP, LSTM: `pipeline/adaptive.py`), for lambda in {', '.join(f'{v:g}' for v in m['lambdas'])}.
lambda = 0 is plain PGD on the same seed (one run, also the `pgd` transfer row). "worst over lambda"
is the attacker who tries every lambda and keeps, per frame, a harmful unflagged image when one
exists, else an unflagged one, else the one with the largest error.

{_table(groups['adaptive'], with_lambda=True)}
{_meaning(groups['adaptive'], 'an attacker who knows the detector')}

## Transfer from a surrogate model (black box)

Attacks crafted on a second pose model trained with seed {r['surrogate_seed']} for at most {r['surrogate_epochs']} epochs
(`rpod train --surrogate`; best epoch {m['surrogate']['best_epoch']}, test position error
{m['surrogate']['test_position_m']:.2f} m): fewer epochs than ours to fit the CPU budget, so a weaker
surrogate than a real attacker would train. Evaluated on our chain.

{_table(groups['surrogate'])}
{_meaning(groups['surrogate'], 'an attacker who cannot read our weights')}

## Benign corruptions (must not be flagged)

Units: noise = standard deviation in [0, 1] pixel units; blur = Gaussian sigma in pixels; jpeg =
quality; brightness = gain; contrast = factor around the frame's mean grey level.

{markdown_table(corr, decimals=2)}
For a mission: the clean false-alarm rate is {100 * base['false_alarm_rate']:.1f}%, and the worst corruption
({worst_fa['corruption']} {worst_fa['strength']:g}) raises it to {100 * worst_fa['false_alarm_rate']:.1f}% with a mean position
error of {worst_fa['position_error_m']:.2f} m; every false alarm there would interrupt the approach for an image that is
not attacked.

![detection and harmful-undetected rate against eps, 95% Wilson intervals; the adaptive attack as its worst case over lambda](figures/robustness.png)
"""
