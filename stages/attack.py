"""`rpod attack`: adversarial test images at every eps in params, and their effect on the pose errors.

Reads models/pose.pt and the test split; writes datasets/attack/adv.zarr (one uint8 (N, H, W, 3)
array per eps, named `eps_<eps>`, plus `source_index` = the label `index` of each row),
reports/attack.md, reports/figures/fgsm_example.png and reports/metrics/attack.json.
Errors are measured on the stored uint8 adversarial images (what the SHAP stage reads).
The batches fan out over the engine's workers on the CPU (stages/engine/attack_worker.py on
stages/engine/pool.py; in-process with one worker or on a GPU), each batch's attack seeded by its place,
so adv.zarr does not depend on the workers.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

import numpy as np
import typer

from pipeline.geometry.labels import POSITION, QUAT, TARGET
from pipeline.io.atomic import atomic_outputs, atomic_write_text, save_figure
from pipeline.io.store import create_array, seal_zarr
from pipeline.seeds import seed_for
from stages.artifacts.dvc import write_metrics
from stages.artifacts.models import load_pose
from stages.artifacts.paths import ADV, POSE
from stages.artifacts.paths import ATTACK_FIGURE as FIGURE
from stages.artifacts.paths import ATTACK_METRICS as METRICS
from stages.artifacts.paths import ATTACK_REPORT as REPORT
from stages.artifacts.readers import adv_array_name
from stages.config.build import check_attack_params, make_attack
from stages.config.device import torch_setup
from stages.config.schema import Params
from stages.config.sections import Attack
from stages.engine import pool as engine
from stages.engine.attack_worker import AttackBatch, AttackSetup, AttackWorker
from stages.errors import StageError
from stages.pages.attack import attack_page


def main(params: Params) -> None:
    """Attack the test set at every attack.eps with attack.method on attack.loss; report the pose errors."""
    import torch

    a = params.attack
    check_attack_params(a, "attack")
    eps_list = [float(e) for e in a.eps]
    torch_setup(params)
    make_attack(a, a.method, 0)  # refuses bad attack params before anything is loaded
    pose = load_pose(params)
    images, labels, n = _test_set(params)
    t_gt = labels[POSITION].to_numpy(np.float64)
    q_gt = labels[QUAT].to_numpy(np.float64)
    y_all = torch.tensor(labels[TARGET].to_numpy(np.float32))
    k = int(np.argmin(np.abs(t_gt[:, 2] - np.median(t_gt[:, 2]))))  # figure: a mid-range test image
    es, threads = _engine(params, pose.model.device)
    setup = AttackSetup(
        params=params,
        pose_path=str(POSE.resolve()),
        eps=tuple(eps_list),
        batch=a.batch_size,
        seed=seed_for(params.seed, "attack"),
        torch_threads=None if es.in_process else threads,
    )
    t0 = time.perf_counter()
    # adv.zarr, the metrics, the report and the figure move into place together, once all are written
    with atomic_outputs(METRICS, REPORT, FIGURE, dirs=(ADV.parent,)) as (metrics_tmp, report_tmp, figure_tmp, adv):
        out = _attack_into(adv / ADV.name, setup, images, labels["index"].to_numpy(np.int64), y_all, k, es, threads)
        out["root"].attrs.update(
            {
                "eps": eps_list,
                "method": a.method,
                "loss": a.loss,
                "model_hash": pose.hash,
                "quantisation": "round to nearest 8-bit level, at least one level, sign kept",
            }
        )
        seal_zarr(adv / ADV.name)
        seconds = time.perf_counter() - t0
        rows = _rows(out, eps_list, t_gt, q_gt)
        write_metrics(metrics_tmp, _metrics(a, n, seconds, pose.hash, rows), params.profile_name)
        atomic_write_text(report_tmp, attack_page(rows, a, n))
        save_figure(_figure(images, k, t_gt, out, eps_list, a.method), figure_tmp)
    typer.echo(f"attack: {n} test images x {len(eps_list)} eps in {seconds:.0f} s -> {ADV}, {REPORT}")


def _test_set(params: Params) -> tuple[Any, Any, int]:
    """The test split's images, the labels of the first n of them and n (attack.max_images, else every test
    image); n < 1 stops the stage."""
    from stages.artifacts.data import load_split

    a = params.attack
    split = load_split(params, "test")
    n = len(split) if a.max_images is None else min(len(split), a.max_images)
    if n < 1:
        raise StageError(f"params.yaml attack.max_images must be at least 1, got {a.max_images}")
    return split.images, split.labels.iloc[:n], n


def _metrics(a: Attack, n: int, seconds: float, model_hash: str, rows: list[dict[str, Any]]) -> dict[str, Any]:
    """reports/metrics/attack.json: the attack, the image count, the seconds and the pose errors of `rows`
    (clean, then per eps)."""
    return {
        "method": a.method,
        "loss": a.loss,
        "images": n,
        "seconds": seconds,
        "model_hash": model_hash,
        "measured_on": "stored uint8 images",
        "clean": {key: v for key, v in rows[0].items() if key != "eps"},
        "eps": {r["eps"]: {key: v for key, v in r.items() if key != "eps"} for r in rows[1:]},
    }


def _figure(images: Any, k: int, t_gt: np.ndarray, out: dict[str, Any], eps_list: list[float], method: str) -> Any:
    """reports/figures/fgsm_example.png's figure: test image k, its stored adversarial images and the pose
    predictions, clean and per eps."""
    from pipeline.report.figures import attack_example

    return attack_example(
        np.asarray(images[k]),
        out["example"],
        t_gt[k],
        {e: out["preds"][e][k] for e in ["clean", *eps_list]},
        method,
    )


def _attack_into(
    path: Path,
    setup: AttackSetup,
    images: Any,
    source_index: np.ndarray,
    y_all: Any,
    k: int,
    es: engine.EngineSettings,
    threads: int,
) -> dict[str, Any]:
    """Attack the first len(source_index) images at every eps into a new zarr group at `path` (one uint8
    array per eps), one batch per engine job on `AttackWorker(setup)`; returns the group, the pose
    outputs (clean, stored uint8, float), the stored L-inf per eps and image k's stored adversarial
    images (for the figure)."""
    import zarr
    from tqdm import tqdm

    eps_list, batch = setup.eps, setup.batch
    n = len(source_index)
    preds = {"clean": np.zeros((n, 9))} | {e: np.zeros((n, 9)) for e in eps_list}
    preds_float = {e: np.zeros((n, 9)) for e in eps_list}
    linf = {e: 0.0 for e in eps_list}
    example: dict[float, np.ndarray] = {}
    root = zarr.open_group(str(path), mode="w")
    h, w = np.asarray(images[0]).shape[:2]
    arrays = {
        e: create_array(root, adv_array_name(e), shape=(n, h, w, 3), chunks=(min(batch, n), h, w, 3), dtype="uint8")
        for e in eps_list
    }
    create_array(root, "source_index", data=source_index)
    starts = list(range(0, n, batch))

    def done(j: int, out: dict[str, Any]) -> None:
        """Write one batch's stored images (whole chunks) and keep its outputs."""
        i = starts[j]
        hi = i + len(out["clean"])
        preds["clean"][i:hi] = out["clean"]
        for e in eps_list:
            arrays[e][i:hi], preds[e][i:hi], preds_float[e][i:hi], m = out[e]
            linf[e] = max(linf[e], m)
            if i <= k < hi:
                example[e] = out[e][0][k - i]
        bar.update(1)

    jobs = [
        AttackBatch(i, np.stack([np.asarray(images[j]) for j in range(i, min(i + batch, n))]), y_all[i : i + batch])
        for i in starts
    ]
    desc = f"attack ({setup.params.attack.method}, {len(eps_list)} eps)"
    with tqdm(total=len(jobs), desc=desc, unit="batch") as bar:
        engine.run(AttackWorker, setup, jobs, es, num_cpus=threads, progress=done)
    return {"root": root, "preds": preds, "preds_float": preds_float, "linf": linf, "example": example}


