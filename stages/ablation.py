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
"""
from __future__ import annotations

import time
from typing import Any

import numpy as np
import typer

from pipeline.io.atomic import atomic_write_text
from pipeline.geometry.labels import POSITION, SIXD
from pipeline.seeds import seed_for
from stages.artifacts.data import load_split
from stages.artifacts.dvc import write_metrics
from stages.artifacts.models import load_chain
from stages.artifacts.paths import ABLATION_METRICS, ABLATION_REPORT, DETECT_RENDER, PAPER
from stages.artifacts.readers import read_detect_render
from stages.config.device import torch_setup
from stages.config.schema import Params
from stages.errors import StageError
from stages.pages.ablation import ablation_page, cell_json


def main(params: Params) -> None:
    """Fit the paper's LSTM detector in the four cells FGSM (ours | paper-literal) x protocol (strict | paper) and
    write the ablation's page and metrics."""
    import torch

    from pipeline.attacks.gradient import attack_loss
    from pipeline.evaluation.ablation import run_ablation
    from pipeline.detectors.lstm import LSTMConfig

    a, d = params.ablation, params.detect
    device = torch_setup(params)
    seed = seed_for(params.seed, "ablation")
    rng = np.random.default_rng(seed)
    chain = load_chain(params, PAPER, defended=False)   # the standard model and its detector's SHAP explainer
    loss_fn = attack_loss(params.attack.loss, chain.loss)
    shap = chain.onboard.shap
    background = shap.background_mean
    t0 = time.perf_counter()
    protocols = [_strict(params, rng, chain.model, shap, loss_fn), _paper(params, rng, chain.model, shap, loss_fn)]
    explain_s = time.perf_counter() - t0
    torch.set_num_threads(1)   # the LSTM's matrices are small: extra threads cost more than they give (as rpod detect)
    config = LSTMConfig(n_rows=9, n_features=len(background), hidden=d.hidden, dense=list(d.dense))
    fit = {"epochs": d.epochs, "patience": d.patience, "batch_size": d.batch_size, "lr": float(d.lr)}
    t1 = time.perf_counter()
    try:
        cells = run_ablation(protocols, config, fit, float(d.test_fraction), float(d.val_fraction), seed, device)
    except ValueError as e:   # also a diverged fit (DivergenceError)
        raise StageError(f"params.yaml ablation / detect: {e}") from None
    fit_s = time.perf_counter() - t1
    metrics = {"model_hash": chain.pose_hash, "eps": [float(e) for e in a.eps], "normal": a.normal, "per_eps": a.per_eps,
               "seconds": {"explain": explain_s, "fit": fit_s, "total": explain_s + fit_s},
               "cells": [cell_json(c) for c in cells]}
    write_metrics(ABLATION_METRICS, metrics, params.profile_name)
    atomic_write_text(ABLATION_REPORT, ablation_page(cells, a, d, (params.render.frames_per_sequence, params.shap.frames)))
    typer.echo(f"ablation: 4 cells of {sum(cells[0].counts.values())} samples in {explain_s + fit_s:.0f} s "
               f"(SHAP values {explain_s:.0f} s, LSTM fits {fit_s:.0f} s) -> {ABLATION_REPORT}")


def _strict(p: Params, rng: np.random.Generator, model: Any, shap: Any, loss_fn: Any) -> Any:
    """Our protocol's samples: images of the detector split, each clean once and attacked at most once."""
    from pipeline.evaluation.ablation import ProtocolSamples
    from pipeline.shap import sample_plan

    a = p.ablation
    images, poses, _ = read_detect_render(p)
    try:
        plan = sample_plan(a.normal, a.per_eps, a.eps, np.arange(len(poses)), rng)
    except ValueError as e:
        raise StageError(f"{DETECT_RENDER}: {e}; lower ablation.normal / ablation.per_eps or raise shap.frames") from None
    idx = plan["index"]
    rows = poses.iloc[idx]
    values = _values(np.asarray(images[:])[idx], rows[POSITION + SIXD].to_numpy(np.float32), plan["eps"], model,
                     shap, loss_fn, "strict")
    return ProtocolSamples("strict", plan["eps"].astype(np.float64), idx, rows["trajectory"].to_numpy(),
                           rows["frame"].to_numpy(), values)


def _paper(p: Params, rng: np.random.Generator, model: Any, shap: Any, loss_fn: Any) -> Any:
    """The paper's protocol's samples: pose-test images topped up with pose-training ones (clean) and attacked
    pose-test images."""
    import pandas as pd

    from pipeline.evaluation.ablation import ProtocolSamples
    from pipeline.evaluation.protocols import paper_plan

    a = p.ablation
    splits = [load_split(p, "test"), load_split(p, "train")]
    table = pd.concat([s.labels for s in splits], ignore_index=True)
    try:
        plan = paper_plan(table["split"].to_numpy(), a.normal, a.per_eps, a.eps, rng)
    except ValueError as e:
        raise StageError(f"datasets/labels.parquet: {e}; lower ablation.normal / ablation.per_eps") from None
    idx = plan["index"]
    n_test = len(splits[0])
    images = np.stack([splits[0].images[i] if i < n_test else splits[1].images[i - n_test] for i in idx.tolist()])
    rows = table.iloc[idx]
    values = _values(images, rows[POSITION + SIXD].to_numpy(np.float32), plan["eps"], model, shap, loss_fn, "paper")
    return ProtocolSamples("paper", plan["eps"].astype(np.float64), rows["index"].to_numpy(np.int64),
                           rows["sequence"].to_numpy(), rows["frame"].to_numpy(), values)


def _values(images: np.ndarray, targets: np.ndarray, eps: np.ndarray, model: Any, shap: Any, loss_fn: Any,
            protocol: str) -> dict[str, np.ndarray]:
    """`pipeline.evaluation.ablation.protocol_values` with a progress bar."""
    from tqdm import tqdm

    from pipeline.evaluation.ablation import protocol_values

    with tqdm(total=len(eps), desc=f"ablation: SHAP values ({protocol} protocol)", unit="sample") as bar:
        return protocol_values(model, shap, loss_fn, images, targets, eps, progress=bar.update)
