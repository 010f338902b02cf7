"""DeepSHAP values of the pose network's GAP features for each of its 9 outputs.

The pose model is `forward_head(forward_features(x))`: features `a` (B, 1000) from the Global
Average Pooling layer, then the heads give 9 outputs (position in metres, then the 6-D rotation).
When the heads are affine (`y = W a + b`), DeepSHAP with a background set is exact and closed-form:

    phi[b, j, i] = W[j, i] * (a[b, i] - mean_background[i])

so a (9, 1000) explanation per image costs one broadcast multiply. For a head that is not affine,
`deep_shap` runs the `shap` library's DeepExplainer on the head module (about 10^5 times slower).
`explain(..., method="auto")` picks the closed form when the head is affine.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
from torch import nn

Method = Literal["auto", "exact", "deep"]


class Head(nn.Module):
    """The part of a pose model after the GAP layer as a module: features (B, D) -> outputs (B, 9)."""

    def __init__(self, model: nn.Module):
        super().__init__()
        self.model = model

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return self.model.forward_head(features)


@dataclass(frozen=True)
class AffineHead:
    """`y = features @ weight.T + bias`: weight (n_outputs, n_features), bias (n_outputs,), float32."""

    weight: np.ndarray
    bias: np.ndarray


def affine_head(
    model: nn.Module, n_features: int, probe: np.ndarray | None = None, rtol: float = 1e-5, seed: int = 0
) -> AffineHead | None:
    """Read the head of `model` as an affine map, or None when it is not affine.

    Works from `model.forward_head` alone (no attribute names): in float64 and eval mode, the bias
    is the output at 0 and column i of the weight the output at the unit vector e_i minus the bias.
    The map is then checked on random points around `probe` (features (N, D), e.g. the background;
    standard normal points when None): a head with a ReLU, a product or a normalisation fails it.
    """
    head = Head(copy.deepcopy(model)).double().eval()
    with torch.no_grad():
        basis = torch.cat([torch.zeros(1, n_features, dtype=torch.float64), torch.eye(n_features, dtype=torch.float64)])
        out = head(basis)
        bias = out[0]
        weight = (out[1:] - bias).T
        gen = torch.Generator().manual_seed(seed)
        if probe is None:
            centre, spread = torch.zeros(n_features, dtype=torch.float64), torch.ones(n_features, dtype=torch.float64)
        else:
            p = torch.as_tensor(np.asarray(probe), dtype=torch.float64)
            centre, spread = p.mean(0), p.std(0) + p.abs().mean(0) + 1e-3
        z = centre + spread * torch.randn(64, n_features, dtype=torch.float64, generator=gen)
        y = head(z)
        y_lin = z @ weight.T + bias
        if not torch.allclose(y, y_lin, rtol=rtol, atol=rtol * float(y.abs().max()) + 1e-9):
            return None
    return AffineHead(weight.numpy().astype(np.float32), bias.numpy().astype(np.float32))


def background_mean(features: np.ndarray) -> np.ndarray:
    """Mean GAP feature vector (D,) float32 over background features (N, D)."""
    features = np.asarray(features)
    if features.ndim != 2 or len(features) == 0:
        raise ValueError(f"background features must be a non-empty (N, D) array, got shape {features.shape}")
    return features.astype(np.float64).mean(0).astype(np.float32)


def exact_shap(
    features: np.ndarray | torch.Tensor, weight: np.ndarray | torch.Tensor, bg_mean: np.ndarray | torch.Tensor
) -> torch.Tensor:
    """Closed-form DeepSHAP of an affine head: (B, D) features -> (B, n_outputs, D) values.

    phi[b, j, i] = weight[j, i] * (features[b, i] - bg_mean[i]); the values of one output sum to
    that output minus its mean over the background. Float32 torch tensor on the features' device.
    """
    a = torch.as_tensor(features, dtype=torch.float32)
    w = torch.as_tensor(weight, dtype=torch.float32, device=a.device)
    mu = torch.as_tensor(bg_mean, dtype=torch.float32, device=a.device)
    return w.unsqueeze(0) * (a - mu).unsqueeze(1)


class ExactShap(nn.Module):
    """The closed-form SHAP core every chain uses (pipeline/defense/chain.py onboard, its folded LSTM
    path, pipeline/attacks/adaptive.py for the attacker): the affine head's `weight` (9, D) and the
    background mean (D,) as float32 buffers; GAP features (B, D) -> SHAP values (B, 9, D) by `exact_shap`."""

    def __init__(self, weight: np.ndarray | torch.Tensor, background_mean: np.ndarray | torch.Tensor):
        super().__init__()
        self.register_buffer("weight", torch.as_tensor(np.asarray(weight), dtype=torch.float32).contiguous())
        self.register_buffer(
            "background_mean", torch.as_tensor(np.asarray(background_mean), dtype=torch.float32).contiguous()
        )
        if self.weight.ndim != 2 or self.background_mean.shape != (self.weight.shape[1],):
            raise ValueError(
                f"head weight {tuple(self.weight.shape)} and background mean "
                f"{tuple(self.background_mean.shape)} do not fit (need (9, D) and (D,))"
            )

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """GAP features (B, D) -> SHAP values (B, 9, D), float32, on the features' device."""
        return exact_shap(features, self.weight, self.background_mean)


