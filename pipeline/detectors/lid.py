"""Baseline: local intrinsic dimensionality (LID) of the GAP features (Ma et al. 2018).

The maximum-likelihood LID estimate of x from its k nearest neighbours in a reference minibatch
of clean samples is  LID(x) = -(1/k * sum_i log(r_i / r_k))^-1  (r_i the i-th neighbour distance).
Adversarial examples tend to have a higher LID. As in Ma et al., training LIDs come from minibatches
of the training data, each sample against the clean samples of its own minibatch (a clean sample
never counts itself), and a logistic regression on the LID separates the classes. At test time a
sample is compared with random clean minibatches from training (averaged over `n_reference`
draws), so a frame is scored on its own, without other test frames. One layer (GAP) only.
"""

from __future__ import annotations

import numpy as np
from sklearn.linear_model import LogisticRegression
from sklearn.neighbors import NearestNeighbors
from sklearn.pipeline import Pipeline, make_pipeline
from sklearn.preprocessing import StandardScaler

from pipeline.seeds import seed_for


def lid_mle(x: np.ndarray, reference: np.ndarray, k: int, skip_self: bool = False) -> np.ndarray:
    """MLE of the LID of each row of x (N, D) against `reference` (M, D); `skip_self` drops the
    nearest neighbour (x is a subset of reference). Returns (N,)."""
    k = min(k, len(reference) - int(skip_self))
    if k < 2:
        raise ValueError(f"LID needs at least 2 neighbours; the reference has {len(reference)} samples")
    nn = NearestNeighbors(n_neighbors=k + int(skip_self)).fit(reference)
    dist, _ = nn.kneighbors(x)
    dist = np.maximum(dist[:, int(skip_self) :], 1e-12)
    return -1.0 / np.mean(np.log(dist / dist[:, -1:]), axis=1).clip(max=-1e-12)


def neighbours(k: int, labels: np.ndarray, batch_size: int) -> int:
    """The fewest neighbours `LIDDetector(k, batch_size).fit(features, labels)` estimates a LID from: k, or one
    less than the clean samples of its smallest training minibatch when they are fewer (what a report states)."""
    labels = np.asarray(labels)
    n_batches = max(1, len(labels) // batch_size)
    return min(k, int(np.sum(labels == 0)) // n_batches - 1)


class LIDDetector:
    """LID features on minibatches + logistic regression; `score` is the probability of "attacked"."""

    def __init__(self, k: int = 20, batch_size: int = 100, n_reference: int = 5, seed: int = 0):
        self.k, self.batch_size, self.n_reference, self.seed = k, batch_size, n_reference, seed
        self.model: Pipeline = make_pipeline(StandardScaler(), LogisticRegression())

    def fit(self, features: np.ndarray, labels: np.ndarray) -> "LIDDetector":
        features, labels = np.asarray(features, dtype=np.float64), np.asarray(labels).astype(int)
        rng = np.random.default_rng(self.seed)
        clean, adv = np.flatnonzero(labels == 0), np.flatnonzero(labels == 1)
        n_batches = max(1, len(labels) // self.batch_size)
        lid = np.zeros(len(features))
        # each minibatch gets its share of both classes, so every one has clean references
        for c, a in zip(
            np.array_split(rng.permutation(clean), n_batches), np.array_split(rng.permutation(adv), n_batches)
        ):
            ref = features[c]
            lid[c] = lid_mle(ref, ref, self.k, skip_self=True)
            if len(a):
                lid[a] = lid_mle(features[a], ref, self.k)
        self.reference_ = features[clean]
        self.ref_size_ = max(3, len(clean) // n_batches)  # clean references per training minibatch
        self.model.fit(lid[:, None], labels)
        return self

    def lid(self, features: np.ndarray) -> np.ndarray:
        """Mean LID of each sample against `n_reference` random clean training minibatches (each as
        large as the clean part of a training minibatch, since the estimate depends on that size)."""
        rng = np.random.default_rng(seed_for(self.seed, "lid.reference"))
        size = min(self.ref_size_, len(self.reference_))
        draws = [
            lid_mle(features, self.reference_[rng.choice(len(self.reference_), size, replace=False)], self.k)
            for _ in range(self.n_reference)
        ]
        return np.mean(draws, axis=0)

    def score(self, features: np.ndarray) -> np.ndarray:
        return self.model.predict_proba(self.lid(np.asarray(features, dtype=np.float64))[:, None])[:, 1]
