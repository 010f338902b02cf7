"""Issue 38's 2 x 2 ablation of the paper's LSTM detector: FGSM as we deliver it (clipped to [0, 1], stored as 8 bits)
or as the paper's equation prints it (unclipped floats, `pipeline.attacks.literal`), crossed with our strict detector
protocol or the paper's (`pipeline.evaluation.protocols`). Each cell trains one LSTM detector (the `rpod detect`
recipe) on clean samples and the attacked samples of every eps, and reports its test rates per eps.

The two FGSM variants of a protocol attack the same images (one sample plan per protocol, the clean samples shared),
and both protocols' cells use the same split of their plan, so within a protocol only the attack differs and within
an attack only the protocol. `protocol_values` computes a protocol's SHAP values (the closed form of
`pipeline.shap.ExactShap`) for both variants; `run_ablation` fits and measures the four cells, `learning_curve` one
cell on fractions of its training samples. On image sequences (the integrated evaluation's trajectories, the lab's),
`attacked_features` gives the GAP features of the frames as onboard under either FGSM variant and `flag_counts` a
detector's per-sequence counts on them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

import numpy as np
import torch

from pipeline.attacks.literal import VARIANTS, fgsm_variant
from pipeline.detectors.lstm import LSTMConfig, train_lstm
from pipeline.evaluation.protocols import neighbour_fraction, random_split, shared_fraction
from pipeline.evaluation.rates import DetectionRates, rates_by_eps
from pipeline.evaluation.splits import grouped_split

PROTOCOLS = ("strict", "paper")  # ours: grouped by source image / the paper's: random per sample (leaky)


@dataclass(frozen=True, eq=False)
class ProtocolSamples:
    """One protocol's SHAP samples: its plan (eps, source image, its approach and frame) and, per FGSM variant
    (`pipeline.attacks.literal.VARIANTS`), the SHAP values (N, 9, F) float32; the clean rows are the same in each."""

    protocol: str
    eps: np.ndarray  # (N,) float: 0 = clean, else the FGSM budget (pixels in [0, 1])
    source: np.ndarray  # (N,) int: the source image of each sample
    sequence: np.ndarray  # (N,) int: the approach (sequence or trajectory) of the source image
    frame: np.ndarray  # (N,) int: its frame number in that approach
    values: dict[str, np.ndarray]


@dataclass(frozen=True, eq=False)
class CellResult:
    """One cell: its detector's test rates ("all" and per eps, Wilson), the LSTM fit, and how leaky its split is."""

    attack: str  # "ours" | "paper"
    protocol: str  # "strict" | "paper"
    rates: dict[str, DetectionRates]
    threshold: float  # on the detector's probability, chosen on the validation samples
    epochs: int
    best_epoch: int
    counts: dict[str, int]  # train, validation, test samples
    shared: float  # test samples whose source image is also a train/validation sample
    neighbours: float  # ... or a frame of the same approach at most one frame away
    eps_set: str = "ablation"  # its detector's eps: "ablation" (ablation.eps) | "paper" (the paper's five)
    detector: Any = None  # the fitted LSTMDetector (threshold set), for the sequences

    @property
    def leaky(self) -> bool:
        """True when test samples share source images with the samples the detector was fitted or selected on."""
        return self.shared > 0


