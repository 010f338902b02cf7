"""`rpod ablation`: issue 38's 2 x 2 ablation of the paper's detector on the standard model -> reports/ablation.md and
reports/metrics/ablation.json. A stage of optional/dvc.yaml (`dvc repro optional/dvc.yaml`), not of the default
`dvc repro`: it does not fit the default profile's 40-minute budget (README, "Running one stage").

Cells: FGSM as we deliver it (clipped to [0, 1], stored as 8 bits) or as the paper's equation prints it (unclipped
floats: pipeline/attacks/literal.py), crossed with two detector protocols (pipeline/evaluation/protocols.py):
- strict (ours): `ablation.normal` clean and `ablation.per_eps` attacked samples per eps of `ablation.eps`, all images
  of the detector split (datasets/detect_render, never seen by the pose network; `pipeline.shap.sample_plan`), split
  grouped by source image;
- paper (leaky): clean = pose-test images topped up with pose-training images, attacked = pose-test images
  (datasets/labels.parquet, datasets/render), split at random per sample as the paper did.
Both FGSM variants of a protocol attack the same images and use the same split. SHAP values are the closed form with
the background mean of the standard model's own detector (models/detector.pt), so the explainer is the one `rpod shap`
used; each cell trains one LSTM with the `detect` params (split fractions, architecture, fit) and is measured on its
test part (rates per eps with Wilson intervals; pipeline/evaluation/ablation.py).

The 2 x 2 runs twice: its detectors trained on `ablation.eps` (`ablation.per_eps` attacked samples each), then on the
paper's eps mix `ablation.paper_eps` (`ablation.paper_per_eps` each: the eps our `rpod detect` trains on too); the
paper's-mix cells ours/strict and paper/paper are also refitted on `ablation.fractions` of their training samples (a
learning curve). Then the detectors run on image sequences as onboard: the integrated evaluation's trajectories
(datasets/eval_render with `rpod evaluate`'s attack schedules) and the lab's recordings (datasets/lab, or
`lab.real_data`, with `rpod lab`'s; left out when the lab stage retrains its models), every `ablation.eps` attacked
by either FGSM variant: the standard detector (models/detector.pt, the one `rpod evaluate` and `rpod lab` run) under
both, each cell's detector under its own; rates per eps with the bootstrap over the sequences, and the per-sequence
counts (for paired differences on the same sequences).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import typer

from pipeline.attacks.literal import VARIANTS
from pipeline.geometry.labels import POSITION, SIXD, TARGET
from pipeline.io.atomic import atomic_write_text
from pipeline.seeds import seed_for
from stages.artifacts.data import load_split
from stages.artifacts.dvc import write_metrics
from stages.artifacts.models import load_chain
from stages.artifacts.paths import ABLATION_METRICS, ABLATION_REPORT, DETECT_RENDER, LAB, PAPER
from stages.artifacts.readers import read_detect_render, read_eval_render
from stages.config.build import retrain_reason
from stages.config.device import torch_setup
from stages.config.params import evaluation_seed, given
from stages.config.schema import Params
from stages.errors import StageError
from stages.pages.ablation import ablation_page, cell_json, cell_key, sequences_json


def main(params: Params) -> None:
    """Fit the paper's LSTM detector in the cells FGSM (ours | paper-literal) x protocol (strict | paper), on two eps
    mixes, run the detectors on the evaluation and lab sequences, and write the ablation's page and metrics."""
    import torch

    from pipeline.attacks.gradient import attack_loss
    from pipeline.detectors.lstm import LSTMConfig

    a, d = params.ablation, params.detect
    device = torch_setup(params)
    seed = seed_for(params.seed, "ablation")
    rng = np.random.default_rng(seed)
    chain = load_chain(params, PAPER, defended=False)  # the standard model and its detector's SHAP explainer
    loss_fn = attack_loss(params.attack.loss, chain.loss)
    shap = chain.onboard.shap
    background = shap.background_mean
    t0 = time.perf_counter()
    mixes = {"ablation": (a.eps, a.per_eps), "paper": (a.paper_eps, a.paper_per_eps)}  # drawn in this order
    protocols = {
        mix: [
            _strict(params, rng, chain.model, shap, loss_fn, eps, n),
            _paper(params, rng, chain.model, shap, loss_fn, eps, n),
        ]
        for mix, (eps, n) in mixes.items()
    }
    explain_s = time.perf_counter() - t0
    threads = torch.get_num_threads()  # as torch_setup left them, for the sequences' pose network
    torch.set_num_threads(1)  # the LSTM's matrices are small: extra threads cost more than they give (as rpod detect)
    config = LSTMConfig(n_rows=9, n_features=len(background), hidden=d.hidden, dense=list(d.dense))
    fit = {"epochs": d.epochs, "patience": d.patience, "batch_size": d.batch_size, "lr": float(d.lr)}
    split = (float(d.test_fraction), float(d.val_fraction), seed)
    t1 = time.perf_counter()
    cells, curves = _fit_cells(protocols, list(a.fractions), config, fit, split, device)
    fit_s = time.perf_counter() - t1
    torch.set_num_threads(threads)
    t2 = time.perf_counter()
    runs, detectors = _sequence_runs(params, chain, loss_fn, cells)
    sequence_s = time.perf_counter() - t2
    metrics = _metrics(params, chain.pose_hash, cells, curves, runs, (explain_s, fit_s, sequence_s))
    write_metrics(ABLATION_METRICS, metrics, params.profile_name)
    atomic_write_text(
        ABLATION_REPORT,
        ablation_page(
            cells, curves, metrics["sequences"], a, d, (params.render.frames_per_sequence, params.shap.frames)
        ),
    )
    typer.echo(
        f"ablation: {len(cells)} cells in {explain_s + fit_s:.0f} s (SHAP values {explain_s:.0f} s, LSTM fits "
        f"{fit_s:.0f} s), {len(detectors)} detectors on {', '.join(runs)} sequences in {sequence_s:.0f} s "
        f"-> {ABLATION_REPORT}"
    )


