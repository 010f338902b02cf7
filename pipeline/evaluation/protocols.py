"""The two detector protocols of the issue-38 ablation: which images make the clean and the attacked samples, and
how they are split into train / validation / test.

- strict (ours, `rpod shap` + `rpod detect`): every sample is an image of the detector split (trajectories the pose
  network never saw), each source image explained clean once and attacked once
  (`pipeline.shap.sample_plan`), split grouped by source image (`pipeline.evaluation.splits.grouped_split`), so no
  image sits on both sides.
- paper (its sections on the SHAP data and the detector, as the paper states them): clean samples are pose-test
  images topped up with pose-training images, attacked samples are attacked pose-test images (`paper_plan`: each
  eps draws its own test images, so one test image can be clean and attacked at several eps), and the split is
  random per sample (`random_split`). The same source image, and its neighbouring frames of the same approach
  (2 cm apart at the paper's 2,500 frames per 50 m), then sit in training and test: the split is **leaky**, which
  `shared_fraction` and `neighbour_fraction` measure.
"""

from __future__ import annotations

import numpy as np


def paper_plan(
    split: np.ndarray, normal: int, per_eps: int, eps: list[float], rng: np.random.Generator
) -> dict[str, np.ndarray]:
    """The paper's SHAP samples from a label table's `split` column ("train" / "test" per row).

    Clean: every test row (in random order; `normal` of them when there are more), topped up to `normal` with
    training rows drawn without replacement. Attacked: for each eps in `eps` (L-inf, pixels in [0, 1]) `per_eps`
    test rows drawn without replacement, independently per eps. Returns {"index": label-table rows int64, "eps":
    float32 (0 = clean)}. Raises ValueError when the table has too few test or training rows.
    """
    split = np.asarray(split).astype(str)
    test, train = np.flatnonzero(split == "test"), np.flatnonzero(split == "train")
    normal, per_eps = int(normal), int(per_eps)
    if per_eps > len(test):
        raise ValueError(f"{per_eps} attacked samples per eps need as many test images, the table has {len(test)}")
    n_test_clean = min(normal, len(test))
    if normal - n_test_clean > len(train):
        raise ValueError(
            f"{normal} clean samples need {normal - n_test_clean} training images, the table has {len(train)}"
        )
    clean = np.concatenate(
        [rng.permutation(test)[:n_test_clean], rng.choice(train, normal - n_test_clean, replace=False)]
    )
    attacked = [rng.choice(test, per_eps, replace=False) for _ in eps]
    index = np.concatenate([clean, *attacked]).astype(np.int64)
    eps_out = np.concatenate([np.zeros(normal), np.repeat(np.asarray(eps, dtype=np.float64), per_eps)])
    return {"index": index, "eps": eps_out.astype(np.float32)}


def random_split(
    n: int, test_fraction: float, val_fraction: float, seed: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sorted (train, validation, test) sample indices of a random per-sample split, as the paper's: round(n
    test_fraction) samples to test, then round(val_fraction x the rest) to validation. Raises ValueError when a
    fraction is not in (0, 1) or a part would be empty."""
    for name, frac in (("test", test_fraction), ("validation", val_fraction)):
        if not 0 < frac < 1:
            raise ValueError(f"{name} fraction must be in (0, 1), got {frac}")
    order = np.random.default_rng(seed).permutation(int(n))
    n_test = int(round(n * test_fraction))
    n_val = int(round((n - n_test) * val_fraction))
    if min(n_test, n_val, n - n_test - n_val) < 1:
        raise ValueError(f"{n} samples cannot be split with test {test_fraction} and validation {val_fraction}")
    test, val, train = order[:n_test], order[n_test : n_test + n_val], order[n_test + n_val :]
    return np.sort(train), np.sort(val), np.sort(test)


def shared_fraction(source: np.ndarray, train: np.ndarray, test: np.ndarray) -> float:
    """Share of the `test` samples whose source image (`source`: an id per sample) is also the source of a training
    sample: 0 for a split grouped by source image. NaN without test samples."""
    source = np.asarray(source)
    if len(test) == 0:
        return float("nan")
    return float(np.isin(source[test], source[train]).mean())


def neighbour_fraction(
    sequence: np.ndarray, frame: np.ndarray, train: np.ndarray, test: np.ndarray, within: int = 1
) -> float:
    """Share of the `test` samples with a training sample of the same sequence at most `within` frames away (the
    same frame included): what a split leaks through near-identical neighbouring frames. NaN without test samples."""
    sequence, frame = np.asarray(sequence), np.asarray(frame, dtype=np.int64)
    if len(test) == 0:
        return float("nan")
    seen = {(s, f) for s, f in zip(sequence[train].tolist(), frame[train].tolist())}
    hit = [
        any((s, f + d) in seen for d in range(-within, within + 1))
        for s, f in zip(sequence[test].tolist(), frame[test].tolist())
    ]
    return float(np.mean(hit))
