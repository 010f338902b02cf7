"""Markdown building blocks for reports: tables with fixed decimals, sections, marked blocks.

Tables keep the row order they are given and format every float with the same decimals, so a
re-run diffs cleanly in review.
"""

from __future__ import annotations

import re
from typing import Any, Iterable, Mapping, Sequence

import numpy as np
import pandas as pd


def markdown_table(
    rows: Sequence[Mapping[str, Any]] | pd.DataFrame, columns: Sequence[str] | None = None, decimals: int = 2
) -> str:
    """Rows (dicts or a DataFrame) -> a GitHub Markdown table; floats with `decimals` places."""
    df = rows.copy() if isinstance(rows, pd.DataFrame) else pd.DataFrame(list(rows))
    if columns is not None:
        missing = [c for c in columns if c not in df.columns]
        if missing:
            raise KeyError(f"table rows lack columns {missing}")
        df = df[list(columns)]
    fmt = f"{{:.{decimals}f}}"
    df = df.map(lambda v: fmt.format(v) if isinstance(v, float) else ("" if v is None else v))
    return df.to_markdown(index=False, disable_numparse=True) + "\n"


def demote_headings(md: str, levels: int = 1) -> str:
    """Push every ATX heading down `levels` levels (to nest a stage report in a larger page)."""
    return re.sub(r"^(#{1,6}) ", lambda m: "#" * min(6, len(m.group(1)) + levels) + " ", md, flags=re.M)


_BLOCK = "<!-- {name}:{edge} -->"


def replace_block(text: str, name: str, body: str) -> str:
    """Replace the text between `<!-- name:start -->` and `<!-- name:end -->` (appended if absent)."""
    start, end = _BLOCK.format(name=name, edge="start"), _BLOCK.format(name=name, edge="end")
    block = f"{start}\n{body.strip()}\n{end}"
    if start in text and end in text:
        i, j = text.index(start), text.index(end) + len(end)
        return text[:i] + block + text[j:]
    return text.rstrip("\n") + "\n\n" + block + "\n"


def extract_block(text: str, name: str) -> str | None:
    """The body between the markers of `name`, or None when the block is absent."""
    start, end = _BLOCK.format(name=name, edge="start"), _BLOCK.format(name=name, edge="end")
    if start not in text or end not in text:
        return None
    return text[text.index(start) + len(start) : text.index(end)].strip()


def replace_section(md: str, heading: str, body: str) -> str:
    """Replace the `## heading` section of a Markdown page (up to the next `## `), or append it."""
    pattern = re.compile(rf"^## {re.escape(heading)}\n.*?(?=^## |\Z)", re.M | re.S)
    section = f"## {heading}\n\n{body.strip()}\n\n"
    if pattern.search(md):
        return pattern.sub(lambda _: section, md, count=1)
    return (md.rstrip("\n") + "\n\n" if md.strip() else "") + section


def mean_abs_by_class(
    blocks: Iterable[tuple[np.ndarray, np.ndarray]], shape: tuple[int, ...]
) -> dict[str, np.ndarray] | None:
    """Mean |phi| (`shape`, e.g. (9, F)) over normal and over adversarial samples, from blocks of
    (values (B, *shape), is_adversarial (B,) bool) read in order; keys `normal (n)` and
    `adversarial (n)`; None when either class has no sample."""
    sums = {False: np.zeros(shape), True: np.zeros(shape)}
    counts = {False: 0, True: 0}
    for values, flags in blocks:
        block = np.abs(np.asarray(values, dtype=np.float64))
        for flag in (False, True):
            sums[flag] += block[flags == flag].sum(axis=0)
            counts[flag] += int((flags == flag).sum())
    if not all(counts.values()):
        return None
    return {
        f"normal ({counts[False]})": sums[False] / counts[False],
        f"adversarial ({counts[True]})": sums[True] / counts[True],
    }
