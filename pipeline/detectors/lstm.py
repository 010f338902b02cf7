"""The paper's attack detector: an LSTM with ReLU over the 9 SHAP rows, dense layers, a sigmoid.

Input: SHAP values (B, 9, 1000), one row per pose output (tx, ty, tz, r0..r5), read as a sequence
of 9 steps of 1000 features. The LSTM (100 units) uses ReLU where a standard LSTM uses tanh (the
Keras `LSTM(activation="relu")` of the paper); `torch.nn.LSTM` has no such option, hence the small
cell below. Then dense ReLU layers and one logit; `predict_proba` applies the sigmoid.

The inputs are standardised per row (output) with one mean and one standard deviation over the
training set's values of that row, kept as buffers so the module takes raw SHAP values. A per-row
scale keeps the relative size of the features within a row, which is what SHAP measures (with linear
heads a row is W[j] * (a - mean_bg): a per-feature standardisation would make the 9 rows equal up to
sign); it also came out a little more accurate than a per-feature standardisation in a rehearsal. The decision threshold on the
probability is a buffer too, chosen on validation data, so a checkpoint carries everything.
"""

from __future__ import annotations

import copy
from dataclasses import asdict, dataclass, field
from typing import Any, Callable

import numpy as np
import torch
from torch import nn

from pipeline.detectors.metrics import choose_threshold
from pipeline.pose.train import check_improved, check_loss