def _fit_cells(
    protocols: dict[str, list[Any]],
    fractions: list[float],
    config: Any,
    fit: dict[str, Any],
    split: tuple[float, float, int],
    device: Any,
) -> tuple[list[Any], dict[str, list[Any]]]:
    """(the cells of every eps mix's 2 x 2, each with its fitted LSTM; the learning curves of the paper's-mix cells
    ours/strict and paper/paper on `fractions` of their training samples); a StageError for a failed fit."""
    from pipeline.evaluation.ablation import learning_curve, run_ablation

    try:
        cells = [c for mix, prot in protocols.items() for c in run_ablation(prot, config, fit, *split, device, mix)]
        strict, paper = protocols["paper"]
        curves = {
            f"{attack}/{p.protocol}": learning_curve(p, attack, fractions, config, fit, *split, device, "paper")
            for attack, p in (("ours", strict), ("paper", paper))
        }
    except ValueError as e:  # also a diverged fit (DivergenceError)
        raise StageError(f"params.yaml ablation / detect: {e}") from None
    return cells, curves


def _sequence_runs(
    params: Params, chain: Any, loss_fn: Any, cells: list[Any]
) -> tuple[dict[str, dict[str, dict[str, Any]]], dict[str, tuple[Any, float, str]]]:
    """(per place, integrated evaluation and lab (unless the lab stage retrains its models), the `sequence_counts`
    of the standard detector under each FGSM variant and of each cell's detector under its own; those detectors)."""
    a = params.ablation
    sequences = {
        "integrated": _eval_sequences(params),
        **({"lab": _lab_sequences(params)} if retrain_reason(params) is None else {}),
    }
    onboard = chain.onboard
    detectors = {
        **{f"standard/{v}": (onboard.detector, onboard.threshold, v) for v in VARIANTS},
        **{cell_key(c): (c.detector, c.threshold, c.attack) for c in cells},
    }
    runs = {
        where: sequence_counts(chain.model, loss_fn, onboard.shap, seqs, detectors, [float(x) for x in a.eps])
        for where, seqs in sequences.items()
    }
    return runs, detectors


