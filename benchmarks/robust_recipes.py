"""Robust-training recipes (issue 37, item 3) and the ablation rows, under the lean attack suite, on black and
Earth backgrounds: what `rpod train --robust` should run.

The committed render is black only, so Earth-background versions of seeded frames are rendered here
(`render`: the same draw a render with `render.background.share` > 0 gives those frames; settings EARTH) of the
fit split (FIT_FRAMES), every validation frame and TEST_FRAMES test frames. A candidate (`train NAME`: a
preset of RECIPES) is the robust stage's recipe (the standard model fine-tuned behind the clamp, its seeds,
schedule and validation split) with overrides of train.adversarial, on the fit split with its FIT_FRAMES Earth
renders swapped in (23%; or a recipe's `earth_share`, with the MORE_FIT_FRAMES renders) and EARTH_SHARE of the
validation frames it selects its checkpoint on. The ablation of the committed recipe is three presets of it on
the same frames: `neither` (fine-tuned clean, no clamp), `clamp-only` (no attacks) and `adversarial-only` (no
clamp), beside `today+earth` (both). `eval NAME`
runs the LEAN suite (pipeline.attacks.strongest) on a seeded sample of validation (choosing) or test (reporting)
frames, each frame black and over its Earth background (pipeline.pose.ablation.ablation_rows: rows per
background kind: black, space = stars and the sensor's offset and noise, earth = the sunlit Earth in view), plus
the clean errors of the whole black split. `table [NAME ...] [--section TITLE]` writes a section of
reports/benchmarks.md (default `## Robust training recipes`) from the stored evaluations of those recipes (all).
Files go to datasets/robust_recipes/ (ignored by git).

    .venv/bin/python benchmarks/robust_recipes.py render
    .venv/bin/python benchmarks/robust_recipes.py train c4 && .venv/bin/python benchmarks/robust_recipes.py eval c4
    .venv/bin/python benchmarks/robust_recipes.py table
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

# before torch loads (as stages/cli.py does): spinning OpenMP threads are many times slower on a shared machine
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402
import torch  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from pipeline.attacks.strongest import LEAN  # noqa: E402
from pipeline.pose.ablation import ablation_rows  # noqa: E402
from pipeline.pose.robustness import sample_rows  # noqa: E402
from pipeline.seeds import seed_for  # noqa: E402
from stages.artifacts import data  # noqa: E402
from stages.config import params as params_mod  # noqa: E402

OUT = ROOT / "datasets" / "robust_recipes"
EARTH = {"share": 1.0, "stars": 0.05, "star_peak": 0.6, "black_offset": 0.02, "noise_std": 0.01}
FIT_FRAMES, TEST_FRAMES, PICK_SEED, MORE_PICK_SEED = 640, 256, 37, 38
MORE_FIT_FRAMES = 764  # more fit frames (other seed), so that half the fit split can be swapped (640 + 764)
EARTH_SHARE = 0.25
EPS = (0.01, 0.05, 0.1)
PAST_CLAMP = {"start": "lift", "bpda": True, "eps": 0.1}
# name -> (overrides of train.adversarial, options: black_level (None: the params'), clean (no attack), earth_share)
RECIPES: dict[str, tuple[dict[str, Any], dict[str, Any]]] = {
    "today+earth": ({}, {}),  # the committed recipe (params.yaml), on the Earth-swapped frames: clamp and attacks
    # the ablation of the committed recipe, same frames, epochs and schedule: what the clamp and the attacks each buy
    "neither": ({}, {"clean": True, "black_level": 0.0}),
    "clamp-only": ({}, {"clean": True}),
    "adversarial-only": ({}, {"black_level": 0.0}),
    "c1": ({**PAST_CLAMP, "objectives": ["position", "attitude"], "attacked_rotation": True}, {}),
    "c2": ({**PAST_CLAMP, "eps": 0.05, "objectives": ["position", "attitude"], "attacked_rotation": True}, {}),
    "c4": (
        {**PAST_CLAMP, "objectives": ["position", "attitude"], "objective_eps": [0.1, 0.02], "attacked_rotation": True},
        {},
    ),
    "c5": ({**PAST_CLAMP, "objectives": ["position"]}, {}),
    "c7": (
        {**PAST_CLAMP, "objectives": ["position", "attitude"], "objective_eps": [0.1, 0.02], "attacked_rotation": True},
        {"earth_share": 0.5},
    ),
    "c6": (
        {
            **PAST_CLAMP,
            "objectives": ["position", "attitude"],
            "objective_eps": [0.1, 0.03],
            "attacked_rotation": True,
            "trades": 0.3,
        },
        {},
    ),
}


def _earth_frames(p: Any) -> dict[str, np.ndarray]:
    """The stored Earth renders: {set}_index (render indices), {set}_images uint8, {set}_kind, set in fit, val, test."""
    path = OUT / "earth.npz"
    if not path.exists():
        raise SystemExit(f"{path} not found: run `benchmarks/robust_recipes.py render` first")
    return dict(np.load(path))


def render(p: Any) -> None:
    """Earth-background versions of FIT_FRAMES seeded fit frames, every validation frame, TEST_FRAMES test frames."""
    from pipeline.geometry.trajectories import flatten
    from pipeline.render.backgrounds import draw, kind
    from pipeline.render.scene import Renderer
    from pipeline.render.settings import BackgroundSettings
    from stages.config.build import intrinsics, scene_settings
    from stages.render import sequences

    K, bg = intrinsics(p), BackgroundSettings(**EARTH)
    scene = dataclasses.replace(scene_settings(p.render), background=bg)
    seqs = sequences(p)
    _, _, R, t = flatten(seqs)
    R_cam, seed = np.concatenate([s.R_cam for s in seqs]), seed_for(p.seed, "render")
    fit, val = data.fit_and_validation_splits(p, seed_for(p.seed, "train"))
    test = data.load_split(p, "test")
    rng = np.random.default_rng(PICK_SEED)
    picks = {
        "fit": np.sort(rng.choice(fit.labels["index"].to_numpy(), FIT_FRAMES, replace=False)),
        "val": np.sort(val.labels["index"].to_numpy()),
        "test": np.sort(rng.choice(test.labels["index"].to_numpy(), TEST_FRAMES, replace=False)),
    }
    rest = np.setdiff1d(fit.labels["index"].to_numpy(), picks["fit"])
    picks["fit_more"] = np.sort(np.random.default_rng(MORE_PICK_SEED).choice(rest, MORE_FIT_FRAMES, replace=False))
    sun, out, t0 = np.asarray(scene.sun_direction, np.float64), {}, time.perf_counter()
    with Renderer(K, scene) as renderer:
        for name, index in picks.items():
            draws = [draw(bg, R_cam[k], seed, int(k)) for k in index]
            out[f"{name}_index"] = index
            out[f"{name}_kind"] = np.array([kind(K, bg, d, R[k] @ sun) for d, k in zip(draws, index)])
            out[f"{name}_images"] = np.stack([renderer.render(R[k], t[k], d) for d, k in zip(draws, index)])
            print(f"{name}: {len(index)} frames, {time.perf_counter() - t0:.0f} s", flush=True)
    OUT.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(OUT / "earth.npz", **out)


def _swapped(split: Any, earth: dict[str, np.ndarray], keys: tuple[str, ...], share: float, seed: int) -> np.ndarray:
    """The split's images with a seeded `share` of its frames swapped for their Earth renders: those of the first
    set of `keys` (a seeded choice when there are more), then a seeded choice of the next set's."""
    images, index = np.array(split.images), split.labels["index"].to_numpy()
    left = int(round(share * len(index)))
    for k, key in enumerate(keys):
        where = {int(f): i for i, f in enumerate(earth[f"{key}_index"])}
        have = np.flatnonzero([int(f) in where for f in index])
        n = min(len(have), left)
        for i in np.random.default_rng(seed + k).choice(have, n, replace=False) if n else []:
            images[i] = earth[f"{key}_images"][where[int(index[i])]]
        left -= n
    return images


