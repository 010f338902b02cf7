"""The safety chain: image -> pose -> SHAP signature -> attack flag (`OnboardChain`), its calibrated defense
(`Defended`: pipeline/defense/fusion.py) and the whole trained chain (`SafetyChain`, loaded by the one door
pipeline/formats/chain.py `load_chain`).

The pose network's GAP features `a` (B, 1000) are computed once and used twice: the affine heads
turn them into the pose (B, 9), and the closed-form DeepSHAP of those heads,
phi[b, j, i] = W[j, i] * (a[b, i] - mean_background[i]), turns them into the (B, 9, 1000)
signature the detector reads. So the chain costs the pose forward plus one broadcast multiply and
the detector's small LSTM over 9 steps. The chain keeps no state between frames: a batch of frames
gives the same result as the frames one at a time.
"""

from __future__ import annotations

import copy
import dataclasses
import warnings
from dataclasses import dataclass
from functools import partial
from typing import Any, Callable, Iterable

import numpy as np
import torch
from torch import nn

from pipeline.defense.fusion import Defense
from pipeline.defense.gate import MotionSettings
from pipeline.defense.integrity import AlertLimitSettings, alert_limit
from pipeline.defense.noise import NoiseModel
from pipeline.defense.settings import DefenseSettings
from pipeline.detectors.lstm import LSTMDetector
from pipeline.shap import ExactShap, affine_head


@dataclass(frozen=True)
class ChainOutput:
    """One batch through the chain: pose (B, 9) [m, 6-D], shap (B, 9, D), prob (B,), flag (B,) bool."""

    pose: torch.Tensor
    shap: torch.Tensor
    prob: torch.Tensor
    flag: torch.Tensor