def _metrics(
    params: Params,
    model_hash: str,
    cells: list[Any],
    curves: dict[str, list[Any]],
    runs: dict[str, dict[str, dict[str, Any]]],
    seconds: tuple[float, float, float],
) -> dict[str, Any]:
    """reports/metrics/ablation.json: the settings, the seconds (SHAP values, LSTM fits, sequences), the cells, the
    learning curves and the sequence counts."""
    a = params.ablation
    explain_s, fit_s, sequence_s = seconds
    return {
        "model_hash": model_hash,
        "eps": [float(e) for e in a.eps],
        "normal": a.normal,
        "per_eps": a.per_eps,
        "paper_eps": [float(e) for e in a.paper_eps],
        "paper_per_eps": a.paper_per_eps,
        "seconds": {
            "explain": explain_s,
            "fit": fit_s,
            "sequences": sequence_s,
            "total": explain_s + fit_s + sequence_s,
        },
        "cells": [cell_json(c) for c in cells],
        "curves": {k: [cell_json(c) for c in v] for k, v in curves.items()},
        "sequences": {where: sequences_json(r, where) for where, r in runs.items()},
    }


def sequence_counts(
    model: Any,
    loss_fn: Any,
    shap: Any,
    sequences: list[Any],
    detectors: dict[str, tuple[Any, float, str]],
    eps_list: list[float],
) -> dict[str, dict[str, Any]]:
    """Per detector (name -> (detector, threshold, the FGSM variant it is run under)) and eps, the per-sequence
    counts (G, 4) on `sequences` (pipeline.evaluation.sequences.Sequence: images, targets, attack schedule), each
    sequence's frames attacked once per variant and eps (pipeline.evaluation.ablation.attacked_features)."""
    from tqdm import tqdm

    from pipeline.evaluation.ablation import attacked_features, flag_counts

    out: dict[str, dict[str, Any]] = {name: {} for name in detectors}
    jobs = [(v, e) for v in VARIANTS for e in eps_list]
    for variant, eps in tqdm(jobs, desc="ablation: sequences (variant x eps)", unit="job"):
        feats = [attacked_features(model, loss_fn, s.images, s.targets, s.attacked, variant, eps) for s in sequences]
        for name, (det, threshold, v) in detectors.items():
            if v == variant:
                out[name][f"{eps:g}"] = flag_counts(feats, [s.attacked for s in sequences], shap, det, threshold)
    return out


def _eval_sequences(p: Params) -> list[Any]:
    """The integrated evaluation's trajectories (datasets/eval_render) with `rpod evaluate`'s attack schedules."""
    from pipeline.attacks.schedule import attack_schedule
    from pipeline.evaluation.sequences import Sequence

    e = p.evaluate
    images, poses, _ = read_eval_render(p)
    return [
        Sequence(
            name=f"T{int(tr) + 1}",
            images=images[g["index"].to_numpy()],
            targets=g[TARGET].to_numpy(np.float32),
            attacked=attack_schedule(
                len(g), e.p_start, e.attack_length, seed_for(evaluation_seed(p), "evaluate.schedule", int(tr))
            ),
        )
        for tr, g in poses.groupby("trajectory", sort=True)
    ]


