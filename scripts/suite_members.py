"""Which members a lean suite needs: from the full suite's parts (`rpod suite`, datasets/suite/), the share of the
full suite's worst case that a subset of its members finds, per model, error and eps.

    python scripts/suite_members.py                          # every 3-member subset of the gradient members
    python scripts/suite_members.py --size 2 --top 3         # 2-member subsets, the best 3 per model and error
    python scripts/suite_members.py --subset bpda/position,bpda/range_near,bpda/attitude   # named subsets only

For each subset the worst case is taken as the suite takes it (per frame, the largest error of any of its
members at any eps up to the row's, and at least the clean error: `nested_worst`), its mean over the frames
divided by the full suite's. The subset's members ran at the full suite's strength (its steps and restarts), so a
ratio is an upper bound of what a lean suite of these members with fewer steps finds; where the lean suite's
parts are there too, the lean suite as it ran is shown beside them (the ratio reports/suite.md prints).
Members are named as the full suite runs them; on the standard model (no clamp) a bpda member is its apgd member.
The frames are `rpod suite`'s (the test split): this chooses the attacker, whose figures can only grow with a
stronger choice; nothing about the pose models or the defense is chosen from it. Results only, printed.
"""

from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from pipeline.attacks.strongest import SuiteResult, join_eps, nested_worst  # noqa: E402
from pipeline.formats.suite import read_suite_part  # noqa: E402

ERRORS = ("position_m", "attitude_deg")


def load_run(folder: Path, model: str, kind: str) -> SuiteResult | None:
    """The `kind` (full | lean) suite's parts of `model` in `folder`, joined in increasing eps; None when there is
    none. Parts of one run share their key (one model file, frames and settings); SystemExit otherwise."""
    paths = sorted(folder.glob(f"{model}-{kind}-*.npz"), key=lambda p: float(p.stem.rsplit("-", 1)[1]))
    if not paths:
        return None
    keys = set()
    parts = []
    for path in paths:
        with np.load(path, allow_pickle=False) as z:
            key = str(z["key"])
        keys.add(key)
        parts.append(read_suite_part(path, key)[0])
    if len(keys) > 1:
        raise SystemExit(f"suite_members: {folder}/{model}-{kind}-*.npz are parts of {len(keys)} runs: keep one")
    return join_eps(parts)


def share(full: SuiteResult, members: tuple[str, ...], error: str) -> np.ndarray:
    """(E,) the mean over frames of the nested worst case of `members` (of `full`) over the full suite's."""
    index = [full.members.index(_name(full, m)) for m in members]
    clean = full.clean[error]
    ours = nested_worst(full.errors[error][index], clean).mean(axis=1)  # a member off its eps (square) counts as clean
    return ours / nested_worst(full.errors[error], clean).mean(axis=1)


def _name(full: SuiteResult, member: str) -> str:
    """`member` as `full` ran it (bpda/x is apgd/x on a model without a clamp); SystemExit when it did not run."""
    if member in full.members:
        return member
    plain = member.replace("bpda/", "apgd/")
    if plain in full.members:
        return plain
    raise SystemExit(f"suite_members: {member} is not a member of the full suite ({', '.join(full.members)})")


def candidates(full: SuiteResult, size: int) -> list[tuple[str, ...]]:
    """Every `size`-member subset of the full suite's gradient members (Square runs at one eps only)."""
    gradient = [m for m in full.members if not m.startswith("square/")]
    return list(itertools.combinations(gradient, size))


def lean_share(full: SuiteResult, lean: SuiteResult, error: str) -> np.ndarray:
    """(E',) the lean suite's nested worst case over the full suite's, at the eps both ran."""
    n = min(len(full.eps), len(lean.eps))
    if full.eps[:n] != lean.eps[:n]:
        raise SystemExit(f"suite_members: the lean parts' eps {lean.eps} are not the full parts' {full.eps}")
    ours = nested_worst(lean.errors[error][:, :n], full.clean[error]).mean(axis=1)
    return ours / nested_worst(full.errors[error][:, :n], full.clean[error]).mean(axis=1)


def report(folder: Path, subsets: list[tuple[str, ...]], size: int, top: int) -> None:
    """Print, per model with full parts in `folder`, each error's best subsets (or the named ones)."""
    found = False
    for model in ("robust", "standard"):
        full = load_run(folder, model, "full")
        if full is None:
            continue
        found = True
        lean = load_run(folder, model, "lean")
        eps = " / ".join(f"{e:g}" for e in full.eps)
        print(f"\n{model}: {full.clean['position_m'].size} frames, eps {eps}")
        for error in ERRORS:
            worst = nested_worst(full.errors[error], full.clean[error]).mean(axis=1)
            print(f"  {error}: full suite {' / '.join(f'{v:.2f}' for v in worst)}")
            if lean is not None:
                print(f"    lean suite as run ({', '.join(lean.members)}): {_ratios(lean_share(full, lean, error))}")
            rows = [(m, share(full, m, error)) for m in (subsets or candidates(full, size))]
            rows.sort(key=lambda r: -r[1].min())
            for members, ratio in rows if subsets else rows[:top]:
                print(f"    {', '.join(members)}: {_ratios(ratio)}")
    if not found:
        raise SystemExit(f"suite_members: no full-suite parts (<model>-full-<eps>.npz) in {folder}: run `rpod suite`")


def _ratios(values: np.ndarray) -> str:
    return " / ".join(f"{v:.3f}" for v in values) + f" (least {values.min():.3f})"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folder", nargs="?", type=Path, default=Path("datasets/suite"), help="the parts' folder")
    parser.add_argument("--subset", action="append", default=[], help="members, comma-separated (repeatable)")
    parser.add_argument("--size", type=int, default=3, help="members per subset when none is named (default 3)")
    parser.add_argument("--top", type=int, default=5, help="subsets shown per model and error (default 5)")
    args = parser.parse_args()
    if not args.folder.is_dir():
        raise SystemExit(
            f"suite_members: {args.folder} is not a folder of suite parts (rpod suite writes datasets/suite/)"
        )
    if args.size < 1 or args.top < 1:
        raise SystemExit(f"suite_members: --size and --top must be >= 1, got {args.size} and {args.top}")
    report(args.folder, [tuple(s.split(",")) for s in args.subset], args.size, args.top)


if __name__ == "__main__":
    main()
