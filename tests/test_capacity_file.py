"""The attacker-capacity files (pipeline/formats/capacity.py): round trip into `capacity_at`, and the files or
inputs that do not fit together refused, on synthetic shifts: no network."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from pipeline.attacks.capacity import Shifts, capacity_at, fit_capacity
from pipeline.formats.capacity import COLUMNS, capacity_paths, read_capacity, write_capacity
from pipeline.io.errors import DataError

EPS = [0.01, 0.05]
EDGES = [10.0, 30.0, 60.0]


def synthetic(n: int = 40, seed: int = 0) -> tuple[pd.DataFrame, list]:
    """A per-frame table (COLUMNS) of n frames at each of EPS, shifts growing with eps, and its overbounds."""
    rng = np.random.default_rng(seed)
    range_m = rng.uniform(11, 59, n)
    rows, caps = [], []
    for k, eps in enumerate(EPS):
        along, across, att = (rng.uniform(0, 1, n) * (k + 1) * range_m / 50 for _ in range(3))
        rows.append(
            pd.DataFrame(
                {
                    "index": np.arange(n),
                    "range_m": range_m,
                    "eps": eps,
                    "along_m": along,
                    "across_m": across,
                    "attitude_deg": att,
                }
            )
        )
        caps.append(fit_capacity(Shifts(eps, range_m, along, across, att), EDGES, 0.9, 0.25, min_count=5))
    return pd.concat(rows, ignore_index=True)[COLUMNS], caps


def test_the_files_round_trip_into_capacity_at(tmp_path):
    table, caps = synthetic()
    content = write_capacity(tmp_path, "robust", table, caps[::-1], {"split": "val", "model_hash": "abc"})
    assert [e["eps"] for e in content["per_eps"]] == EPS  # written in increasing eps
    assert {p.name for p in tmp_path.iterdir()} == {"robust.parquet", "robust.json"}
    frames, back, meta = read_capacity(tmp_path, "robust")
    assert frames.equals(table) and meta == {"split": "val", "model_hash": "abc"} and [c.eps for c in back] == EPS
    r = np.array([12.0, 45.0])
    np.testing.assert_array_equal(capacity_at(back, 0.03, r), capacity_at(caps, 0.03, r))
    assert capacity_at(back, 0.05, r)[1, 0] == pytest.approx(max(caps[0].along[1], caps[1].along[1]))


def test_a_file_of_another_model_or_format_or_with_missing_bins_is_refused(tmp_path):
    table, caps = synthetic()
    write_capacity(tmp_path, "robust", table, caps, {})
    table_path, json_path = capacity_paths(tmp_path, "robust")
    (tmp_path / "standard.json").write_text(json_path.read_text())
    (tmp_path / "standard.parquet").write_bytes(table_path.read_bytes())
    with pytest.raises(DataError, match="not a rpodguard-capacity/1 file of the standard model"):
        read_capacity(tmp_path, "standard")
    data = json.loads(json_path.read_text())
    data["per_eps"][1]["along_m"] = [1.0]  # one bin short
    json_path.write_text(json.dumps(data))
    with pytest.raises(DataError, match="do not hold a consistent capacity.*needs 2 finite values"):
        read_capacity(tmp_path, "robust")
    with pytest.raises(DataError):
        read_capacity(tmp_path, "missing")


def test_inputs_that_do_not_fit_together_are_refused(tmp_path):
    table, caps = synthetic()
    with pytest.raises(ValueError, match="eps"):
        write_capacity(tmp_path, "robust", table, caps[:1], {})  # the table has an eps with no overbound
    with pytest.raises(ValueError, match="columns"):
        write_capacity(tmp_path, "robust", table.drop(columns="attitude_deg"), caps, {})
    bad = table.copy()
    bad.loc[3, "along_m"] = -1.0
    with pytest.raises(ValueError, match="shifts finite and >= 0"):
        write_capacity(tmp_path, "robust", bad, caps, {})
    other = fit_capacity(Shifts(0.05, *np.full((4, 40), 20.0)), [10.0, 40.0], min_count=5)
    with pytest.raises(ValueError, match="share the range bins"):
        write_capacity(tmp_path, "robust", table, [caps[0], other], {})
    with pytest.raises(ValueError, match="model name"):
        capacity_paths(tmp_path, "../robust")
    assert not list(tmp_path.iterdir())  # nothing written by a refused call
