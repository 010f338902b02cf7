"""Render the README's example sequence: a short approach with its motion file, for `rpod predict --motion`.

Writes examples/approach/NN.png (the default profile's camera and render settings, on black, as the stages
render) and examples/approach/motion.csv (rpodguard.sequence.MOTION_COLUMNS: the commanded displacement of the
target's position relative to the chaser since the previous frame, world axes, m, row 0 zero; the camera ->
world rotation, row-major). The approach is pipeline.geometry.trajectories.approach_trajectory with a seed of its
own (not a training, validation or test trajectory). A few seconds on one core. Run from the repository root:
`python scripts/example_sequence.py` (params.yaml on the default profile).
"""

from __future__ import annotations

import argparse
import csv
import shutil
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

OUT = ROOT / "examples" / "approach"
FRAMES = 8  # images in the sequence
START_XY = (6.0, -4.0)  # m: lateral offset at the first frame (world x, y)
START_RANGE, END_RANGE = 40.0, 12.0  # m: range at the first and last frame
SEED = 4141  # the example's own trajectory seed


def main(argv: list[str] | None = None) -> None:
    import cv2
    import numpy as np

    from pipeline.geometry.trajectories import approach_trajectory
    from pipeline.render.scene import Renderer
    from rpodguard.sequence import MOTION_COLUMNS
    from stages.config.build import intrinsics, scene_settings
    from stages.config.params import load

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=OUT, help="folder to (re)write")
    args = parser.parse_args(argv)
    p = load(ROOT / "params.yaml")
    if p.profile_name != "default":
        sys.exit(f"example_sequence: params.yaml is on the {p.profile_name!r} profile; run `rpod params default`")
    seq = approach_trajectory(FRAMES, START_XY, START_RANGE, END_RANGE, seed=SEED, path="projectile")
    shutil.rmtree(args.out, ignore_errors=True)
    args.out.mkdir(parents=True)
    with Renderer(intrinsics(p), scene_settings(p.render)) as renderer:
        for k in range(FRAMES):
            if not cv2.imwrite(str(args.out / f"{k:02d}.png"), renderer.render(seq.R[k], seq.t[k])[..., ::-1]):
                sys.exit(f"example_sequence: could not write {args.out / f'{k:02d}.png'}")
    commands = np.vstack([np.zeros(3), np.diff(seq.rel, axis=0)])
    with open(args.out / "motion.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(MOTION_COLUMNS)
        for u, c in zip(commands, seq.R_cam):
            writer.writerow([f"{v:.6f}" for v in (*u, *c.ravel())])
    print(f"wrote {FRAMES} images and motion.csv to {args.out} (ranges {np.linalg.norm(seq.t, axis=1).round(1)} m)")


if __name__ == "__main__":
    main()