class FoldedShapLSTM(nn.Module):
    """The onboard chain's fast path (traced by `OnboardChain` on the CPU): SHAP + LSTM folded into one graph.

    `detector` on the exact SHAP values of an affine head, from the head's GAP features:
    (B, D) features -> (SHAP values (B, n_rows, D), attack probability (B,)).

    The detector reads x[b, j] = (phi[b, j] - m_j) / s_j with phi[b, j] = W[j] * (a[b] - mu), that
    is x[b, j] = (W[j] / s_j) * (a[b] - mu) - m_j / s_j: the SHAP scaling and the standardisation
    fold into one (n_rows, D) weight and a per-row shift, so one multiply-add gives the LSTM input.
    The input projection keeps the detector's shared (4H, D) weight: folding it further into 9
    distinct (D, 4H) matrices needs as many multiply-adds and 9x the memory to stream. The gates
    are reordered (i, f, o | g) so that one sigmoid covers three of them, and since the cell state is
    never negative (c' = f c + i relu(g), c_0 = 0) h' = o * c' needs no ReLU: the fewest small ops,
    which is what a 9-step, 100-unit recurrence costs at batch 1. Equal to
    `detector(exact_shap(a, W, mu))` to float32 rounding; the detector's weights are copied here.
    """

    def __init__(self, detector: LSTMDetector, shap: ExactShap):
        super().__init__()
        h = self.hidden = detector.config.hidden
        order = torch.cat([torch.arange(2 * h), torch.arange(3 * h, 4 * h), torch.arange(2 * h, 3 * h)])
        inv_scale = 1.0 / detector.scale.detach().double()  # (n_rows, 1)
        cell = detector.lstm
        weight = shap.weight
        buffers = {
            "weight": weight,
            "background_mean": shap.background_mean,
            "scaled": weight.double() * inv_scale,
            "shift": -detector.mean.detach().double() * inv_scale,
            "w_in": cell.input_proj.weight.detach()[order],
            "b_in": cell.input_proj.bias.detach()[order],
            "w_hidden": cell.hidden_proj.weight.detach()[order].T,
        }
        for name, value in buffers.items():
            self.register_buffer(name, value.float().contiguous())
        self.classifier = copy.deepcopy(detector.classifier)

    def forward(self, features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        centred = (features - self.background_mean).unsqueeze(1)  # (B, 1, D)
        x = torch.addcmul(self.shift, self.scaled, centred)  # (B, n_rows, D)
        steps = torch.nn.functional.linear(x, self.w_in, self.b_in).unbind(1)
        sizes = [3 * self.hidden, self.hidden]
        ifo, g = steps[0].split(sizes, dim=1)
        i, f, o = torch.sigmoid(ifo).chunk(3, dim=1)
        c = i * torch.relu(g)
        for step in steps[1:]:
            ifo, g = torch.addmm(step, o * c, self.w_hidden).split(sizes, dim=1)
            i, f, o = torch.sigmoid(ifo).chunk(3, dim=1)
            c = torch.addcmul(f * c, i, torch.relu(g))
        prob = torch.sigmoid(self.classifier(o * c).squeeze(1))
        return self.weight * centred, prob


class OnboardChain:
    """The chain that runs onboard, frame by frame, no gradients: image -> pose, SHAP, attack flag; the
    `onboard` part of a SafetyChain (the stages, rpodguard.api, the evaluation and guidance).

    Pose model + exact SHAP (head weights, background mean) + detector, in eval mode, no grad.

    `detector` maps SHAP values (B, 9, D) to attack logits (B,); a frame is flagged when
    sigmoid(logit) >= `threshold`. With `fast` (default) and an LSTM detector, frames on the CPU
    go from the GAP features through one traced and frozen TorchScript graph (`FoldedShapLSTM`: SHAP
    values, the folded standardisation, the LSTM and the probability); its results equal the
    detector's on the SHAP values to float32 rounding (tested to 1e-4). Other detectors, and
    frames on another device, take the plain path. benchmarks/chain_latency.py measures the cost.
    """

    def __init__(
        self,
        model: nn.Module,
        weight: np.ndarray | torch.Tensor,
        background_mean: np.ndarray | torch.Tensor,
        detector: nn.Module,
        threshold: float = 0.5,
        fast: bool = True,
    ):
        self.model = model.eval()
        self.detector = detector.eval()
        self.shap = ExactShap(weight, background_mean)
        self.threshold = float(threshold)
        self._fast = None
        if fast and isinstance(detector, LSTMDetector):
            example = torch.zeros(1, self.shap.weight.shape[1])
            # TorchScript is deprecated in favour of torch.compile, which needs a C++ toolchain and
            # recompiles per batch size; tracing still works in torch 2.13 and has neither cost.
            with torch.no_grad(), warnings.catch_warnings():
                warnings.simplefilter("ignore", DeprecationWarning)
                module = FoldedShapLSTM(self.detector, self.shap).eval()
                self._fast = torch.jit.freeze(torch.jit.trace(module, example))

    @classmethod
    def from_model(
        cls,
        model: nn.Module,
        background_mean: np.ndarray | torch.Tensor,
        detector: nn.Module,
        threshold: float = 0.5,
        fast: bool = True,
    ) -> "OnboardChain":
        """Read the head weights from `model` (they must form an affine map, as in PoseNet)."""
        mu = np.asarray(torch.as_tensor(background_mean, dtype=torch.float32))
        head = affine_head(model, n_features=len(mu))
        if head is None:
            raise ValueError("the safety chain needs an affine pose head (exact SHAP); this model's head is not")
        return cls(model, head.weight, mu, detector, threshold, fast)

    @torch.inference_mode()
    def __call__(self, images: torch.Tensor) -> ChainOutput:
        """(B, 3, H, W) images in [0, 1] -> ChainOutput; a single (3, H, W) frame is batched."""
        x = images.unsqueeze(0) if images.ndim == 3 else images
        features = self.model.forward_features(x)
        pose = self.model.forward_head(features)
        if self._fast is not None and features.device.type == "cpu":
            phi, prob = self._fast(features)
        else:
            phi = self.shap(features)
            prob = torch.sigmoid(self.detector(phi))
        return ChainOutput(pose, phi, prob, prob >= self.threshold)

    @torch.inference_mode()
    def pose_only(self, images: torch.Tensor) -> torch.Tensor:
        """The pose forward alone, (B, 9): the baseline the chain's cost is compared with."""
        x = images.unsqueeze(0) if images.ndim == 3 else images
        return self.model(x)


AttackFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
"""An attack as `run_sequence` calls it: (images (B, 3, H, W) in [0, 1], labels (B, 9)) -> attacked images
(not the `attack` params section, stages.config.schema.Attack)."""


@dataclass(frozen=True)
class SequenceResult:
    """A sequence through the chain: pose (N, 9), prob (N,), flag (N,) bool, as numpy arrays."""

    pose: np.ndarray
    prob: np.ndarray
    flag: np.ndarray


def run_sequence(
    chain: OnboardChain,
    images: np.ndarray,
    targets: np.ndarray,
    attacked: np.ndarray,
    attack: AttackFn | None,
    batch_size: int = 64,
    progress: Callable[[Iterable[int]], Iterable[int]] = iter,
) -> SequenceResult:
    """Frames as onboard: attacked frames are replaced by `attack(x, y)` against their own true label.

    images: (N, H, W, 3) uint8; targets: (N, 9) labels (m, 6-D); attacked: (N,) bool. `attack`
    takes and returns (B, 3, H, W) images in [0, 1] (it may run with gradients). Frames are batched
    for speed only: the chain is stateless, so each frame's result is that of the frame alone.
    """
    n = len(images)
    attacked = np.asarray(attacked, dtype=bool)
    if len(targets) != n or len(attacked) != n:
        raise ValueError(f"images ({n}), targets ({len(targets)}) and schedule ({len(attacked)}) differ in length")
    if attacked.any() and attack is None:
        raise ValueError("frames are scheduled for attack but no attack was given")
    pose, prob, flag = np.zeros((n, 9), np.float32), np.zeros(n), np.zeros(n, bool)
    for lo in progress(range(0, n, batch_size)):
        hi = min(lo + batch_size, n)
        x = torch.from_numpy(np.ascontiguousarray(images[lo:hi])).permute(0, 3, 1, 2).float() / 255.0
        hit = torch.from_numpy(attacked[lo:hi])
        if hit.any():
            y = torch.from_numpy(np.array(targets[lo:hi], dtype=np.float32))
            x = x.clone()
            x[hit] = attack(x[hit], y[hit])
        out = chain(x)
        pose[lo:hi], prob[lo:hi], flag[lo:hi] = out.pose.numpy(), out.prob.numpy(), out.flag.numpy()
    return SequenceResult(pose, prob, flag)


@dataclass(frozen=True)
class Defended:
    """A chain's calibrated defense (pipeline/defense/fusion.py): the fusion settings (with the calibrated
    detector threshold and doubt level), the motion filter's settings (with the calibrated h), the inflated
    noise model and the alert limit its availability is judged against (PL <= AL; None: no availability check)."""

    settings: DefenseSettings
    motion: MotionSettings
    noise: NoiseModel
    alert: AlertLimitSettings | None = None

    def new(self, fusion: str | None = None) -> Defense:
        """A fresh Defense (one per trajectory or closed-loop run), optionally with another fusion."""
        s = self.settings if fusion is None else dataclasses.replace(self.settings, fusion=fusion)
        limit = None if self.alert is None else partial(alert_limit, settings=self.alert)
        return Defense(s, self.motion, self.noise, limit)

    def defense(self) -> Defense:
        """`new()` by the name pipeline/evaluation/integrity_runs.py calls."""
        return self.new()


@dataclass(frozen=True)
class SafetyChain:
    """A trained chain: `name` (its pose model: standard or robust), `onboard` (the pose model, exact SHAP and
    its detector), the pose model's learned training loss (`loss`, what attacks ascend), its file hash and
    checkpoint facts (`checkpoint`: arch, input_size, K, labels_hash, meta; no weights), the files it was read
    from (pose, detector, defense) and, once calibrated, its defense (`defended`) and the defense file's record
    (`calibration`: pipeline.formats.defense.DefenseFile; None before `rpod calibrate`)."""

    name: str
    onboard: OnboardChain
    loss: nn.Module
    pose_hash: str
    checkpoint: dict[str, Any]
    files: tuple[Any, Any, Any]
    defended: Defended | None = None
    calibration: Any = None

    @property
    def model(self) -> nn.Module:
        """The pose network (eval mode)."""
        return self.onboard.model

    @property
    def threshold(self) -> float:
        """The detector checkpoint's own flag threshold (the defended chain flies `defended.settings.threshold`)."""
        return self.onboard.threshold
