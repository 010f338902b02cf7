"""Issue 28, item 3: does the allocentric attitude (relative to the viewing ray) train a better pose model?

Trains the standard recipe of `rpod train` (params.yaml's `train` section, its seed, its validation split,
40 epochs at the default profile) once more with the attitude targets made allocentric
(pipeline.geometry.rotations.to_allocentric: the target's rotation relative to the ray through its centre,
so the same appearance anywhere in the image has the same label) and turns its predictions back into
camera-frame attitudes with the predicted position (to_egocentric). Both models are compared on the
**validation** split only (the decision); the test split is not read. The egocentric model is the run's
models/pose.pt, trained by `rpod train` from the same seed and split (checkpoints are bit-identical run to
run under one instruction-set cap, reports/benchmarks.md). Writes the section "Allocentric attitude" of reports/trials.md (results only).

Usage (in a checkout that ran `dvc repro train`): python scripts/allocentric_trial.py [--epochs N]
(--epochs: fewer than train.epochs for a quick check only; the comparison is fair at train.epochs).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
from stages.config.cpu import pin_cpu_isa  # noqa: E402

pin_cpu_isa()

import numpy as np  # noqa: E402


def allocentric_targets(targets: np.ndarray) -> np.ndarray:
    """(N, 9) targets (t in m, 6-D egocentric rotation) -> the same with the 6-D allocentric rotation."""
    from pipeline.geometry.allocentric import to_allocentric
    from pipeline.geometry.rotations import matrix_to_6d, sixd_to_matrix

    t = np.asarray(targets, np.float64)
    return np.concatenate([t[:, :3], matrix_to_6d(to_allocentric(sixd_to_matrix(t[:, 3:]), t[:, :3]))], 1)


def egocentric_predictions(pred: np.ndarray) -> np.ndarray:
    """(N, 9) allocentric predictions -> camera-frame ones, composed with the predicted position's ray."""
    from pipeline.geometry.allocentric import to_egocentric
    from pipeline.geometry.rotations import matrix_to_6d, sixd_to_matrix

    p = np.asarray(pred, np.float64)
    return np.concatenate([p[:, :3], matrix_to_6d(to_egocentric(sixd_to_matrix(p[:, 3:]), p[:, :3]))], 1)


def errors(pred: np.ndarray, target: np.ndarray) -> dict[str, float]:
    """Mean position (m), attitude, tilt and roll (deg) errors, with the attitude's 95% interval."""
    from pipeline.pose.metrics import pose_errors, tilt_roll_deg
    from pipeline.stats import mean_interval

    pos, att = pose_errors(pred, target)
    tilt, roll = tilt_roll_deg(pred, target)
    _, lo, hi = mean_interval(att)
    return {
        "position_m": float(pos.mean()),
        "attitude_deg": float(att.mean()),
        "attitude_ci": (lo, hi),
        "tilt_deg": float(tilt.mean()),
        "roll_deg": float(roll.mean()),
    }


def main(epochs: int | None = None) -> None:
    import torch

    from pipeline.io.atomic import atomic_write_text
    from pipeline.pose.loss import PoseLoss
    from pipeline.pose.metrics import pose_errors
    from pipeline.pose.model import PoseNet
    from pipeline.pose.train import fit, make_deterministic, predict
    from pipeline.seeds import seed_for
    from pipeline.stats import mean_interval
    from stages.artifacts import data
    from stages.artifacts.paths import POSE
    from stages.config import params as params_mod
    from stages.config.build import train_config
    from stages.config.device import torch_setup

    os.chdir(ROOT)
    missing = [str(p) for p in (POSE, Path("datasets/labels.parquet")) if not (ROOT / p).exists()]
    if missing:  # before ten minutes of training, not after
        raise SystemExit(f"allocentric trial: {', '.join(missing)} not found: run `dvc repro train` first")
    params = params_mod.load()
    device = torch_setup(params)
    cfg = train_config(params.train, epochs or params.train.epochs, seed_for(params.seed, "train"))
    make_deterministic(cfg.seed)
    model = PoseNet(float(params.train.width), float(params.train.dropout))
    (train_split, train_set, _), (val_split, val_set) = data.training_sets(params, cfg.seed)
    ego_val = val_set.targets.numpy().astype(np.float64)
    for ds in (train_set, val_set):
        ds.targets = torch.tensor(allocentric_targets(ds.targets.numpy()), dtype=torch.float32)
    model.set_output_bias(train_set.targets[:, :3].mean(0), train_set.targets[:, 3:].mean(0))
    model.place(device, params.amp)
    print(
        f"allocentric trial: {len(train_split)} train / {len(val_split)} validation images, {cfg.epochs} epochs",
        flush=True,
    )
    result = fit(model, PoseLoss("mean"), train_set, val_set, cfg, device)
    model.load_state_dict(result.best_state)
    allo = egocentric_predictions(predict(model, val_set, device=device))
    ego_model = _load_standard(ROOT / POSE)
    ego = predict(ego_model, val_set).astype(np.float64)
    diff = mean_interval(pose_errors(allo, ego_val)[1] - pose_errors(ego, ego_val)[1])
    rows = [
        {"attitude parametrisation": name, "best epoch": epoch, **_row(errors(p, ego_val))}
        for name, p, epoch in (
            ("egocentric (models/pose.pt, `rpod train`)", ego, "-"),
            ("allocentric (this trial)", allo, result.best_epoch),
        )
    ]
    from pipeline.report.markdown import replace_section

    text = _report(params, cfg.epochs, len(val_split), rows, diff)
    page = ROOT / "reports" / "trials.md"
    old = page.read_text() if page.exists() else "# Trials\n"
    atomic_write_text(page, replace_section(old, "Allocentric attitude", text))
    print(text)


def _report(params: Any, epochs: int, n_val: int, rows: list[dict[str, Any]], diff: tuple[float, float, float]) -> str:
    """reports/trials.md's section "Allocentric attitude": the trial's recipe, the table `rows` on its `n_val`
    validation images and the paired allocentric minus egocentric attitude error (mean, 95% interval; deg)."""
    from pipeline.report.markdown import markdown_table

    return f"""`scripts/allocentric_trial.py`: the standard recipe (`train` params, seed {params.seed}, {epochs} epochs,
{params.render.width}x{params.render.height}) trained with allocentric attitude targets (relative to the viewing ray,
turned back with the predicted position), against the egocentric model of `rpod train`, on the
{n_val} **validation** images of the same split (the decision; the test split is not read).
Means; attitude with its 95% interval (pipeline.stats.mean_interval).

{markdown_table(rows)}
Paired over the same images, allocentric minus egocentric attitude error: {diff[0]:+.2f} [{diff[1]:+.2f}, {diff[2]:+.2f}] deg.
"""


def _row(e: dict[str, float]) -> dict[str, str]:
    lo, hi = e["attitude_ci"]
    return {
        "position (m)": f"{e['position_m']:.3f}",
        "attitude (deg)": f"{e['attitude_deg']:.2f} [{lo:.2f}, {hi:.2f}]",
        "tilt (deg)": f"{e['tilt_deg']:.2f}",
        "roll (deg)": f"{e['roll_deg']:.2f}",
    }


def _load_standard(path: Path):
    from pipeline.formats.models import load_pose

    return load_pose(path).model


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--epochs", type=int, default=None, help="epochs (default: train.epochs)")
    main(parser.parse_args().epochs)