def _rows(out: dict[str, Any], eps_list: list[float], t_gt: np.ndarray, q_gt: np.ndarray) -> list[dict[str, Any]]:
    """The report's rows: clean, then per eps the errors on the stored uint8 images, their L-inf and the
    errors on the float (unquantised) images."""
    preds = out["preds"]
    rows = [{"eps": "clean", "stored_linf": 0.0, **_errors(preds["clean"], t_gt, q_gt)}]
    for e in eps_list:
        f = _errors(out["preds_float"][e], t_gt, q_gt)
        rows.append(
            {
                "eps": f"{e:g}",
                "stored_linf": out["linf"][e],
                **_errors(preds[e], t_gt, q_gt),
                "float_position_mean_m": f["position_mean_m"],
                "float_attitude_mean_deg": f["attitude_mean_deg"],
            }
        )
    return rows


def _errors(pred: np.ndarray, t_gt: np.ndarray, q_gt: np.ndarray) -> dict[str, float]:
    """Mean and median position (m) and attitude (deg) errors of (N, 9) outputs against the labels."""
    from pipeline.geometry.rotations import sixd_to_quat
    from pipeline.pose.metrics import attitude_error_deg, position_error

    pos = position_error(pred[:, :3], t_gt)
    att = attitude_error_deg(sixd_to_quat(pred[:, 3:]), q_gt)
    return {
        "position_mean_m": float(pos.mean()),
        "position_median_m": float(np.median(pos)),
        "attitude_mean_deg": float(att.mean()),
        "attitude_median_deg": float(np.median(att)),
    }


def _engine(p: Params, device: Any) -> tuple[engine.EngineSettings, int]:
    """(engine settings, torch threads per worker): the batches fan out over CPU workers (threads shared
    out); on a GPU they run in-process, where the GPU does the work."""
    import dataclasses

    es = engine.engine_settings(p)
    if device.type != "cpu":
        es = dataclasses.replace(es, workers=1, address=None)
    return es, es.threads(p.threads or os.cpu_count() or 1)
