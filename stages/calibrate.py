"""`rpod calibrate`: fit the defense on validation trajectories (issue 16).

Runs the safety chain clean over the validation approaches `rpod eval_render` rendered into
datasets/val_render/ (seed `defense.val_seed`, never the evaluation seed), fits the pose model's
range-dependent measurement noise and bias (`pipeline.defense.noise.fit_noise`, `defense.noise_bins` range
bins), inflates its standard deviations by the smallest factor that keeps the defended chain's false
alarms on those clean frames within `defense.target_false_alarm` (a Gaussian fit under-states the
errors' heavy, correlated tails), and writes models/defense.json: the noise model, the detector threshold and pose-model hash
it belongs to, and the defense's false alarms on those clean validation frames.
"""
from __future__ import annotations

from typing import Any

import numpy as np
import typer

from pipeline.io.atomic import write_json
from pipeline.pose.labels import TARGET
from stages.artifacts.paths import DEFENSE
from stages.artifacts.readers import chaser_motion, read_eval_render
from stages.artifacts.models import DEFENSE_FORMAT, load_chain
from stages.config.build import defense_settings
from stages.config.device import torch_setup
from stages.config.schema import Params
from stages.errors import StageError



def main(params: Params) -> None:
    """Fit the defense's measurement-noise model on clean validation trajectories -> models/defense.json.

    Params: `defense` (noise_bins, val_trajectories, val_seed and the filter settings), `evaluate.batch_size`.
    """
    from tqdm import tqdm

    from pipeline.defense.chain import run_sequence
    from pipeline.evaluation.sequences import defend_trace
    from pipeline.defense.noise import fit_noise, inflate, smallest_inflation
    from pipeline.geometry.rotations import sixd_to_matrix

    d = params.defense
    torch_setup(params)
    images, poses, _ = read_eval_render(params, validation=True)
    chain, _, model_hash = load_chain(params)
    targets = poses[TARGET].to_numpy(np.float32)
    batch = params.evaluate.batch_size
    with tqdm(total=-(-len(images) // batch), desc="calibrate", unit="batch", dynamic_ncols=True) as bar:
        def progress(it):
            for i in it:
                yield i
                bar.update(1)

        res = run_sequence(chain, images, targets, np.zeros(len(images), bool), None, batch, progress)
    try:
        noise = fit_noise(targets[:, :3], res.pose[:, :3], sixd_to_matrix(targets[:, 3:]),
                          sixd_to_matrix(res.pose[:, 3:]), bins=d.noise_bins)
    except ValueError as e:
        raise StageError(f"calibrate on {len(images)} validation frames (defense.val_trajectories, "
                         f"defense.noise_bins): {e}") from None
    settings, motion = defense_settings(d, chain.threshold)
    R_cam, u = chaser_motion(poses)
    groups = [g.index.to_numpy() for _, g in poses.groupby("trajectory", sort=True)]

    def flags(model: Any) -> np.ndarray:
        """The defended chain's flags on the clean validation frames with noise model `model`."""
        return np.concatenate([defend_trace(settings, motion, model, res.pose[i], res.prob[i], R_cam[i], u[i]).flag
                               for i in groups])

    k, rates = smallest_inflation(lambda k: flags(inflate(noise, k)).mean(), d.target_false_alarm)
    fitted, noise = noise, inflate(noise, k)
    flag = flags(noise)
    doubt = settings.threshold if settings.update_below is None else settings.update_below
    cal = {"format": DEFENSE_FORMAT, "pose_model_hash": model_hash, "threshold": chain.threshold,
           "noise": noise.as_dict(), "fitted_noise": fitted.as_dict(), "inflation": k,
           "validation": {"trajectories": d.val_trajectories, "seed": d.val_seed, "frames": len(images),
                          "fpr_clean": round(100 * float(flag.mean()), 3),
                          "fpr_clean_by_inflation": {f"{f:g}": round(100 * r, 3) for f, r in rates.items()},
                          "target_fpr": 100 * d.target_false_alarm,
                          "detector_fpr_clean": round(100 * float(res.flag.mean()), 3),
                          "doubtful_fraction": float(np.mean(res.prob >= doubt)),
                          "prob_quantiles": {f"{q:g}": float(np.quantile(res.prob, q)) for q in (0.5, 0.9, 0.99)}}}
    write_json(DEFENSE, cal)
    typer.echo(f"calibrate: noise model from {len(images)} clean validation frames, inflated x{k:g} (target "
               f"{100 * d.target_false_alarm:g}%); defended FPR on them {cal['validation']['fpr_clean']:.2f}% -> {DEFENSE}")
