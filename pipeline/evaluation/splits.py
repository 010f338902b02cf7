"""Leak-free data splits: every group (a rendered frame, a source image) lands on one side only.

`holdout` carves a seeded fraction of whole groups out of a set of samples: the validation split the
pose training selects its checkpoint on, taken from the training split so the test split is never
read before the final evaluation. `grouped_split` is the detector's train / validation / test split:
grouped by source image, so the clean version of a frame and all its adversarial versions (FGSM's
sign pattern does not depend on eps) sit on the same side, and stratified by eps as far as the
groups allow (scikit-learn's StratifiedGroupKFold).
"""

from __future__ import annotations

import numpy as np

from pipeline.seeds import seed_for


def holdout(groups: np.ndarray, fraction: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(kept, held out) sorted sample indices; round(fraction * number of groups) whole groups are held out.

    Raises ValueError when `fraction` is not in (0, 1) or either side would be empty.
    """
    groups = np.asarray(groups)
    if not 0 < fraction < 1:
        raise ValueError(f"fraction must be in (0, 1), got {fraction}")
    unique = np.unique(groups)
    n_out = int(round(fraction * len(unique)))
    if not 0 < n_out < len(unique):
        raise ValueError(
            f"{len(unique)} groups cannot be split {1 - fraction:.0%} / {fraction:.0%} with both sides non-empty"
        )
    out = np.isin(groups, np.random.default_rng(seed).permutation(unique)[:n_out])
    return np.flatnonzero(~out), np.flatnonzero(out)


def grouped_split(
    groups: np.ndarray, strata: np.ndarray, test_fraction: float, val_fraction: float, seed: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sorted (train, validation, test) indices, grouped by `groups` and stratified by `strata`.

    The test part is one fold of StratifiedGroupKFold with round(1 / test_fraction) folds (0.2 -> 5),
    the validation part one fold of the rest with round(1 / val_fraction) folds, so the fractions
    are met to 1/k and as closely as whole groups allow. Raises ValueError when a fraction is not in
    (0, 0.5] or there are fewer groups than folds.
    """
    from sklearn.model_selection import StratifiedGroupKFold

    groups = np.asarray(groups)
    if len(groups) != len(strata):
        raise ValueError(f"{len(groups)} groups but {len(strata)} strata")
    strata = np.unique(np.asarray(strata), return_inverse=True)[1]  # class labels, as scikit-learn wants

    def one_fold(idx: np.ndarray, fraction: float, rng_seed: int) -> tuple[np.ndarray, np.ndarray]:
        if not 0 < fraction <= 0.5:
            raise ValueError(f"split fractions must be in (0, 0.5], got {fraction}")
        k = int(round(1 / fraction))
        if len(np.unique(groups[idx])) < k:
            raise ValueError(f"{len(np.unique(groups[idx]))} source images cannot fill {k} folds")
        folds = StratifiedGroupKFold(n_splits=k, shuffle=True, random_state=rng_seed)
        keep, out = next(folds.split(idx, strata[idx], groups[idx]))
        return idx[keep], idx[out]

    rest, test = one_fold(np.arange(len(groups)), test_fraction, seed)
    train, val = one_fold(rest, val_fraction, seed_for(seed, "splits.validation"))
    return np.sort(train), np.sort(val), np.sort(test)
