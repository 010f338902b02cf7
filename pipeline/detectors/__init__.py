"""Attack detectors, one per module, all scoring "higher = more likely attacked".

- `lstm`: the paper's detector: an LSTM with ReLU over the 9 SHAP rows (9 x 1000).
- `mlp`: an MLP on the flattened SHAP values (scikit-learn).
- `mahalanobis`: class-conditional Gaussian distance on the GAP features (Lee et al. 2018).
- `lid`: local intrinsic dimensionality of the GAP features (Ma et al. 2018).
- `squeeze`: pose change under bit-depth reduction and median filtering of the input (Xu et al. 2018).
- `metrics`: validation threshold, detection metrics overall and per eps, ROC points.
"""
