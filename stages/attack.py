"""`rpod attack`: adversarial test images at every eps in params, and their effect on the pose errors.

Reads models/pose.pt and the test split; writes datasets/attack/adv.zarr (one uint8 (N, H, W, 3)
array per eps, named `eps_<eps>`, plus `source_index` = the label `index` of each row),
reports/attack.md, reports/figures/fgsm_example.png and reports/metrics/attack.json.
Errors are measured on the stored uint8 adversarial images (what the SHAP stage reads).
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import typer

from stages import params as params_mod
from stages.artifacts import ADV, adv_array_name, load_pose
from stages.io import StageError, atomic_dir, atomic_write_text, create_array, save_figure, write_metrics

REPORT = Path("reports/attack.md")
FIGURE = Path("reports/figures/fgsm_example.png")
METRICS = Path("reports/metrics/attack.json")
SEED_OFFSET = 400


def main() -> None:
    """Attack the test set at every attack.eps with attack.method on attack.loss; report the pose errors."""
    import torch

    from pipeline.attacks import attack_loss
    from pipeline.figures import attack_example
    from stages.data import load_split

    p = params_mod.load()
    a = p["attack"]
    params_mod.check_attack_params(a, "attack")
    eps_list = [float(e) for e in a["eps"]]
    params_mod.torch_setup(p)
    attack = params_mod.make_attack(a, a["method"], int(p["seed"]) + SEED_OFFSET)
    pose = load_pose(p)
    split = load_split(p, "test")
    n = len(split) if a["max_images"] is None else min(len(split), int(a["max_images"]))
    if n < 1:
        raise StageError(f"params.yaml attack.max_images must be at least 1, got {a['max_images']}")
    images, labels = split.images, split.labels.iloc[:n]
    t_gt = labels[["tx", "ty", "tz"]].to_numpy(np.float64)
    q_gt = labels[["qw", "qx", "qy", "qz"]].to_numpy(np.float64)
    y_all = torch.tensor(labels[["tx", "ty", "tz", "r0", "r1", "r2", "r3", "r4", "r5"]].to_numpy(np.float32))
    k = int(np.argmin(np.abs(t_gt[:, 2] - np.median(t_gt[:, 2]))))  # figure: a mid-range test image
    t0 = time.perf_counter()
    with atomic_dir(ADV.parent) as tmp:
        out = _attack_into(tmp / ADV.name, pose.model, attack, attack_loss(a["loss"], pose.loss), images,
                           labels["index"].to_numpy(np.int64), y_all, eps_list, int(a["batch_size"]), k, a["method"])
        out["root"].attrs.update({"eps": eps_list, "method": a["method"], "loss": a["loss"], "model_hash": pose.hash,
                                  "quantisation": "round to nearest 8-bit level, at least one level, sign kept"})
    seconds = time.perf_counter() - t0
    preds = out["preds"]
    rows = [{"eps": "clean", "stored_linf": 0.0, **_errors(preds["clean"], t_gt, q_gt)}]
    for e in eps_list:
        f = _errors(out["preds_float"][e], t_gt, q_gt)
        rows.append({"eps": f"{e:g}", "stored_linf": out["linf"][e], **_errors(preds[e], t_gt, q_gt),
                     "float_position_mean_m": f["position_mean_m"], "float_attitude_mean_deg": f["attitude_mean_deg"]})
    metrics = {"method": a["method"], "loss": a["loss"], "images": n, "seconds": seconds, "model_hash": pose.hash,
               "measured_on": "stored uint8 images", "clean": {key: v for key, v in rows[0].items() if key != "eps"},
               "eps": {r["eps"]: {key: v for key, v in r.items() if key != "eps"} for r in rows[1:]}}
    write_metrics(METRICS, metrics, p)
    atomic_write_text(REPORT, _report(rows, a, n))
    save_figure(attack_example(np.asarray(images[k]), out["example"], t_gt[k],
                               {e: preds[e][k] for e in ["clean", *eps_list]}, a["method"]), FIGURE)
    typer.echo(f"attack: {n} test images x {len(eps_list)} eps in {seconds:.0f} s -> {ADV}, {REPORT}")


def _attack_into(path: Path, model: Any, attack: Any, loss_fn: Any, images: Any, source_index: np.ndarray, y_all: Any,
                 eps_list: list[float], batch: int, k: int, method: str) -> dict[str, Any]:
    """Attack the first len(source_index) images at every eps into a new zarr group at `path` (one uint8
    array per eps); returns the group, the pose outputs (clean, stored uint8, float), the stored L-inf
    per eps and image k's stored adversarial images (for the figure)."""
    import torch
    import zarr
    from tqdm import tqdm

    from pipeline.attacks import quantize

    n = len(source_index)
    preds = {"clean": np.zeros((n, 9))} | {e: np.zeros((n, 9)) for e in eps_list}
    preds_float = {e: np.zeros((n, 9)) for e in eps_list}
    linf = {e: 0.0 for e in eps_list}
    example: dict[float, np.ndarray] = {}
    root = zarr.open_group(str(path), mode="w")
    h, w = np.asarray(images[0]).shape[:2]
    arrays = {e: create_array(root, adv_array_name(e), shape=(n, h, w, 3), chunks=(min(batch, n), h, w, 3),
                             dtype="uint8") for e in eps_list}
    create_array(root, "source_index", data=source_index)
    model.eval()
    for i in tqdm(range(0, n, batch), desc=f"attack ({method}, {len(eps_list)} eps)", unit="batch"):
        u8 = np.stack([np.asarray(images[j]) for j in range(i, min(i + batch, n))])
        x = torch.from_numpy(u8).to(model.device).permute(0, 3, 1, 2).float() / 255   # uint8 over the bus
        y = y_all[i:i + batch].to(model.device)
        with torch.no_grad():
            preds["clean"][i:i + len(x)] = model(x).cpu().numpy()
        for e in eps_list:
            x_adv = attack(model, x, y, e, loss_fn)
            stored = quantize(x_adv, x)
            stored_hwc = stored.permute(0, 2, 3, 1).cpu().numpy()
            arrays[e][i:i + len(x)] = stored_hwc
            if i <= k < i + len(x):
                example[e] = stored_hwc[k - i]
            linf[e] = max(linf[e], float((stored.float() / 255 - x).abs().max()))
            with torch.no_grad():
                preds[e][i:i + len(x)] = model(stored.float() / 255).cpu().numpy()
                preds_float[e][i:i + len(x)] = model(x_adv).cpu().numpy()
    return {"root": root, "preds": preds, "preds_float": preds_float, "linf": linf, "example": example}


