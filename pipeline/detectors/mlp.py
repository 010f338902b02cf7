"""Baseline: a multilayer perceptron on the flattened SHAP values (B, 9 * 1000), scikit-learn."""

from __future__ import annotations

import numpy as np
from sklearn.neural_network import MLPClassifier
from sklearn.pipeline import Pipeline, make_pipeline
from sklearn.preprocessing import StandardScaler


class MLPDetector:
    """Standardise each SHAP value, then an MLP (ReLU, Adam, scikit-learn's own early stopping)."""

    def __init__(self, hidden: tuple[int, ...] = (100,), max_iter: int = 200, seed: int = 0):
        self.pipeline: Pipeline = make_pipeline(
            StandardScaler(),
            MLPClassifier(
                hidden_layer_sizes=tuple(hidden),
                max_iter=max_iter,
                early_stopping=True,
                n_iter_no_change=20,
                random_state=seed,
            ),
        )

    def fit(self, values: np.ndarray, labels: np.ndarray) -> "MLPDetector":
        """values (N, 9, 1000) SHAP; labels 1 = attacked."""
        self.pipeline.fit(np.asarray(values).reshape(len(values), -1), np.asarray(labels).astype(int))
        return self

    def score(self, values: np.ndarray) -> np.ndarray:
        """Probability of "attacked", (N,)."""
        return self.pipeline.predict_proba(np.asarray(values).reshape(len(values), -1))[:, 1]