def protocol_split(
    protocol: str, source: np.ndarray, eps: np.ndarray, test_fraction: float, val_fraction: float, seed: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(train, validation, test) sample indices of a protocol: "strict" grouped by source image and stratified by eps
    (`grouped_split`), "paper" random per sample (`random_split`). Raises ValueError for another protocol."""
    if protocol == "strict":
        return grouped_split(source, np.round(np.asarray(eps, np.float64), 6), test_fraction, val_fraction, seed)
    if protocol == "paper":
        return random_split(len(source), test_fraction, val_fraction, seed)
    raise ValueError(f"unknown detector protocol {protocol!r}; choose one of {', '.join(PROTOCOLS)}")


def protocol_values(
    model: Any,
    shap: Callable[[torch.Tensor], torch.Tensor],
    loss_fn: Any,
    images: np.ndarray,
    targets: np.ndarray,
    eps: np.ndarray,
    batch_size: int = 64,
    progress: Callable[[int], None] | None = None,
) -> dict[str, np.ndarray]:
    """SHAP values (N, 9, F) float32 of a protocol's samples under each FGSM variant.

    `images` uint8 (N, H, W, 3) are the source images of the samples, `targets` (N, 9) their labels (m, 6-D), `eps`
    (N,) 0 for a clean sample; `shap` maps GAP features (B, F) to SHAP values (B, 9, F) (e.g. `ExactShap`). A clean
    sample is explained once (the same values under each variant); an attacked one is attacked by the model on
    `loss_fn` at its eps once per variant. `progress` gets the number of samples done after each batch.
    """
    eps = np.asarray(eps, np.float64)
    out: dict[str, list[np.ndarray]] = {v: [] for v in VARIANTS}
    for start in range(0, len(eps), batch_size):
        sl = slice(start, min(start + batch_size, len(eps)))
        x = torch.from_numpy(np.ascontiguousarray(images[sl])).permute(0, 3, 1, 2).float() / 255
        y = torch.tensor(np.asarray(targets[sl], np.float32))
        e = eps[sl]
        clean = _explain(model, shap, x)
        for v in VARIANTS:
            values = clean.copy()
            for level in sorted(set(e[e > 0].tolist())):
                rows = np.flatnonzero(e == level)
                values[rows] = _explain(model, shap, fgsm_variant(model, loss_fn, level, v)(x[rows], y[rows]))
            out[v].append(values)
        if progress is not None:
            progress(sl.stop - sl.start)
    return {v: np.concatenate(parts) for v, parts in out.items()}


def _explain(model: Any, shap: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor) -> np.ndarray:
    """SHAP values (B, 9, F) float32 of float images (B, 3, H, W) through the model's GAP features."""
    with torch.no_grad():
        return shap(model.forward_features(x)).cpu().numpy().astype(np.float32)


def run_cell(
    samples: ProtocolSamples,
    attack: str,
    split: tuple[np.ndarray, np.ndarray, np.ndarray],
    config: LSTMConfig,
    fit: dict[str, Any],
    seed: int,
    device: str | torch.device = "cpu",
    eps_set: str = "ablation",
) -> CellResult:
    """Fit the LSTM detector of one cell on `split`'s train part (early stopping and threshold on its validation
    part; `fit`: epochs, patience, batch_size, lr of `train_lstm`) and measure it on the test part."""
    tr, va, te = split
    x, y = samples.values[attack], (samples.eps > 0).astype(np.int64)
    res = train_lstm(x[tr], y[tr], x[va], y[va], config, seed=seed, device=device, **fit)
    flagged = res.model.predict(x[te]).astype(bool)
    seen = np.concatenate([tr, va])
    return CellResult(
        attack=attack,
        protocol=samples.protocol,
        rates=rates_by_eps(y[te] == 1, flagged, samples.eps[te]),
        threshold=float(res.model.threshold),
        epochs=len(res.history),
        best_epoch=res.best_epoch,
        counts={"train": len(tr), "validation": len(va), "test": len(te)},
        shared=shared_fraction(samples.source, seen, te),
        neighbours=neighbour_fraction(samples.sequence, samples.frame, seen, te),
        eps_set=eps_set,
        detector=res.model,
    )


def run_ablation(
    protocols: list[ProtocolSamples],
    config: LSTMConfig,
    fit: dict[str, Any],
    test_fraction: float,
    val_fraction: float,
    seed: int,
    device: str | torch.device = "cpu",
    eps_set: str = "ablation",
) -> list[CellResult]:
    """The cells FGSM variant x protocol, in the order (ours, strict), (paper, strict), (ours, paper), (paper, paper)
    for protocols given strict then paper: one split per protocol (seeded), one LSTM per cell (same seed)."""
    cells = []
    for p in protocols:
        split = protocol_split(p.protocol, p.source, p.eps, test_fraction, val_fraction, seed)
        cells += [run_cell(p, attack, split, config, fit, seed, device, eps_set) for attack in VARIANTS]
    return cells


def learning_curve(
    samples: ProtocolSamples,
    attack: str,
    fractions: list[float],
    config: LSTMConfig,
    fit: dict[str, Any],
    test_fraction: float,
    val_fraction: float,
    seed: int,
    device: str | torch.device = "cpu",
    eps_set: str = "ablation",
) -> list[CellResult]:
    """One cell's detector fitted on the first `fractions` of its training samples (a seeded permutation of the
    protocol's training part, so a smaller set lies inside a larger one; the validation and test parts as in
    `run_ablation`): how its test rates grow with the training samples."""
    tr, va, te = protocol_split(samples.protocol, samples.source, samples.eps, test_fraction, val_fraction, seed)
    order = np.random.default_rng(seed).permutation(tr)
    return [
        run_cell(
            samples,
            attack,
            (np.sort(order[: max(1, int(round(f * len(tr))))]), va, te),
            config,
            fit,
            seed,
            device,
            eps_set,
        )
        for f in fractions
    ]


def attacked_features(
    model: Any,
    loss_fn: Any,
    images: np.ndarray,
    targets: np.ndarray,
    attacked: np.ndarray,
    variant: str,
    eps: float,
    batch_size: int = 64,
) -> np.ndarray:
    """GAP features (N, F) float32 of a sequence's frames as onboard: the frames `attacked` ((N,) bool, a schedule)
    replaced by the FGSM variant at `eps` against their own labels (`fgsm_variant`: "ours" stored as 8 bits, "paper"
    unclipped floats), the others clean. `images` uint8 (N, H, W, 3), `targets` (N, 9) (m, 6-D)."""
    attack = fgsm_variant(model, loss_fn, eps, variant)
    out = []
    for lo in range(0, len(images), batch_size):
        hi = min(lo + batch_size, len(images))
        x = torch.from_numpy(np.ascontiguousarray(images[lo:hi])).permute(0, 3, 1, 2).float() / 255
        hit = torch.from_numpy(np.asarray(attacked[lo:hi], bool))
        if hit.any():
            x = x.clone()
            x[hit] = attack(x[hit], torch.tensor(np.asarray(targets[lo:hi], np.float32))[hit])
        with torch.no_grad():
            out.append(model.forward_features(x).cpu().numpy().astype(np.float32))
    return np.concatenate(out) if out else np.zeros((0, 0), np.float32)


def flag_counts(
    features: list[np.ndarray],
    attacked: list[np.ndarray],
    shap: Callable[[torch.Tensor], torch.Tensor],
    detector: Any,
    threshold: float,
) -> np.ndarray:
    """Per sequence the counts (flagged attacked, attacked, flagged clean, clean) (G, 4) (`rates.COUNTS`) of a
    detector (`predict_proba` of SHAP values) at `threshold` on the sequences' GAP features (`attacked_features`)."""
    rows = []
    for feats, att in zip(features, attacked):
        with torch.no_grad():
            values = shap(torch.from_numpy(feats)).cpu().numpy()
        flag, att = detector.predict_proba(values) >= threshold, np.asarray(att, bool)
        rows.append([int((flag & att).sum()), int(att.sum()), int((flag & ~att).sum()), int((~att).sum())])
    return np.array(rows, dtype=np.int64).reshape(-1, 4)