def _lab_sequences(p: Params) -> list[Any]:
    """The lab recordings (datasets/lab, or lab.real_data) through the real-data loader, with `rpod lab`'s attack
    schedules and synthetic-frame targets."""
    from pathlib import Path

    from pipeline.evaluation.lab import chain_sequences
    from pipeline.geometry.camera import Intrinsics
    from stages.artifacts.recordings import read_recordings

    lab, c, z = p.lab, p.camera, p.lab.zed
    source = Path(given(lab.real_data) or LAB)
    recs = read_recordings(p, source)
    K_syn = Intrinsics(c.ref_width, c.ref_height, c.fx, c.fy, c.cx, c.cy)
    K_zed = Intrinsics(z.width, z.height, z.fx, z.fy, z.cx, z.cy)
    return chain_sequences(
        recs, K_syn, K_zed, float(lab.scale), float(p.evaluate.p_start), lab.attack_length, lab.seed
    )[0]


def _strict(
    p: Params, rng: np.random.Generator, model: Any, shap: Any, loss_fn: Any, eps: list[float], per_eps: int
) -> Any:
    """Our protocol's samples: images of the detector split, each clean once and attacked at most once."""
    from pipeline.evaluation.ablation import ProtocolSamples
    from pipeline.shap import sample_plan

    a = p.ablation
    images, poses, _ = read_detect_render(p)
    try:
        plan = sample_plan(a.normal, per_eps, eps, np.arange(len(poses)), rng)
    except ValueError as e:
        raise StageError(
            f"{DETECT_RENDER}: {e}; lower ablation.normal / ablation.per_eps / ablation.paper_per_eps or "
            "raise shap.frames"
        ) from None
    idx = plan["index"]
    rows = poses.iloc[idx]
    values = _values(
        np.asarray(images[:])[idx],
        rows[POSITION + SIXD].to_numpy(np.float32),
        plan["eps"],
        model,
        shap,
        loss_fn,
        "strict",
    )
    return ProtocolSamples(
        "strict", plan["eps"].astype(np.float64), idx, rows["trajectory"].to_numpy(), rows["frame"].to_numpy(), values
    )


def _paper(
    p: Params, rng: np.random.Generator, model: Any, shap: Any, loss_fn: Any, eps: list[float], per_eps: int
) -> Any:
    """The paper's protocol's samples: pose-test images topped up with pose-training ones (clean) and attacked
    pose-test images."""
    import pandas as pd

    from pipeline.evaluation.ablation import ProtocolSamples
    from pipeline.evaluation.protocols import paper_plan

    a = p.ablation
    splits = [load_split(p, "test"), load_split(p, "train")]
    table = pd.concat([s.labels for s in splits], ignore_index=True)
    try:
        plan = paper_plan(table["split"].to_numpy(), a.normal, per_eps, eps, rng)
    except ValueError as e:
        raise StageError(
            f"datasets/labels.parquet: {e}; lower ablation.normal / ablation.per_eps / ablation.paper_per_eps"
        ) from None
    idx = plan["index"]
    n_test = len(splits[0])
    images = np.stack([splits[0].images[i] if i < n_test else splits[1].images[i - n_test] for i in idx.tolist()])
    rows = table.iloc[idx]
    values = _values(images, rows[POSITION + SIXD].to_numpy(np.float32), plan["eps"], model, shap, loss_fn, "paper")
    return ProtocolSamples(
        "paper",
        plan["eps"].astype(np.float64),
        rows["index"].to_numpy(np.int64),
        rows["sequence"].to_numpy(),
        rows["frame"].to_numpy(),
        values,
    )


def _values(
    images: np.ndarray, targets: np.ndarray, eps: np.ndarray, model: Any, shap: Any, loss_fn: Any, protocol: str
) -> dict[str, np.ndarray]:
    """`pipeline.evaluation.ablation.protocol_values` with a progress bar."""
    from tqdm import tqdm

    from pipeline.evaluation.ablation import protocol_values

    with tqdm(total=len(eps), desc=f"ablation: SHAP values ({protocol} protocol)", unit="sample") as bar:
        return protocol_values(model, shap, loss_fn, images, targets, eps, progress=bar.update)
