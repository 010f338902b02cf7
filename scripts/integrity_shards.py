"""Issue 39: what a running or killed `rpod integrity` has found so far, from the shards it has written.

The full grid takes hours per trajectory on a CPU and writes each (chain, trajectory) share to
datasets/integrity_shards/<chain>/<trajectory>.pkl as it finishes (stages/artifacts/shards.py). This prints, for
every shard there, each attacker's measures per eps as the page judges them (pipeline.evaluation.campaign.judge:
largest error / AL on the available frames, against the single-frame AL, error / PL, the last frame's trusted error
in m, flagged frames, availability), the largest error / AL nested in eps, and the no-attack flight's. A look at
the stage's own output folder, not a result: the page and metrics come from `rpod integrity` when every share is
flown, and a shard made with other params or models (the stage would fly it again) is printed all the same.

Usage (in the checkout that runs `rpod integrity`): python scripts/integrity_shards.py [FOLDER]
"""

from __future__ import annotations

import argparse
import math
import pickle
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

COLUMNS = (
    "attacker",
    "eps",
    "error / AL",
    "nested",
    "single-frame",
    "error / PL",
    "final (m)",
    "flags",
    "available (%)",
)


def share_rows(share: Any, single: Any) -> list[dict[str, Any]]:
    """Rows of one shard's share (a pipeline.evaluation.campaign.TrackFlights): per (attacker, eps) run its measures,
    then the no-attack flight's; `single` the single-frame AL settings."""
    import numpy as np

    from pipeline.evaluation.campaign import judge

    rows, nested = [], {}
    for name, eps, flown, mask in share.runs:
        m = judge(flown, mask, single)
        if not math.isnan(m.max_error_al):
            nested[name] = max(nested.get(name, m.max_error_al), m.max_error_al)
        rows.append(_row(name, f"{eps:g}", m, nested.get(name, math.nan)))
    clean = judge(share.clean, np.zeros(len(share.clean.trace.flag), bool), single)
    return rows + [_row("no attack", "-", clean, clean.max_error_al)]


def _row(name: str, eps: str, m: Any, nested: float) -> dict[str, Any]:
    def f(x: float) -> str:
        return "-" if math.isnan(x) else f"{x:.2f}"

    values = (f(m.max_error_al), f(nested), f(m.max_error_al_single), f(m.max_error_pl), f(m.final_error))
    return dict(zip(COLUMNS, (name, eps, *values, m.flags, f"{100 * m.availability:.1f}")))


def main(argv: list[str] | None = None) -> int:
    from pipeline.io.errors import DataError
    from pipeline.report.markdown import markdown_table
    from stages.artifacts.paths import INTEGRITY_SHARDS
    from stages.config.build import alert_limit_settings
    from stages.config.params import load
    from stages.config.sections import ParamsError

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folder", nargs="?", default=str(INTEGRITY_SHARDS), help="the shards' folder")
    folder = Path(parser.parse_args(argv).folder)
    shards = sorted(folder.glob("*/*.pkl"))
    if not shards:
        print(f"integrity_shards: no shard under {folder} (rpod integrity writes one per chain and trajectory)")
        return 1
    try:
        single = alert_limit_settings(load(), "single_frame")
    except (ParamsError, DataError) as e:
        print(f"integrity_shards: {e}")
        return 1
    for path in shards:
        try:
            with open(path, "rb") as f:  # the stage's own output folder (stages/artifacts/shards.py)
                share = pickle.load(f)["share"]
        except (OSError, EOFError, pickle.UnpicklingError, KeyError, TypeError, AttributeError) as e:
            print(f"integrity_shards: {path}: unreadable ({type(e).__name__}: {e}); skipped")
            continue
        print(f"\n{path.parent.name} {path.stem} ({path})\n")
        print(markdown_table(share_rows(share, single)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