def deep_shap(model: nn.Module, features: np.ndarray, background: np.ndarray, batch_size: int = 64) -> np.ndarray:
    """DeepSHAP of the head through `shap.DeepExplainer`: (B, D) -> (B, n_outputs, D) float32.

    For any head (affine or not); `shap` is imported here because only this path needs it.
    """
    import shap

    head = Head(model).eval()
    device = next(head.parameters()).device  # the explainer's tensors live with the head's weights
    bg = torch.as_tensor(np.asarray(background), dtype=torch.float32, device=device)
    explainer = shap.DeepExplainer(head, bg)
    out = []
    for start in range(0, len(features), batch_size):
        x = torch.as_tensor(np.asarray(features[start : start + batch_size]), dtype=torch.float32, device=device)
        values = explainer.shap_values(x, check_additivity=False)  # (B, D, n_outputs)
        out.append(np.transpose(np.asarray(values), (0, 2, 1)))
    return np.concatenate(out).astype(np.float32)


class Explainer:
    """SHAP values of GAP features for every head output, fixed to one model and one background.

    `method`: "exact" (closed form, needs an affine head), "deep" (shap.DeepExplainer) or "auto"
    (exact when `affine_head` finds the head affine, else deep). `self.method` is the one chosen.
    """

    def __init__(self, model: nn.Module, background: np.ndarray, method: Method = "auto"):
        if method not in ("auto", "exact", "deep"):
            raise ValueError(f"unknown SHAP method {method!r}; choose auto, exact or deep")
        background = np.asarray(background, dtype=np.float32)
        self.model = model
        self.background = background
        self.bg_mean = background_mean(background)
        n_features = background.shape[1]
        self.affine = affine_head(model, n_features, probe=background) if method != "deep" else None
        if method == "exact" and self.affine is None:
            raise ValueError(
                "method 'exact' needs an affine (linear) head after the GAP layer; use 'deep' or 'auto' for this model"
            )
        self.method: str = "exact" if self.affine is not None else "deep"

    def __call__(self, features: np.ndarray) -> np.ndarray:
        """(B, D) GAP features -> (B, n_outputs, D) float32 SHAP values."""
        if self.method == "exact":
            return exact_shap(features, self.affine.weight, self.bg_mean).numpy()
        return deep_shap(self.model, features, self.background)


def gap_features(model: nn.Module, images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """GAP features (N, D) and pose outputs (N, 9: metres, then 6-D) of uint8 RGB images (N, H, W, 3),
    computed on the model's device (the images cross to it as uint8)."""
    with torch.no_grad():
        device = next(model.parameters()).device
        x = torch.from_numpy(np.ascontiguousarray(images)).to(device).permute(0, 3, 1, 2).float() / 255
        f = model.forward_features(x)
        return f.cpu().numpy(), model.forward_head(f).cpu().numpy()


def draw_background(n_train: int, size: int, rng: np.random.Generator) -> np.ndarray:
    """Sorted rows of `size` distinct training images (out of `n_train`) whose features form the background."""
    if not 1 <= size <= n_train:
        raise ValueError(f"background size must be in [1, {n_train}] (training images), got {size}")
    return np.sort(rng.choice(n_train, size, replace=False))


def plan_sources(normal: int, per_eps: int, n_eps: int) -> int:
    """Source images a sample plan needs: each is explained clean at most once and attacked at most once."""
    return max(int(normal), int(per_eps) * int(n_eps))


def sample_plan(
    normal: int, per_eps: int, eps: list[float], pool: np.ndarray, rng: np.random.Generator
) -> dict[str, np.ndarray]:
    """The samples to explain: `normal` clean ones, then `per_eps` attacked ones per eps (L-inf, pixels
    in [0, 1]), all from the same source images of `pool` (indices of images the pose network never saw).

    `plan_sources` images are drawn from `pool` without replacement, in random order; the first
    `normal` are explained clean, and a random `per_eps x len(eps)` of them attacked, dealt to the eps
    in blocks. With normal = per_eps x len(eps) (every profile) each source image is explained twice,
    once clean and once attacked at one eps, so the two classes show the same images and differ only
    by the attack. Returns {"index": pool indices int64, "eps": float32 (0 = clean)}.
    """
    n = plan_sources(normal, per_eps, len(eps))
    if n > len(pool):
        raise ValueError(f"{n} source images needed but the pool holds {len(pool)}")
    sources = rng.choice(np.asarray(pool, dtype=np.int64), n, replace=False)
    attacked = rng.permutation(sources)[: int(per_eps) * len(eps)]
    eps_out = np.concatenate([np.zeros(int(normal)), np.repeat(np.asarray(eps, dtype=np.float64), int(per_eps))])
    return {
        "index": np.concatenate([sources[: int(normal)], attacked]).astype(np.int64),
        "eps": eps_out.astype(np.float32),
    }
