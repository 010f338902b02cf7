"""The attacker-capacity files of a chain (issue 37 item 4 -> issue 40: what the integrity bound consumes), one
pair per pose model in a folder (`rpod train --robust` -> datasets/capacity/, models "standard" and "robust"):

- `<model>.parquet`: the per-frame capacity the strongest-attack suite reached on validation frames
  (pipeline/evaluation/strongest.py `capacity_frames`): one row per frame and eps, columns `COLUMNS`: index (the
  frame's row in datasets/labels.parquet), range_m (true range, m, > 0), eps (L-inf, pixel units in [0, 1]),
  along_m, across_m (|shift| of the estimate from its clean estimate along and across the true line of sight,
  m, >= 0), attitude_deg (attitude change, deg, >= 0); nested in eps (a frame's shift does not drop as eps
  grows);
- `<model>.json`: format `CAPACITY_FORMAT`, model, and `meta` (what made it: the pose model's hash, the split,
  the suite's settings), then the fitted overbound F(eps, range) (pipeline/attacks/capacity.py `Capacity`, one per
  eps, the same range bins, the same quantile and margin): edges (m), quantile, margin, and per eps (increasing)
  the bins' along_m, across_m (m), attitude_deg (deg) and frame counts.

API (stable; other stages read it):
- `write_capacity(folder, model, frames, overbounds, meta) -> dict`: both files, checked (columns, finite
  non-negative shifts, the table's eps are the overbounds' eps, shared bins); returns the JSON content.
- `read_capacity(folder, model) -> (frames, overbounds, meta)`: the same, checked again; a DataError naming the
  file otherwise. The overbounds come in increasing eps, ready for `pipeline.attacks.capacity.capacity_at`:

      frames, overbounds, meta = read_capacity("datasets/capacity", "robust")
      box = capacity_at(overbounds, eps, range_m)     # (N, 3) half-widths [along LOS, cross, cross] (m)

- `capacity_paths(folder, model) -> (parquet, json)`: the two files' paths.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import pandas as pd

from pipeline.attacks.capacity import Capacity
from pipeline.io.atomic import read_json, write_json
from pipeline.io.errors import DataError
from pipeline.io.tables import read_parquet, write_parquet

CAPACITY_FORMAT = "rpodguard-capacity/1"
COLUMNS = ["index", "range_m", "eps", "along_m", "across_m", "attitude_deg"]
_MODEL = re.compile(r"[A-Za-z0-9_-]+")


def capacity_paths(folder: Path | str, model: str) -> tuple[Path, Path]:
    """(per-frame table, fitted overbound) of pose model `model` (letters, digits, _ and -) in `folder`."""
    if not _MODEL.fullmatch(model):
        raise ValueError(f"capacity: model name {model!r} must be letters, digits, _ or -")
    return Path(folder) / f"{model}.parquet", Path(folder) / f"{model}.json"


def write_capacity(
    folder: Path | str, model: str, frames: pd.DataFrame, overbounds: Sequence[Capacity], meta: dict[str, Any]
) -> dict[str, Any]:
    """A chain's capacity files (module doc) into `folder`: `frames` (COLUMNS), `overbounds` (one per eps of
    `frames`, any order); returns the JSON file's content. A ValueError when they do not fit together."""
    overbounds = sorted(overbounds, key=lambda c: c.eps)
    _check_frames(frames)
    _check_overbounds(overbounds, frames)
    table, fitted = capacity_paths(folder, model)
    first = overbounds[0]
    content = {
        "format": CAPACITY_FORMAT,
        "model": model,
        "meta": meta,
        "edges": first.edges.tolist(),
        "quantile": float(first.quantile),
        "margin": float(first.margin),
        "per_eps": [
            {
                "eps": float(c.eps),
                "along_m": c.along.tolist(),
                "across_m": c.across.tolist(),
                "attitude_deg": c.attitude_deg.tolist(),
                "count": c.count.tolist(),
            }
            for c in overbounds
        ],
    }
    write_parquet(frames, table)
    write_json(fitted, content)
    return content


