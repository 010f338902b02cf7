"""Issue 39: why the shipped chain's no-attack detect-and-recover run ends in a hold, measured.

Flies the guidance stage's own no-attack run of the shipped chain (true-state dynamics, detect-and-recover, the
stage's plan, seeds and execution errors: stages/guidance.py) in one process and records, after every frame, the
protection level and its parts (pipeline/defense/protection.py; the split of pipeline/evaluation/availability.py):
the noise term, the slow ramp c sum|W|, the transients h TV+ and a restart's offset, against the alert limit at
the true range, and the error of the estimate the guidance flew on (m; where it exceeds the PL, the frames and the
largest error / PL). The ramp and the transients are what leaving each out removes from the PL: the bias adds them over
the world axes in quadrature, so the parts add up to a little less than the PL (millimetres on the approach).
Prints every fifth frame and the last ones, and the frame where the chain first stops being available; `--json
PATH` writes every frame's record. A measurement of the committed models, not a choice.

Usage (in a checkout with the default run's models/, e.g. after `dvc checkout`):
python scripts/recover_hold.py [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
from stages.config.cpu import pin_cpu_isa  # noqa: E402

pin_cpu_isa()


def _record(defense: Any, out: Any) -> dict[str, Any]:
    """One frame's PL (m) and its parts (pipeline/guidance/law.py `protection_parts`) after `defense.step` returned
    `out`; the PL is None before it exists."""
    from pipeline.guidance.law import protection_parts

    row: dict[str, Any] = {"mode": out.mode, "available": bool(out.available), "pl": None}
    if math.isfinite(defense.filter.protection_level):
        noise, ramp, transients, offset = protection_parts(defense)
        row |= {"pl": defense.filter.protection_level, "noise": noise, "ramp": ramp, "transients": transients}
        row["offset"] = offset
    return row


def fly(params: Any) -> tuple[Any, list[dict[str, Any]]]:
    """(the no-attack detect-and-recover run's RendezvousResult, one record per frame) of the shipped chain."""
    import pipeline.defense.fusion as fusion
    from pipeline.seeds import seed_for
    from stages import guidance as stage
    from stages.artifacts.models import load_chain
    from stages.artifacts.paths import SHIPPED
    from stages.config.build import intrinsics, scene_settings
    from stages.engine import chunks
    from stages.engine import pool as engine
    from stages.engine.guidance_worker import Flight, GuidanceSetup, GuidanceWorker

    settings, grid = stage._plan(params.guidance)
    plan = stage._grid_plan(params, settings, grid, stage._in_loop(params.integrity, settings))
    shipped = load_chain(params, SHIPPED, defended=True)
    K = intrinsics(params)
    scene, _ = chunks.prepare(K, scene_settings(params.render), engine.engine_settings(params))
    setup = GuidanceSetup(params, K, scene, str(ROOT), shipped.defended, plan, seed_for(params.seed, "guidance"), None)
    rows: list[dict[str, Any]] = []
    step = fusion.Defense.step

    def recorded(self: Any, *args: Any, **kwargs: Any) -> Any:
        out = step(self, *args, **kwargs)
        rows.append(_record(self, out))
        return out

    fusion.Defense.step = recorded
    try:
        worker = GuidanceWorker(setup)
        result, _ = worker.run(Flight(chain="shipped", dynamics="true_state", defense="recover", cell=None))
        worker.close()
    finally:
        fusion.Defense.step = step
    return result, rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", type=Path, help="write every frame's record (m) to this file")
    args = parser.parse_args()
    if args.json is not None and not args.json.parent.is_dir():
        parser.error(f"--json {args.json}: the folder {args.json.parent} does not exist")
    import numpy as np

    from pipeline.defense.integrity import alert_limit
    from stages.config.build import alert_limit_settings
    from stages.config.params import load

    params = load()
    result, rows = fly(params)
    limit = alert_limit_settings(params)
    for i, row in enumerate(rows):  # frame i is taken at positions[i], before step i moves the chaser
        row["true_range"] = float(np.linalg.norm(result.positions[i]))
        row["al"] = float(alert_limit(row["true_range"], limit))
        error = float(np.linalg.norm(result.acted[i] - result.positions[i]))  # NaN where the chaser held
        row["error"] = error if math.isfinite(error) else None
    print(f"outcome: {result.outcome}, {result.miss:.2f} m from the goal after {len(rows)} frames")
    over = [i for i, r in enumerate(rows) if r["pl"] is not None and r["error"] is not None and r["error"] > r["pl"]]
    if over:
        worst = max(over, key=lambda i: rows[i]["error"] / rows[i]["pl"])
        print(
            f"the flown estimate's error exceeds the PL on {len(over)} frames ({over[0]}-{over[-1]}, "
            f"{rows[over[-1]]['true_range']:.1f}-{rows[over[0]]['true_range']:.1f} m); the largest error / PL "
            f"{rows[worst]['error'] / rows[worst]['pl']:.2f} at frame {worst}: error {rows[worst]['error']:.2f} m, PL "
            f"{rows[worst]['pl']:.2f} m (noise {rows[worst]['noise']:.2f}, ramp {rows[worst]['ramp']:.2f})"
        )
    lost = next((i for i, r in enumerate(rows) if r["pl"] is not None and r["pl"] > r["al"]), None)
    for i, r in enumerate(rows):
        if r["pl"] is not None and (i % 5 == 0 or i >= len(rows) - 3 or i == lost):
            flown = "held" if r["error"] is None else f"flown error {r['error']:.2f}"
            print(
                f"frame {i:3d}{' (first PL > AL)' if i == lost else ''}: range {r['true_range']:.2f} m, AL "
                f"{r['al']:.2f}, PL {r['pl']:.2f}: noise {r['noise']:.2f}, ramp {r['ramp']:.2f}, transients "
                f"{r['transients']:.2f}, offset {r['offset']:.2f}; {r['mode']}, {flown}"
            )
    if args.json:
        from pipeline.io.atomic import atomic_write_text

        atomic_write_text(args.json, json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