def _errors(pred: np.ndarray, t_gt: np.ndarray, q_gt: np.ndarray) -> dict[str, float]:
    """Mean and median position (m) and attitude (deg) errors of (N, 9) outputs against the labels."""
    from pipeline.rotations import attitude_error_deg, position_error, sixd_to_quat

    pos = position_error(pred[:, :3], t_gt)
    att = attitude_error_deg(sixd_to_quat(pred[:, 3:]), q_gt)
    return {"position_mean_m": float(pos.mean()), "position_median_m": float(np.median(pos)),
            "attitude_mean_deg": float(att.mean()), "attitude_median_deg": float(np.median(att))}


def _report(rows: list[dict[str, Any]], a: dict[str, Any], n: int) -> str:
    from pipeline.report import markdown_table

    table = markdown_table(
        [{"eps": r["eps"], "stored L-inf": r["stored_linf"], "pos. mean (m)": r["position_mean_m"],
          "pos. median (m)": r["position_median_m"], "att. mean (deg)": r["attitude_mean_deg"],
          "att. median (deg)": r["attitude_median_deg"]} for r in rows], decimals=3)
    float_table = markdown_table(
        [{"eps": r["eps"], "pos. mean, stored uint8 (m)": r["position_mean_m"],
          "pos. mean, float (m)": r["float_position_mean_m"], "att. mean, stored uint8 (deg)": r["attitude_mean_deg"],
          "att. mean, float (deg)": r["float_attitude_mean_deg"]} for r in rows[1:]], decimals=3)
    step = "" if a["method"] == "fgsm" else (
        f" ({a['steps']} steps, step size {a['step_size'] if a['step_size'] is not None else 'default'}"
        + (", random start" if a["method"] == "pgd" and a["random_start"] else "")
        + (f", momentum {a['momentum']}" if a["method"] == "mifgsm" else "") + ")")
    return f"""# Adversarial attack on the pose estimator

Attack: **{a['method']}**{step} on the **{a['loss']}** loss (`full` = the training loss with its
learned weights), L-inf budget eps in pixel units ([0, 1] images), {n} test images (time: reports/metrics/attack.json).
FGSM is `x' = clip(x + eps * sign(grad_x L), 0, 1)`.

Errors are measured on the adversarial images **as stored** in `datasets/attack/adv.zarr` (uint8):
each pixel's perturbation is rounded to the nearest 8-bit level, but never to zero, so every
perturbed pixel keeps the sign of its perturbation. "stored L-inf" is the largest stored change of a
pixel: it can exceed eps by up to half a level (eps = 0.01 = 2.55 levels is stored as 3 levels).

{table}
Position error `||t_pred - t_gt||`, attitude error `2 acos(|<q_pred, q_gt>|)`.
{_trend(rows)}

Same attack measured on the float adversarial images, before quantisation:

{float_table}
![the original, the stored adversarial image per eps and the amplified perturbation](figures/fgsm_example.png)
"""


def _trend(rows: list[dict[str, Any]]) -> str:
    """One sentence on whether the mean errors grow with eps (rows[1:] in any eps order)."""
    by_eps = sorted(rows[1:], key=lambda r: float(r["eps"]))
    out = []
    for key, what in (("position_mean_m", "position"), ("attitude_mean_deg", "attitude")):
        vals = [rows[0][key]] + [r[key] for r in by_eps]
        grows = all(b >= a for a, b in zip(vals, vals[1:]))
        out.append(f"the mean {what} error {'grows' if grows else 'does not grow'} monotonically from clean "
                   f"through eps = {', '.join(r['eps'] for r in by_eps)}")
    return "Over this test set, " + "; ".join(out) + "."
