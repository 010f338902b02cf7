"""Resumable shards of a long campaign (`rpod integrity`): one file per chain and trajectory holding that
trajectory's share of the campaign (pipeline/evaluation/campaign.py `TrackFlights`), written atomically once the
share is flown, and read back only when its key (a fingerprint of everything the share depends on: params, the
chain's files, the trajectory) matches; a missing, unreadable or stale shard is flown again.

The shards are pickles of this project's own dataclasses and numpy arrays, read only from the stage's own output
folder (datasets/integrity_shards/): not a format for exchange.
"""

from __future__ import annotations

import pickle
from pathlib import Path
from typing import Any

from pipeline.io.atomic import atomic_write_bytes

SUFFIX = ".pkl"


def shard_path(folder: Path | str, chain: str, track: str) -> Path:
    """The shard of trajectory `track` of chain `chain` under `folder`."""
    return Path(folder) / chain / f"{track}{SUFFIX}"


def write_shard(path: Path | str, key: str, share: Any) -> None:
    """`share` with its `key` to `path`, through a temporary file in the same folder and a rename (a kill leaves
    the previous shard or none, never half of one)."""
    atomic_write_bytes(path, pickle.dumps({"key": key, "share": share}, protocol=pickle.HIGHEST_PROTOCOL))


def read_shard(path: Path | str, key: str) -> Any | None:
    """The share stored at `path` under `key`; None when the file is missing, unreadable or holds another key."""
    try:
        with open(path, "rb") as f:
            stored = pickle.load(f)
    except (OSError, EOFError, pickle.UnpicklingError, AttributeError, ImportError, IndexError, TypeError):
        return None
    if not isinstance(stored, dict) or stored.get("key") != key:
        return None
    return stored.get("share")
