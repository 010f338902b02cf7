"""Run `rpod suite`'s parts on another machine (a GPU box that has torch and numpy but not the project's data,
DVC cache or environment) and bring them back: `rpod suite` reads them as its own.

    python scripts/suite_parts.py export JOB                # here: test frames, both pose models, the plan -> JOB/
    python scripts/suite_parts.py run JOB OUT [--minutes M] [--only standard/lean]  # there: parts -> OUT/*.npz
    cp OUT/*.npz datasets/suite/ && rpod suite               # here: matching parts are read, the rest computed

`export` writes JOB/frames.npz (the test split's uint8 images and targets, as `rpod suite` loads them), JOB/<name>.pt
(each pose model file) and JOB/plan.json (each suite run of `rpod suite`: model, suite, settings and the key of
its parts, stages/engine/suite.py `suite_jobs`). `run` needs numpy, torch and this checkout's pipeline/ only: it
runs each part with pipeline.attacks.strongest.run_suite on `--device` (default: cuda when there is one), in the
stage's order, skipping the parts already in OUT, and stores each as it finishes (pipeline/formats/suite.py, with
its key re-derived from the files it ran on and checked against the plan). With `--minutes` it starts no part that
would end past the budget (judged by the run's last part) and exits with status 3; run it again to go on.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def export(job: Path) -> None:
    """The test frames, both pose models and the plan of `rpod suite` (the params.yaml of this checkout) -> job/."""
    from stages.artifacts import data
    from stages.config.params import load
    from stages.engine.suite import suite_jobs

    params = load()
    test = data.load_split(params, "test")
    images, targets = np.stack([test.images[i] for i in range(len(test))]), test.targets.astype(np.float64)
    job.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(job / "frames.npz", images=images, targets=targets)
    runs = []
    for j in suite_jobs(params, images, targets):
        shutil.copyfile(j.path, job / f"{j.name}.pt")
        config = {k: list(v) if isinstance(v, tuple) else v for k, v in vars(j.config).items()}
        parts = {f"{e:g}": j.part_path(e).name for e in params.suite.eps}
        runs.append({"name": j.name, "kind": j.kind, "key": j.key, "config": config, "parts": parts})
    plan = {"eps": [float(e) for e in params.suite.eps], "amp": params.amp, "runs": runs}
    (job / "plan.json").write_text(json.dumps(plan, indent=1))
    print(f"suite_parts: {len(images)} test frames, {len(runs)} runs x {len(plan['eps'])} eps -> {job}/")


def run(job: Path, out: Path, minutes: float | None, device: str | None, only: list[str]) -> int:
    """Every part of job/plan.json not yet in out/, in order, on `device` (of the runs `only` names as
    model/suite, e.g. standard/lean; none: every run); 0 when all are there, 3 when the budget stopped it."""
    import torch

    from pipeline.attacks.strongest import SuiteConfig, run_suite
    from pipeline.formats.models import load_pose
    from pipeline.formats.suite import part_key, read_suite_part, write_suite_part
    from pipeline.io.atomic import file_hash

    plan, images, targets = _read_job(job)
    dev = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
    name = f"cuda ({torch.cuda.get_device_name(dev)})" if dev.type == "cuda" else "cpu"
    torch.backends.cudnn.benchmark = dev.type == "cuda"  # fixed shapes: the fastest convolution per layer
    out.mkdir(parents=True, exist_ok=True)
    start, budget = time.perf_counter(), None if minutes is None else 60.0 * minutes
    for r in plan["runs"]:
        if only and f"{r['name']}/{r['kind']}" not in only:
            continue
        config = SuiteConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in r["config"].items()})
        path = job / f"{r['name']}.pt"
        if part_key(file_hash(path, 64), images, targets, config) != r["key"]:
            raise SystemExit(f"suite_parts: {path} or frames.npz is not what the plan was made from")
        model = load_pose(path, dev, plan["amp"]).model
        last: list[float] = []

        def part(e: float, compute: Any, r: dict[str, Any] = r, last: list[float] = last) -> Any:
            target = out / r["parts"][f"{e:g}"]
            stored = read_suite_part(target, r["key"])
            if stored is not None:
                return stored[0]
            if budget is not None and time.perf_counter() - start + (last[-1] if last else 0.0) > budget:
                raise TimeoutError
            t0 = time.perf_counter()
            result = compute()
            last.append(time.perf_counter() - t0)
            write_suite_part(target, result, r["key"], name)
            print(f"suite_parts: {target.name} in {last[-1]:.1f} s ({name})", flush=True)
            return result

        try:
            run_suite(model, images, targets, plan["eps"], config, device=dev, part=part)
        except TimeoutError:
            print(f"suite_parts: stopped at the {minutes:g}-minute budget; run again to go on", flush=True)
            return 3
    print(f"suite_parts: every part in {out}/", flush=True)
    return 0


def _read_job(job: Path) -> tuple[dict[str, Any], np.ndarray, np.ndarray]:
    """(plan, images, targets) of an exported job folder; SystemExit with one line naming the folder otherwise."""
    try:
        plan = json.loads((job / "plan.json").read_text())
        with np.load(job / "frames.npz") as z:
            images, targets = z["images"], z["targets"]
    except (OSError, ValueError, KeyError) as e:
        raise SystemExit(f"suite_parts: the job folder {job} cannot be read ({e}): export it again") from None
    return plan, images, targets


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    e = sub.add_parser("export", help="test frames, pose models and the plan of `rpod suite` -> JOB/")
    e.add_argument("job", type=Path)
    r = sub.add_parser("run", help="the plan's parts not yet in OUT -> OUT/")
    r.add_argument("job", type=Path)
    r.add_argument("out", type=Path)
    r.add_argument("--minutes", type=float, default=None, help="time budget (no part starts that would end past it)")
    r.add_argument("--device", default=None, help="torch device (default: cuda when there is one, else cpu)")
    r.add_argument("--only", action="append", default=[], help="a run as model/suite, e.g. standard/lean (repeatable)")
    args = parser.parse_args()
    if args.command == "export":
        export(args.job)
    else:
        sys.exit(run(args.job, args.out, args.minutes, args.device, args.only))


if __name__ == "__main__":
    main()
