"""Baseline: Mahalanobis distance of the GAP features to class-conditional Gaussians (Lee et al. 2018).

Lee et al. fit one Gaussian per class with a covariance shared by all classes ("tied") on clean
training features and score a sample by its smallest Mahalanobis distance to a class mean. A pose
regressor has no classes, so the caller passes groups (e.g. range bins). The shared covariance of
1000 features from a few hundred samples is singular, so it is estimated with Ledoit-Wolf
shrinkage (scikit-learn). Lee et al.'s input preprocessing and multi-layer ensemble are left out:
one layer, the GAP layer the other detectors see too.
"""

from __future__ import annotations

import numpy as np
from sklearn.covariance import LedoitWolf


class MahalanobisDetector:
    """score(features) = min over groups of the squared Mahalanobis distance; higher = more anomalous."""

    def fit(self, features: np.ndarray, groups: np.ndarray) -> "MahalanobisDetector":
        """Clean features (N, D) and their group ids (N,): per-group means, one shared covariance."""
        features = np.asarray(features, dtype=np.float64)
        groups = np.asarray(groups)
        self.groups_ = np.unique(groups)
        self.means_ = np.stack([features[groups == g].mean(0) for g in self.groups_])
        centred = features - self.means_[np.searchsorted(self.groups_, groups)]
        self.cov_ = LedoitWolf(assume_centered=True).fit(centred)
        return self

    def score(self, features: np.ndarray) -> np.ndarray:
        features = np.asarray(features, dtype=np.float64)
        dist = np.stack([self.cov_.mahalanobis(features - m) for m in self.means_], axis=1)
        return dist.min(axis=1)
