"""The label columns of every pose table (labels.parquet, the eval-render and lab poses, SPEED imports).

t = target origin in the camera frame (metres), q = target -> camera quaternion, scalar first, and
the 6-D rotation (first two columns of R, column-wise): the conventions of pipeline/geometry/rotations.py.
The pose network's 9 outputs are `TARGET`, in that order.
"""

from __future__ import annotations

import numpy as np

POSITION = ["tx", "ty", "tz"]
QUAT = ["qw", "qx", "qy", "qz"]
SIXD = [f"r{i}" for i in range(6)]
TARGET = POSITION + SIXD


def pose_columns(t: np.ndarray, q: np.ndarray, r6: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """{column: values} for positions t (N, 3) m, quaternions q (N, 4) and optionally 6-D rotations
    r6 (N, 6), in the order tx, ty, tz, qw, qx, qy, qz[, r0..r5] (column views, no copies)."""
    cols = {**{c: t[:, k] for k, c in enumerate(POSITION)}, **{c: q[:, k] for k, c in enumerate(QUAT)}}
    if r6 is not None:
        cols.update({c: r6[:, k] for k, c in enumerate(SIXD)})
    return cols


SPLITS = ("train", "test")  # a label table's split values
MAX_RANGE_M = 10_000.0  # m: a target farther than this is no rendezvous frame (SPEED's are 3-40 m)
SIXD_TOLERANCE = 1e-6  # |r0..r5 - the 6-D rotation of q| above this: the columns disagree


def _first(bad: np.ndarray, df, what: str) -> str | None:
    """ "row R (index I): WHAT (N rows)" of the first True row of `bad`, or None."""
    if not bad.any():
        return None
    k = int(np.argmax(bad))
    index = df["index"].iloc[k] if "index" in df else k
    return f"row {k} (index {index!r}): {what} ({int(bad.sum())} such rows)"


def poses_problem(df) -> str | None:
    """What is wrong with a table's poses (t, q, range), or None: t finite, in front of the camera (tz > 0) and at
    most MAX_RANGE_M away; q a unit quaternion (rotations.UNIT_TOLERANCE; an all-zero q is none); range = |t|."""
    from pipeline.geometry.rotations import UNIT_TOLERANCE

    t, q = df[POSITION].to_numpy(np.float64), df[QUAT].to_numpy(np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        distance = np.linalg.norm(t, axis=1)
        return (
            _first(~np.isfinite(t).all(axis=1), df, f"position {POSITION} is not finite")
            or _first(t[:, 2] <= 0, df, "the target is behind the camera or in its plane (tz <= 0)")
            or _first(distance > MAX_RANGE_M, df, f"the target is more than {MAX_RANGE_M:g} m away")
            or _first(
                ~(np.abs(np.linalg.norm(q, axis=1) - 1) <= UNIT_TOLERANCE), df, f"{QUAT} is not a unit quaternion"
            )
            or (
                "range" in df
                and _first(
                    ~(np.abs(df["range"].to_numpy(np.float64) - distance) <= 1e-6 * distance),
                    df,
                    "range is not the distance |t| of its position",
                )
            )
            or None
        )


def table_problem(df) -> str | None:
    """What is wrong with a label table (the columns of `rpod label`), or None: integer, unique, non-negative
    index; the poses (`poses_problem`); r0..r5 the 6-D rotation of q; split values from SPLITS; no image in both
    splits."""
    from pipeline.geometry.rotations import quat_to_6d

    index = df["index"].to_numpy()
    if not np.issubdtype(index.dtype, np.number) or np.issubdtype(index.dtype, np.bool_):
        return f"index must be whole numbers, got {index.dtype}"
    with np.errstate(invalid="ignore"):
        index = index.astype(np.float64)
        problem = (
            _first(~(np.floor(index) == index) | (index < 0), df, "index is not a whole number >= 0")
            or _first(_repeated(index), df, "index is given twice")
            or poses_problem(df)
        )
    if problem:
        return problem
    q = df[QUAT].to_numpy(np.float64)
    off = np.abs(df[SIXD].to_numpy(np.float64) - quat_to_6d(q / np.linalg.norm(q, axis=1, keepdims=True))).max(axis=1)
    problem = _first(~(off <= SIXD_TOLERANCE), df, f"{SIXD} are not the 6-D rotation of its quaternion") or _first(
        ~df["split"].isin(SPLITS).to_numpy(), df, f"split is not one of {', '.join(SPLITS)}"
    )
    if problem or "image" not in df:
        return problem
    both = set(df.loc[df["split"] == SPLITS[0], "image"]) & set(df.loc[df["split"] == SPLITS[1], "image"])
    return f"image {sorted(both)[0]!r} is in both splits ({len(both)} such images)" if both else None


def _repeated(values: np.ndarray) -> np.ndarray:
    """True where a value repeats an earlier one."""
    _, first = np.unique(values, return_index=True)
    out = np.ones(len(values), bool)
    out[first] = False
    return out


def against_poses(labels, poses) -> str | None:
    """Where a label table disagrees with the render's poses table (`rpod render`'s poses.parquet), or None: every
    label index a row of the poses, with the same position, quaternion (up to sign), range and sequence."""
    rows = poses.set_index("index")
    missing = ~labels["index"].isin(rows.index).to_numpy()
    if missing.any():
        return _first(missing, labels, f"index is no row of the render's poses (0..{len(poses) - 1})")
    match = rows.loc[labels["index"].to_numpy()]
    t_off = np.abs(labels[POSITION].to_numpy(np.float64) - match[POSITION].to_numpy(np.float64)).max(axis=1)
    dot = np.abs(np.sum(labels[QUAT].to_numpy(np.float64) * match[QUAT].to_numpy(np.float64), axis=1))
    same = lambda c: labels[c].to_numpy() == match[c].to_numpy()  # noqa: E731
    return (
        _first(
            ~(t_off <= 1e-9 * np.maximum(1, np.abs(match[POSITION].to_numpy()).max(axis=1))),
            labels,
            "its position differs from the render's pose",
        )
        or _first(~(dot >= 1 - 1e-9), labels, "its quaternion differs from the render's pose")
        or _first(
            ~np.isclose(labels["range"].to_numpy(np.float64), match["range"].to_numpy(np.float64), rtol=1e-9, atol=0),
            labels,
            "its range differs from the render's pose",
        )
        or ("sequence" in labels and _first(~same("sequence"), labels, "its sequence differs from the render's"))
        or None
    )
