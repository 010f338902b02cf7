"""Compare the reports of two pipeline runs, ignoring what legitimately differs between runs: wall-clock
times and UTC stamps. Usage: `python scripts/compare_reports.py RUN_A RUN_B` (each a folder holding
reports/); prints every other difference and exits 1 when there is one.

Used to check that a refactor leaves the results unchanged (same artifacts and numbers on the same seeds).
"""

from __future__ import annotations

import difflib
import json
import re
import sys
from pathlib import Path
from typing import Any

TIME_KEYS = {
    "produced",
    "seconds",
    "train_minutes",
    "train_images_per_s",
    "render_seconds",
    "images_per_s",
    "seconds_per_image",
    "minutes",
}
# Markdown text that reports times: masked before comparing
TIME_TEXT = [
    re.compile(p)
    for p in (
        r"\d+(\.\d+)? s\b",
        r"\d+(\.\d+)? minutes",
        r"[\d.]+ s/image",
        r"[\d.]+ (training )?images/s",
        r"\d{4}-\d\d-\d\d \d\d:\d\d UTC",
        r"img/s",
    )
]


def strip_times(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: strip_times(v) for k, v in obj.items() if k not in TIME_KEYS}
    if isinstance(obj, list):
        return [strip_times(v) for v in obj]
    return obj


def md_lines(text: str) -> list[str]:
    out = []
    for line in text.splitlines():
        for pat in TIME_TEXT:
            line = pat.sub("<time>", line)
        out.append(line)
    return out


def mask_fit_column(lines: list[str]) -> list[str]:
    """Blank the `fit (s)` column of the detector comparison tables."""
    out, col = [], None
    for line in lines:
        cells = line.split("|")
        if line.startswith("|") and "fit (s)" in line:
            col = [c.strip() for c in cells].index("fit (s)")
        elif not line.startswith("|"):
            col = None
        if col is not None and line.startswith("|") and len(cells) > col:
            cells[col] = " <time> "
            line = "|".join(cells)
        out.append(line)
    return out


def compare(a: Path, b: Path) -> list[str]:
    diffs = []
    files = sorted(
        {p.relative_to(a) for p in (a / "reports").rglob("*") if p.suffix in (".md", ".json", ".csv")}
        | {p.relative_to(b) for p in (b / "reports").rglob("*") if p.suffix in (".md", ".json", ".csv")}
    )
    for rel in files:
        fa, fb = a / rel, b / rel
        if not fa.exists() or not fb.exists():
            diffs.append(f"{rel}: only in {'B' if not fa.exists() else 'A'}")
            continue
        if rel.suffix == ".json":
            ja, jb = strip_times(json.loads(fa.read_text())), strip_times(json.loads(fb.read_text()))
            la = json.dumps(ja, indent=1, sort_keys=True).splitlines()
            lb = json.dumps(jb, indent=1, sort_keys=True).splitlines()
        else:
            la, lb = mask_fit_column(md_lines(fa.read_text())), mask_fit_column(md_lines(fb.read_text()))
        if la != lb:
            diffs.append(f"{rel}:\n" + "\n".join(list(difflib.unified_diff(la, lb, lineterm="", n=0))[2:40]))
    return diffs


if __name__ == "__main__":
    found = compare(Path(sys.argv[1]), Path(sys.argv[2]))
    print("\n".join(found) if found else "no differences besides times")
    sys.exit(1 if found else 0)
