"""The clean runs a defense is calibrated on (`rpod calibrate`) and re-checked on (`rpod heldout`): the chain's
outputs on clean frames, the runs as the defense sees them, and the pose network's noise model fitted on them."""

from __future__ import annotations

from typing import Any

import numpy as np

from stages.artifacts.readers import chaser_motion
from stages.errors import StageError


def chain_outputs(chain: Any, images: np.ndarray, batch: int, desc: str) -> tuple[np.ndarray, np.ndarray]:
    """The onboard chain on clean frames (N, H, W, 3) uint8: (pose (N, 9) [m, 6-D], detector probability (N,)),
    float64, with a progress bar named `desc`."""
    from tqdm import tqdm

    from pipeline.defense.chain import run_sequence

    with tqdm(total=-(-len(images) // batch), desc=desc, unit="batch", dynamic_ncols=True) as bar:

        def progress(it):
            for i in it:
                yield i
                bar.update(1)

        res = run_sequence(
            chain, images, np.zeros((len(images), 9), np.float32), np.zeros(len(images), bool), None, batch, progress
        )
    return res.pose.astype(np.float64), res.prob.astype(np.float64)


def clean_runs(poses: Any, pose: np.ndarray, prob: np.ndarray) -> tuple[list[Any], list[np.ndarray]]:
    """Per trajectory of an eval_render-like poses table (in trajectory order): (its clean run: pose, detector
    probability, chaser motion; its true relative positions (n, 3), world, m)."""
    from pipeline.defense.calibration import CleanRun

    R_cam, u = chaser_motion(poses)
    groups = [g.index.to_numpy() for _, g in poses.groupby("trajectory", sort=True)]
    runs = [CleanRun(pose[i], prob[i], R_cam[i], u[i]) for i in groups]
    truths = [poses[["rel_x", "rel_y", "rel_z"]].to_numpy(np.float64)[i] for i in groups]
    return runs, truths


def fit_pose_noise(targets: np.ndarray, pose: np.ndarray, bins: int, what: str) -> Any:
    """The pose network's range-dependent noise and bias (pipeline.defense.noise.fit_noise) from its clean
    estimates `pose` against `targets` ((N, 9) [m, 6-D]) in `bins` range bins; a fit that fails stops with one
    line naming `what` (the frames and the params that sized them)."""
    from pipeline.defense.noise import fit_noise
    from pipeline.geometry.rotations import sixd_to_matrix

    try:
        return fit_noise(
            targets[:, :3], pose[:, :3], sixd_to_matrix(targets[:, 3:]), sixd_to_matrix(pose[:, 3:]), bins=bins
        )
    except ValueError as e:
        raise StageError(f"fit the noise model on {what}: {e}") from None