def train(p: Any, name: str) -> None:
    """The robust stage's recipe with the preset's overrides, on the fit split with EARTH_SHARE Earth frames."""
    from pipeline.pose.adversarial import Adversary
    from pipeline.pose.loss import PoseLoss
    from pipeline.pose.model import PoseNet
    from pipeline.pose.train import fit, make_deterministic
    from stages.artifacts.models import load_pose
    from stages.config.build import adversarial_config, robust_train_config

    overrides, options = RECIPES[name]
    adv = dataclasses.replace(p.train.adversarial, **overrides)
    level = float(adv.black_level if options.get("black_level") is None else options["black_level"])
    cfg = robust_train_config(p.train, seed_for(p.seed, "robust"))
    make_deterministic(cfg.seed)
    model, loss = PoseNet(float(p.train.width), float(p.train.dropout), level), PoseLoss("mean")
    train_set, val_set = _datasets(p, options, cfg.seed)
    standard = load_pose(p)
    model.load_state_dict(standard.model.state_dict())
    loss.load_state_dict(standard.loss.state_dict())
    adversary = (
        None
        if options.get("clean")
        else Adversary(adversarial_config(adv), loss, len(train_set) // cfg.batch_size, cfg.seed)
    )
    t0, c0 = time.perf_counter(), time.process_time()
    result = fit(
        model,
        loss,
        train_set,
        val_set,
        cfg,
        "cpu",
        progress=False,
        adversary=adversary,
        on_epoch=lambda s, best, net: print(
            f"{name} epoch {s.epoch}: val {s.val_pos_m:.3f} m "
            f"{s.val_att_deg:.2f} deg, attacked {s.val_adv_pos_m:.2f} m "
            f"{s.val_adv_att_deg:.2f} deg, {s.seconds:.0f} s"
            f"{' *' if best else ''}",
            flush=True,
        ),
    )
    OUT.mkdir(parents=True, exist_ok=True)
    torch.save(
        {
            "state": result.best_state,
            "black_level": level,
            "best_epoch": result.best_epoch,
            "wall_s": time.perf_counter() - t0,
            "cpu_s": time.process_time() - c0,
            "epoch_s": [s.seconds for s in result.history],
        },
        OUT / f"{name}.pt",
    )


def _datasets(p: Any, options: dict[str, Any], seed: int) -> tuple[Any, Any]:
    """(training set: the fit split with EARTH_SHARE of its frames swapped for their Earth renders (a recipe's
    `earth_share`: with the MORE_FIT_FRAMES renders too), augmented with `seed`; validation set: the validation
    split with that share swapped)."""
    from pipeline.pose.train import PoseDataset

    (fit_split, fit_set, _), (val_split, _) = data.training_sets(p, seed_for(p.seed, "train"))
    earth = _earth_frames(p)
    share = options.get("earth_share", EARTH_SHARE)  # by default the FIT_FRAMES renders only (23%)
    keys = ("fit", "fit_more") if "earth_share" in options else ("fit",)
    train_set = PoseDataset(_swapped(fit_split, earth, keys, share, 1), fit_split.targets, fit_set.augment_cfg, seed)
    val_set = PoseDataset(_swapped(val_split, earth, ("val",), share, 2), val_split.targets)
    return train_set, val_set


def _model(p: Any, name: str) -> Any:
    """A trained candidate (or the committed models: `committed-standard`, `committed-robust`), eval mode."""
    from pipeline.pose.model import PoseNet
    from stages.artifacts.models import load_pose
    from stages.artifacts.paths import POSE, POSE_ROBUST

    if name.startswith("committed-"):
        return load_pose(p, POSE if name.endswith("standard") else POSE_ROBUST).model
    ckpt = torch.load(OUT / f"{name}.pt")
    model = PoseNet(float(p.train.width), 0.0, ckpt["black_level"])
    model.load_state_dict(ckpt["state"])
    return model.eval()


def evaluate(p: Any, name: str, split_name: str, frames: int) -> None:
    """LEAN on a seeded sample of `frames` frames of the split (val or test) having an Earth render, each black
    and over its Earth background; the clean errors of the whole black split."""
    from pipeline.pose.metrics import pose_errors
    from pipeline.pose.train import PoseDataset, predict

    earth = _earth_frames(p)
    split = (
        data.fit_and_validation_splits(p, seed_for(p.seed, "train"))[1]
        if split_name == "val"
        else data.load_split(p, "test")
    )
    where = {int(k): i for i, k in enumerate(earth[f"{split_name}_index"])}
    have = np.flatnonzero([int(k) in where for k in split.labels["index"].to_numpy()])
    rows = have[sample_rows(len(have), frames, 0)]
    ours = [where[int(split.labels["index"].iloc[r])] for r in rows]
    targets = np.asarray(split.targets[rows], np.float64)
    model = _model(p, name)
    t0, c0 = time.perf_counter(), time.process_time()
    # one suite run on the black frames, one on the same frames over their backgrounds (split by kind)
    rows_out = ablation_rows({name: model}, np.stack([split.images[int(r)] for r in rows]), targets, EPS, LEAN)
    rows_out += ablation_rows(
        {name: model}, earth[f"{split_name}_images"][ours], targets, EPS, LEAN, earth[f"{split_name}_kind"][ours]
    )
    pos, att = pose_errors(predict(model, PoseDataset(np.asarray(split.images), split.targets), 64), split.targets)
    record = {
        "name": name,
        "split": split_name,
        "frames": int(len(rows)),
        "rows": rows_out,
        "whole_split_clean": {"n": int(len(pos)), "pos_m": float(pos.mean()), "att_deg": float(att.mean())},
        "suite_wall_s": time.perf_counter() - t0,
        "suite_cpu_s": time.process_time() - c0,
    }
    (OUT / f"{name}_{split_name}.json").write_text(json.dumps(record, indent=1))
    for r in rows_out:
        print(
            f"{name} {r['background']:6s} eps {r['eps']:.2f} n {r['n']}: {r['pos_m']:.2f} m "
            f"[{r['pos_ci'][0]:.2f}, {r['pos_ci'][1]:.2f}], {r['att_deg']:.1f} deg "
            f"[{r['att_ci'][0]:.1f}, {r['att_ci'][1]:.1f}]",
            flush=True,
        )


def _ci(mean: float, ci: list[float], digits: int) -> str:
    return f"{mean:.{digits}f} [{ci[0]:.{digits}f}, {ci[1]:.{digits}f}]"


def table_rows(records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per evaluated model and background: clean and nested worst-case errors per eps, 95% intervals."""
    out = []
    for rec in records:
        for bg in dict.fromkeys(r["background"] for r in rec["rows"]):
            rows = {r["eps"]: r for r in rec["rows"] if r["background"] == bg}
            row = {"model": rec["name"], "split": rec["split"], "background": bg, "frames": rows[0.0]["n"]}
            for e, r in rows.items():
                label = "clean" if e == 0 else f"eps {e:g}"
                row[f"{label} position (m)"] = _ci(r["pos_m"], r["pos_ci"], 2)
                row[f"{label} attitude (deg)"] = _ci(r["att_deg"], r["att_ci"], 1)
            out.append(row)
    return out


def table(names: list[str], section: str) -> None:
    """The `## {section}` section of reports/benchmarks.md from the stored evaluations of `names` (every stored
    one when empty)."""
    from pipeline.report.markdown import markdown_table
    from stages.report import write_benchmark

    files = sorted(OUT.glob("*_val.json")) + sorted(OUT.glob("*_test.json"))
    records = [r for r in (json.loads(f.read_text()) for f in files) if not names or r["name"] in names]
    unknown = sorted(set(names) - set(RECIPES) - {"committed-standard", "committed-robust"})
    unmeasured = sorted(set(names) - {r["name"] for r in records})
    if unknown or unmeasured or not records:
        raise SystemExit(
            f"table: unknown recipes {unknown}, no stored evaluation in {OUT} for {unmeasured or 'any'}; "
            f"run `eval NAME` first"
        )
    costs = []
    for name, (overrides, options) in RECIPES.items():
        if names and name not in names:
            continue
        path = OUT / f"{name}.pt"
        ckpt = torch.load(path) if path.exists() else {}
        costs.append(
            {
                "recipe": name,
                "train.adversarial overrides": json.dumps(overrides) if overrides else "(params.yaml)",
                "model": json.dumps(options) if options else "",
                "best epoch": ckpt.get("best_epoch", ""),
                "CPU s / epoch": f"{ckpt['cpu_s'] / len(ckpt['epoch_s']):.0f}" if ckpt else "",
                "wall s / epoch": f"{np.mean(ckpt['epoch_s']):.0f}" if ckpt else "",
            }
        )
    clean = [
        {
            "model": r["name"],
            "split": r["split"],
            "frames": r["whole_split_clean"]["n"],
            "position (m)": f"{r['whole_split_clean']['pos_m']:.3f}",
            "attitude (deg)": f"{r['whole_split_clean']['att_deg']:.2f}",
        }
        for r in records
    ]
    body = (
        f"`benchmarks/robust_recipes.py` on {platform.machine()}, torch {torch.__version__}, CPU, 1 thread per "
        f"process, two or more processes on the same 2 cores (wall times are not the idle machine's). Earth frames: "
        f"{json.dumps(EARTH)} (pipeline/render/backgrounds.py; `space` = stars and the sensor only, `earth` = the "
        f"sunlit Earth in view); training swaps {EARTH_SHARE:.0%} of the fit and validation frames for their Earth "
        f"versions. Attacks: LEAN ({', '.join(LEAN.members)}; {LEAN.steps} steps, lifting start), worst case per "
        f"frame nested in eps, means with 95% intervals; each sampled frame scored black and over its Earth "
        f"background.\n\n{markdown_table(costs)}\n{markdown_table(table_rows(records))}\n"
        f"Clean errors of the whole black split:\n\n{markdown_table(clean)}"
    )
    print(body)
    print(f"-> {write_benchmark(section, body)} (## {section})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("command", choices=["render", "train", "eval", "table"])
    ap.add_argument(
        "name",
        nargs="*",
        help="a preset of RECIPES (eval: also committed-standard, committed-robust); table: those to include (all)",
    )
    ap.add_argument("--section", default="Robust training recipes", help="table: the reports/benchmarks.md section")
    ap.add_argument("--split", default="val", choices=["val", "test"])
    ap.add_argument("--frames", type=int, default=64)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    p = params_mod.load()
    if args.command == "render":
        render(p)
    elif args.command in ("train", "eval") and len(args.name) != 1:
        raise SystemExit(f"{args.command} takes one recipe name, got {len(args.name)}")
    elif args.command == "train":
        train(p, args.name[0])
    elif args.command == "eval":
        evaluate(p, args.name[0], args.split, args.frames)
    else:
        table(args.name, args.section)


if __name__ == "__main__":
    main()