def read_capacity(folder: Path | str, model: str) -> tuple[pd.DataFrame, list[Capacity], dict[str, Any]]:
    """(per-frame table, the fitted overbounds in increasing eps, meta) of pose model `model` in `folder`; a
    DataError naming the file when it is missing or not a consistent capacity file of that model."""
    table, fitted = capacity_paths(folder, model)
    data = read_json(fitted)
    try:
        if not isinstance(data, dict) or data.get("format") != CAPACITY_FORMAT or data.get("model") != model:
            raise ValueError("wrong format or model")
        edges = np.asarray(data["edges"], np.float64)
        overbounds = [
            Capacity(
                float(e["eps"]),
                edges,
                np.asarray(e["along_m"], np.float64),
                np.asarray(e["across_m"], np.float64),
                np.asarray(e["attitude_deg"], np.float64),
                np.asarray(e["count"], np.int64),
                float(data["quantile"]),
                float(data["margin"]),
            )
            for e in data["per_eps"]
        ]
    except (KeyError, TypeError, ValueError) as e:
        raise DataError(f"{fitted} is not a {CAPACITY_FORMAT} file of the {model} model ({e})") from None
    frames = read_parquet(table, "capacity table")
    try:
        _check_frames(frames)
        _check_overbounds(overbounds, frames)
    except ValueError as e:
        raise DataError(f"{fitted} and {table} do not hold a consistent capacity ({e})") from None
    return frames, overbounds, data["meta"]


def _check_frames(frames: pd.DataFrame) -> None:
    """A ValueError unless `frames` has exactly COLUMNS, ranges > 0, eps in (0, 1] and finite shifts >= 0."""
    if list(frames.columns) != COLUMNS or frames.empty:
        raise ValueError(f"capacity: frames must be rows with the columns {COLUMNS}, got {list(frames.columns)}")
    values = frames[COLUMNS[1:]].to_numpy(np.float64)
    if not np.isfinite(values).all() or (values[:, 2:] < 0).any() or (values[:, 0] <= 0).any():
        raise ValueError("capacity: ranges must be > 0 and shifts finite and >= 0")
    if not ((frames["eps"] > 0) & (frames["eps"] <= 1)).all():
        raise ValueError("capacity: eps must lie in (0, 1]")


def _check_overbounds(overbounds: Sequence[Capacity], frames: pd.DataFrame) -> None:
    """A ValueError unless `overbounds` (increasing eps) share edges, quantile and margin, have one value per
    bin, finite and >= 0, and are exactly the eps of `frames`."""
    if not overbounds:
        raise ValueError("capacity: at least one overbound is needed")
    first, eps = overbounds[0], [float(c.eps) for c in overbounds]
    edges = np.asarray(first.edges, np.float64)
    if edges.ndim != 1 or len(edges) < 2 or not np.isfinite(edges).all() or not (np.diff(edges) > 0).all():
        raise ValueError(f"capacity: edges must be >= 2 increasing finite ranges (m), got {edges}")
    if len(set(eps)) != len(eps) or sorted(set(frames["eps"].astype(float))) != eps:
        raise ValueError(
            f"capacity: the overbounds' eps {eps} must be distinct and those of the frames {sorted(set(frames['eps']))}"
        )
    for c in overbounds:
        if not np.array_equal(c.edges, edges) or c.quantile != first.quantile or c.margin != first.margin:
            raise ValueError("capacity: every overbound must share the range bins, quantile and margin")
        values = [np.asarray(v, np.float64) for v in (c.along, c.across, c.attitude_deg, c.count)]
        if any(v.shape != (len(edges) - 1,) or not np.isfinite(v).all() or (v < 0).any() for v in values):
            raise ValueError(f"capacity: eps {c.eps} needs {len(edges) - 1} finite values >= 0 per bin")
