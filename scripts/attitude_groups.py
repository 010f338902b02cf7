"""Issue 38, item 3: the standard pose model's errors split by target-attitude group.

The 13 training approaches (pipeline/geometry/trajectories.py) come in two groups: sequences 0-4 with the target at
rest (attitude identity) and sequences 5-12 with a target attitude drawn afresh every frame (render.target_attitude:
per_frame; the paper's Table 1 fixes one attitude per sequence). This prints, per group and split, the mean position,
attitude, tilt and roll errors of models/pose.pt with 95% bootstrap intervals over the sequences, and the rotating
minus fixed difference (pipeline/pose/decomposition.py). It reads the test split: a measurement of the committed
model, not a choice.

Usage (in a checkout with the default run's datasets/ and models/, e.g. after `dvc checkout`):
python scripts/attitude_groups.py [--splits test train]
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
from stages.config.cpu import pin_cpu_isa  # noqa: E402

pin_cpu_isa()


def _ci(v: tuple[float, float, float], digits: int) -> str:
    """(mean, lo, hi) as "m [lo, hi]"."""
    return f"{v[0]:.{digits}f} [{v[1]:.{digits}f}, {v[2]:.{digits}f}]"


def main(argv: list[str]) -> None:
    import numpy as np
    import torch

    from pipeline.geometry.trajectories import attitude_groups
    from pipeline.pose.decomposition import bootstrap_difference, group_errors
    from pipeline.pose.metrics import pose_errors
    from pipeline.report.markdown import markdown_table
    from stages.artifacts.data import load_split
    from stages.artifacts.models import load_pose
    from stages.config.params import load

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--splits", nargs="+", default=["test"], choices=["train", "test"])
    args = parser.parse_args(argv)
    params = load()
    torch.set_num_threads(params.threads or 1)
    pose = load_pose(params)
    rows, diffs = [], []
    for split in args.splits:
        data = load_split(params, split)
        x = np.asarray(data.images)
        with torch.no_grad():
            pred = np.concatenate(
                [
                    pose.model(torch.from_numpy(x[i : i + 64]).permute(0, 3, 1, 2).float() / 255).numpy()
                    for i in range(0, len(x), 64)
                ]
            )
        seq = data.labels["sequence"].to_numpy()
        groups = attitude_groups(seq)
        for g, e in group_errors(pred, data.targets, seq, groups).items():
            rows.append(
                {
                    "split": split,
                    "group": g,
                    "sequences": e["sequences"],
                    "frames": e["frames"],
                    "position (m)": _ci(e["position_m"], 3),
                    "attitude (deg)": _ci(e["attitude_deg"], 2),
                    "tilt (deg)": _ci(e["tilt_deg"], 2),
                    "roll (deg)": _ci(e["roll_deg"], 2),
                }
            )
        pos, att = pose_errors(pred, data.targets)
        rotating = groups == "rotating"
        diffs.append(
            {
                "split": split,
                "attitude, rotating - fixed (deg)": _ci(bootstrap_difference(att, seq, rotating), 2),
                "position, rotating - fixed (m)": _ci(bootstrap_difference(pos, seq, rotating), 3),
            }
        )
    print(f"models/pose.pt (hash {pose.hash}); 95% percentile bootstrap over sequences\n")
    print(markdown_table(rows))
    print(markdown_table(diffs))


if __name__ == "__main__":
    main(sys.argv[1:])
