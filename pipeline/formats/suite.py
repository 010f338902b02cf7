"""Stored runs of the strongest-attack suite at one eps (pipeline/attacks/strongest.py `SuiteResult` with one eps):
what `rpod suite` keeps in datasets/suite/ as it goes, so a run stopped (a time budget, a lost machine) goes on
where it stopped, and a part computed on a GPU is read on any machine.

One `.npz` per part (no pickles): the SuiteResult's arrays (`errors/<key>`, `shifts/<key>`, `clean/<key>`,
`target_range_m`, `seconds`, `cpu_seconds`, `eps`), its `members`, and `key` and `device`: the part's identity
(a digest of the model, frames, settings and eps the caller computes: a part whose key differs is not read) and
the device it ran on.

API: `part_key(model_hash, images, targets, config)`: the identity of a suite run's parts;
`write_suite_part(path, result, key, device)`; `read_suite_part(path, key) -> (SuiteResult, device) | None`
(None when the file is missing or holds another key; a DataError naming the file when it is damaged).
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import json
import zipfile
from pathlib import Path

import numpy as np

from pipeline.attacks.strongest import ERRORS, SHIFTS, SuiteConfig, SuiteResult
from pipeline.io.atomic import atomic_write_bytes
from pipeline.io.errors import DataError
from pipeline.io.files import read_bytes


def part_key(model_hash: str, images: np.ndarray, targets: np.ndarray, config: SuiteConfig) -> str:
    """The identity of a suite run's parts: sha256 of the pose model file's hash, the frames (uint8 images and
    targets, as given) and the suite's settings (its seed and batch size included)."""
    h = hashlib.sha256()
    for item in (
        model_hash.encode(),
        np.ascontiguousarray(images).tobytes(),
        np.ascontiguousarray(targets).tobytes(),
        json.dumps(dataclasses.asdict(config), sort_keys=True).encode(),
    ):
        h.update(hashlib.sha256(item).digest())
    return h.hexdigest()


def write_suite_part(path: Path | str, result: SuiteResult, key: str, device: str) -> None:
    """`result` (one eps) with its identity `key` and the `device` it ran on, atomically, to `path` (.npz)."""
    if len(result.eps) != 1:
        raise ValueError(f"a suite part holds one eps, got {list(result.eps)}")
    arrays = {
        **{f"errors/{k}": v for k, v in result.errors.items()},
        **{f"shifts/{k}": v for k, v in result.shifts.items()},
        **{f"clean/{k}": v for k, v in result.clean.items()},
        "target_range_m": result.target_range_m,
        "seconds": result.seconds,
        "cpu_seconds": result.cpu_seconds,
        "eps": np.asarray(result.eps, np.float64),
        "members": np.asarray(result.members, dtype=np.str_),
        "key": np.asarray(key),
        "device": np.asarray(device),
    }
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    atomic_write_bytes(path, buffer.getvalue())


def read_suite_part(path: Path | str, key: str) -> tuple[SuiteResult, str] | None:
    """The part at `path` and the device it ran on when it holds `key`; None when there is no file or it holds
    another key (a stale part: computed again); a DataError naming the file when it cannot be read."""
    if not Path(path).exists():
        return None
    try:
        with np.load(io.BytesIO(read_bytes(path, "suite part")), allow_pickle=False) as z:
            if str(z["key"]) != key:
                return None
            result = SuiteResult(
                (float(z["eps"][0]),),
                tuple(str(m) for m in z["members"]),
                {k: z[f"errors/{k}"] for k in ERRORS},
                {k: z[f"shifts/{k}"] for k in SHIFTS},
                {k: z[f"clean/{k}"] for k in ERRORS},
                z["target_range_m"],
                z["seconds"],
                z["cpu_seconds"],
            )
            return result, str(z["device"])
    except (KeyError, ValueError, OSError, zipfile.BadZipFile) as e:
        raise DataError(f"{path}: not a readable suite part ({e}); delete it to compute it again") from None