class ReLULSTMCell(nn.Module):
    """LSTM cell with ReLU as the cell-input and output activation (gates stay sigmoid).

    i, f, o = sigmoid(.); g = relu(.); c' = f * c + i * g; h' = o * relu(c').
    """

    def __init__(self, input_size: int, hidden_size: int):
        super().__init__()
        self.hidden_size = hidden_size
        self.input_proj = nn.Linear(input_size, 4 * hidden_size)
        self.hidden_proj = nn.Linear(hidden_size, 4 * hidden_size, bias=False)
        with torch.no_grad():  # forget-gate bias 1 (Jozefowicz et al. 2015), as Keras' unit_forget_bias
            self.input_proj.bias.zero_()
            self.input_proj.bias[hidden_size : 2 * hidden_size] = 1.0

    def step(self, x_proj: torch.Tensor, h: torch.Tensor, c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """One step from the already projected input `x_proj` (B, 4H) and the state (h, c) (B, H)."""
        i, f, g, o = (x_proj + self.hidden_proj(h)).chunk(4, dim=1)
        c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.relu(g)
        h = torch.sigmoid(o) * torch.relu(c)
        return h, c

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(B, T, input_size) -> last hidden state (B, hidden_size)."""
        x_proj = self.input_proj(x)  # all steps at once
        h = x.new_zeros(x.shape[0], self.hidden_size)
        c = torch.zeros_like(h)
        for t in range(x.shape[1]):
            h, c = self.step(x_proj[:, t], h, c)
        return h


@dataclass
class LSTMConfig:
    """Architecture: sequence of `n_rows` steps of `n_features`; `hidden` LSTM units; `dense` widths."""

    n_rows: int = 9
    n_features: int = 1000
    hidden: int = 100
    dense: list[int] = field(default_factory=lambda: [64])


class LSTMDetector(nn.Module):
    """SHAP values (B, 9, 1000) -> attack logit (B,); `predict` thresholds the probability."""

    def __init__(self, config: LSTMConfig):
        super().__init__()
        self.config = config
        self.register_buffer("mean", torch.zeros(config.n_rows, 1))
        self.register_buffer("scale", torch.ones(config.n_rows, 1))
        self.register_buffer("threshold", torch.tensor(0.5))
        self.lstm = ReLULSTMCell(config.n_features, config.hidden)
        layers: list[nn.Module] = []
        width = config.hidden
        for d in config.dense:
            layers += [nn.Linear(width, d), nn.ReLU()]
            width = d
        layers.append(nn.Linear(width, 1))
        self.classifier = nn.Sequential(*layers)

    def set_normalisation(self, values: np.ndarray) -> None:
        """Per-row mean and standard deviation of training SHAP values (N, 9, 1000)."""
        v = torch.as_tensor(np.asarray(values), dtype=torch.float64)
        self.mean.copy_(v.mean(dim=(0, 2)).float()[:, None])
        self.scale.copy_(v.std(dim=(0, 2)).clamp_min(1e-12).float()[:, None])

    def forward(self, values: torch.Tensor) -> torch.Tensor:
        x = (values - self.mean) / self.scale
        return self.classifier(self.lstm(x)).squeeze(1)

    @torch.no_grad()
    def predict_proba(self, values: np.ndarray | torch.Tensor, batch_size: int = 1024) -> np.ndarray:
        """Probability of "attacked" per sample, (N,) float64."""
        self.eval()
        v = torch.as_tensor(np.asarray(values), dtype=torch.float32)
        out = [torch.sigmoid(self(v[s : s + batch_size])) for s in range(0, len(v), batch_size)]
        return torch.cat(out).double().numpy() if out else np.zeros(0)

    def predict(self, values: np.ndarray | torch.Tensor) -> np.ndarray:
        """1 = attacked, 0 = clean, by the stored threshold."""
        return (self.predict_proba(values) >= float(self.threshold)).astype(np.int64)


def to_checkpoint(model: LSTMDetector, extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """A dict of tensors and plain values (loadable with torch.load(weights_only=True))."""
    return {
        "kind": "lstm",
        "config": asdict(model.config),
        "threshold": float(model.threshold),
        "state_dict": model.state_dict(),
        **(extra or {}),
    }


def from_checkpoint(ckpt: dict[str, Any]) -> LSTMDetector:
    """Rebuild a detector (eval mode) from `to_checkpoint`'s dict."""
    if ckpt.get("kind") != "lstm":
        raise ValueError(f"not an LSTM detector checkpoint (kind={ckpt.get('kind')!r})")
    model = LSTMDetector(LSTMConfig(**ckpt["config"]))
    model.load_state_dict(ckpt["state_dict"])
    return model.eval()


@dataclass
class TrainResult:
    model: LSTMDetector
    history: list[dict[str, float]]  # per epoch: train_loss, val_loss, val_accuracy
    best_epoch: int


def train_lstm(
    x_train: np.ndarray,
    y_train: np.ndarray,
    x_val: np.ndarray,
    y_val: np.ndarray,
    config: LSTMConfig,
    *,
    epochs: int = 200,
    patience: int = 20,
    batch_size: int = 64,
    lr: float = 1.0,
    seed: int = 0,
    on_epoch: Callable[[dict[str, float]], None] | None = None,
    progress: str | None = None,
    device: str | torch.device = "cpu",
) -> TrainResult:
    """Fit with Adadelta and binary cross-entropy; early stopping on the validation loss.

    Training stops after `patience` epochs without a lower validation loss; the weights of the
    best epoch are kept, and the threshold is then chosen on the validation probabilities
    (`choose_threshold`: highest validation accuracy). `on_epoch` gets each epoch's record;
    `progress` (a description) shows a tqdm bar over the epochs with the validation loss and accuracy.
    The fit runs on `device` (the shuffles are drawn on the CPU, so they are the same on every device);
    the returned model is on the CPU, where the chain runs it.
    """
    if progress is not None:
        return _with_progress(
            progress,
            epochs,
            on_epoch,
            lambda cb: train_lstm(
                x_train,
                y_train,
                x_val,
                y_val,
                config,
                epochs=epochs,
                patience=patience,
                batch_size=batch_size,
                lr=lr,
                seed=seed,
                on_epoch=cb,
                device=device,
            ),
        )
    _check_settings(config, epochs, patience, batch_size, lr)
    if not (np.isfinite(x_train).all() and np.isfinite(x_val).all()):
        raise ValueError("LSTM detector inputs hold NaN or infinite values")
    model = _seeded_model(config, x_train, seed, device)
    arrays = (x_train, y_train, x_val, y_val)
    best_state, best_epoch, history = _early_stopping(
        model, arrays, device, lr, seed, epochs, patience, batch_size, on_epoch
    )
    check_improved(best_epoch, len(history))
    model.load_state_dict(best_state)
    model.cpu()
    model.threshold.fill_(choose_threshold(model.predict_proba(x_val), y_val))
    return TrainResult(model.eval(), history, best_epoch)


def _seeded_model(config: LSTMConfig, x_train: np.ndarray, seed: int, device: str | torch.device) -> LSTMDetector:
    """A fresh detector, its weights drawn after torch.manual_seed(seed), standardised on x_train, on `device`."""
    torch.manual_seed(seed)
    model = LSTMDetector(config)
    model.set_normalisation(x_train)
    model.to(device)
    return model


def _early_stopping(
    model: LSTMDetector,
    arrays: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    device: str | torch.device,
    lr: float,
    seed: int,
    epochs: int,
    patience: int,
    batch_size: int,
    on_epoch: Callable[[dict[str, float]], None] | None,
) -> tuple[dict[str, torch.Tensor], int, list[dict[str, float]]]:
    """Adadelta at `lr` on binary cross-entropy over the training set of `arrays` (x_train, y_train, x_val,
    y_val), on `device`, its shuffles drawn from a CPU generator seeded with `seed`, until `patience`
    epochs bring no lower validation loss: (the best epoch's state dict, that epoch (0: none improved), every
    epoch's record)."""
    xt, yt, xv, yv = (torch.as_tensor(np.asarray(a), dtype=torch.float32).to(device) for a in arrays)
    opt = torch.optim.Adadelta(model.parameters(), lr=lr)
    loss_fn = nn.BCEWithLogitsLoss()
    gen = torch.Generator().manual_seed(seed)
    best_loss, best_state, best_epoch, stale = float("inf"), copy.deepcopy(model.state_dict()), 0, 0
    history: list[dict[str, float]] = []
    for epoch in range(1, epochs + 1):
        total = _train_epoch(model, xt, yt, opt, loss_fn, torch.randperm(len(xt), generator=gen), batch_size, epoch)
        val_loss, val_acc = _validate(model, xv, yv, loss_fn)
        record = {"epoch": epoch, "train_loss": total / len(xt), "val_loss": val_loss, "val_accuracy": val_acc}
        history.append(record)
        if on_epoch is not None:
            on_epoch(record)
        if val_loss < best_loss - 1e-7:
            best_loss, best_state, best_epoch, stale = val_loss, copy.deepcopy(model.state_dict()), epoch, 0
        else:
            stale += 1
            if stale >= patience:
                break
    return best_state, best_epoch, history


def _validate(model: LSTMDetector, xv: torch.Tensor, yv: torch.Tensor, loss_fn: nn.Module) -> tuple[float, float]:
    """(loss, accuracy at logit 0) of the model in eval mode on the validation set, in batches of 1024."""
    model.eval()
    with torch.no_grad():
        logits = torch.cat([model(xv[s : s + 1024]) for s in range(0, len(xv), 1024)])
        val_loss = float(loss_fn(logits, yv))
        val_acc = float(((logits >= 0).float() == yv).float().mean())
    return val_loss, val_acc


def _check_settings(config: LSTMConfig, epochs: int, patience: int, batch_size: int, lr: float) -> None:
    """Refuse sizes below 1 and a learning rate that is not > 0, naming them."""
    sizes = {
        "epochs": epochs,
        "patience": patience,
        "batch_size": batch_size,
        "hidden": config.hidden,
        **{f"dense[{i}]": w for i, w in enumerate(config.dense)},
    }
    small = [f"{k}={v}" for k, v in sizes.items() if int(v) < 1]
    if small or not lr > 0:
        raise ValueError(f"LSTM detector settings must be positive: {', '.join(small) or f'lr={lr}'}")


def _train_epoch(
    model: LSTMDetector,
    xt: torch.Tensor,
    yt: torch.Tensor,
    opt: torch.optim.Optimizer,
    loss_fn: nn.Module,
    perm: torch.Tensor,
    batch_size: int,
    epoch: int,
) -> float:
    """One pass over the training set in the order `perm` (drawn on the CPU) -> sum of loss * batch size."""
    model.train()
    total = 0.0
    for s in range(0, len(xt), batch_size):
        idx = perm[s : s + batch_size].to(xt.device)
        loss = loss_fn(model(xt[idx]), yt[idx])
        check_loss(loss.item(), f"epoch {epoch}")
        opt.zero_grad()
        loss.backward()
        opt.step()
        total += loss.item() * len(idx)
    return total


def _with_progress(
    desc: str,
    epochs: int,
    on_epoch: Callable[[dict[str, float]], None] | None,
    fit: Callable[[Callable[[dict[str, float]], None]], TrainResult],
) -> TrainResult:
    """Run `fit(callback)` with a tqdm bar over the epochs (closed when the fit returns)."""
    from tqdm import tqdm

    bar = tqdm(total=epochs, desc=desc, unit="epoch")

    def callback(rec: dict[str, float]) -> None:
        bar.update(1)
        bar.set_postfix(val_loss=f"{rec['val_loss']:.4f}", val_acc=f"{rec['val_accuracy']:.3f}")
        if on_epoch is not None:
            on_epoch(rec)

    result = fit(callback)
    bar.close()
    return result
