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
import zipfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from pipeline.attacks.strongest import SuiteResult, join_eps, nested_worst, ratio_rows  # noqa: E402
from pipeline.formats.suite import read_suite_part  # noqa: E402

ERRORS = ("position_m", "attitude_deg")


def load_run(folder: Path, model: str, kind: str, eps: tuple[float, ...] | None = None) -> SuiteResult | None:
    """The `kind` (full | lean) suite's parts of `model` in `folder` (those at `eps` only, when given), joined in
    increasing eps; None when there is none. Parts of one run share their key (one model file, frames and
    settings); SystemExit with one line naming the file otherwise, or when a part is misnamed or damaged."""
    parts: dict[float, Path] = {}
    for path in folder.glob(f"{model}-{kind}-*.npz"):
        try:
            parts[float(path.stem.rsplit("-", 1)[1])] = path
        except ValueError:
            raise SystemExit(f"suite_members: {path}: not named <model>-<suite>-<eps>.npz") from None
    paths = [parts[e] for e in sorted(parts) if eps is None or e in eps]
    if not paths:
        return None
    keys, results = set(), []
    for path in paths:
        try:
            with np.load(path, allow_pickle=False) as z:
                key = str(z["key"])
            keys.add(key)
            results.append(read_suite_part(path, key)[0])
        except (OSError, KeyError, ValueError, zipfile.BadZipFile) as e:
            raise SystemExit(f"suite_members: {path}: not a readable suite part ({e})") from None
    if len(keys) > 1:
        raise SystemExit(f"suite_members: {folder}/{model}-{kind}-*.npz are parts of {len(keys)} runs: keep one")
    return join_eps(results)


def share(full: SuiteResult, members: tuple[str, ...], error: str) -> np.ndarray:
    """(E,) the mean over frames of the nested worst case of `members` (of `full`) over the full suite's."""
    index = [full.members.index(_name(full, m)) for m in members]
    clean = full.clean[error]
    ours = nested_worst(full.errors[error][index], clean).mean(axis=1)  # a member off its eps (square) counts as clean
    return ours / full.worst(error).mean(axis=1)


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


def lean_share(folder: Path, model: str, full: SuiteResult, error: str) -> tuple[tuple[str, ...], np.ndarray] | None:
    """The lean suite's members and its worst case over the full suite's (`ratio_rows`) at the eps both ran; None
    when `folder` has no lean part at the full suite's eps."""
    lean = load_run(folder, model, "lean", full.eps)
    if lean is None:
        return None
    reference = full if lean.eps == full.eps else load_run(folder, model, "full", lean.eps)
    rows = [r for r in ratio_rows(lean, reference) if r["error"] == error]
    return lean.members, np.array([r["ratio"] for r in rows])


def report(folder: Path, subsets: list[tuple[str, ...]], size: int, top: int) -> None:
    """Print, per model with full parts in `folder`, each error's best subsets (or the named ones)."""
    found = False
    for model in ("robust", "standard"):
        full = load_run(folder, model, "full")
        if full is None:
            continue
        found = True
        eps = " / ".join(f"{e:g}" for e in full.eps)
        print(f"\n{model}: {full.clean['position_m'].size} frames, eps {eps}")
        for error in ERRORS:
            print(f"  {error}: full suite {' / '.join(f'{v:.2f}' for v in full.worst(error).mean(axis=1))}")
            lean = lean_share(folder, model, full, error)
            if lean is not None:
                print(f"    lean suite as run ({', '.join(lean[0])}): {_ratios(lean[1])}")
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
