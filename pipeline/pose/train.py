"""Training loop for the pose CNN: Adam, a cyclic or cosine LR schedule (pipeline/pose/optim.py), an optional
EMA of the weights, optional PGD-k adversarial training (pipeline/pose/adversarial.py), best-by-validation
tracking.

With `ema` > 0 the exponential moving average of the weights is what is validated every epoch, what the
best checkpoint is chosen from and what `best_state` holds (the raw weights only train).

Works in one process or under DistributedDataParallel: when `torch.distributed` is initialised
(the caller sets it up, e.g. from torchrun's environment variables), the model and the loss's
learnable weights are wrapped together in DDP, the training set is sharded with a
DistributedSampler and the validation set evaluated in shards that are gathered on every rank.
The caller passes a validation set carved from the training data (pipeline.evaluation.splits.holdout): `fit`
never sees the test split, so the checkpoint it keeps is not selected on test data.

The model selection score is the ESA SPEED score (pipeline/pose/metrics.py); with an adversary, plus the
error of its attacked validation images (`Adversary.validate`, `Adversary.selection_error`): their mean relative
position error ||p - p_gt|| / ||p_gt|| when training attacks the position-weighted loss (the harm is a position
error), their SPEED score (position and attitude) when it attacks the suite's objectives.
"""

from __future__ import annotations

import copy
import math
import os
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np
import torch
import torch.distributed as dist
from torch import nn
from torch.utils.data import DataLoader, Dataset, DistributedSampler
from tqdm import tqdm

from pipeline.pose.adversarial import Adversary
from pipeline.pose.augment import augment
from pipeline.pose.loss import PoseLoss
from pipeline.pose.metrics import pose_errors, speed_score
from pipeline.pose.optim import SCHEDULES, WeightEMA, make_scheduler
from pipeline.pose.settings import AugmentConfig

LOSS_WEIGHT_LR_FACTOR = 10.0


class DivergenceError(ValueError):
    """Training went wrong in a way no checkpoint should survive: a non-finite loss, or no epoch improved."""


def check_loss(value: float, where: str) -> None:
    """Raise DivergenceError when a training loss is NaN or infinite (`where`: e.g. "epoch 3")."""
    if not math.isfinite(value):
        raise DivergenceError(f"training diverged: loss {value} at {where} (learning rate too high, or bad inputs)")


def check_improved(best_epoch: int, epochs_run: int) -> None:
    """Raise DivergenceError when no epoch gave a finite, better validation score (best_epoch < 1)."""
    if best_epoch < 1:
        raise DivergenceError(
            f"no epoch of {epochs_run} improved on the untrained model (every score non-finite); nothing to save"
        )


class PoseDataset(Dataset):
    """uint8 (N, H, W, 3) RGB images + (N, 9) targets -> (uint8 (H, W, 3) tensor, float32 (9,) tensor).

    `images` is anything indexable by an int (a numpy array, or a zarr array: then each item is a
    read from the store). With `augment` set, every item is augmented with an RNG seeded by
    (seed, epoch, index), so results do not depend on the number of loader workers.
    """

    def __init__(self, images: Any, targets: np.ndarray, augment_cfg: AugmentConfig | None = None, seed: int = 0):
        if len(images) != len(targets):
            raise ValueError(f"{len(images)} images but {len(targets)} targets")
        bad = ~np.isfinite(np.asarray(targets, dtype=np.float64)).all(axis=1)
        if bad.any():
            raise ValueError(f"{int(bad.sum())} targets are NaN or infinite (first: row {int(np.argmax(bad))})")
        self.images, self.targets = images, torch.tensor(np.asarray(targets, dtype=np.float32))
        self.augment_cfg, self.seed, self.epoch = augment_cfg, seed, 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def __len__(self) -> int:
        return len(self.targets)

    def __getitem__(self, i: int) -> tuple[torch.Tensor, torch.Tensor]:
        img = np.asarray(self.images[i])
        if self.augment_cfg is not None:
            img = augment(img, np.random.default_rng([self.seed, self.epoch, i]), self.augment_cfg)
        return torch.from_numpy(np.ascontiguousarray(img)), self.targets[i]


def to_input(batch: torch.Tensor, channels_last: bool = True) -> torch.Tensor:
    """uint8 (B, H, W, 3) -> float (B, 3, H, W) in [0, 1] (channels_last memory layout if asked)."""
    x = batch.permute(0, 3, 1, 2).float().div_(255.0)
    return x.contiguous(memory_format=torch.channels_last if channels_last else torch.contiguous_format)


def make_deterministic(seed: int) -> None:
    """Seed torch's generators and switch to deterministic algorithms: call before anything random is
    built (the network's initial weights), so two runs on one machine with the same thread count give
    bit-identical weights. On CUDA, ops without a deterministic kernel warn instead of failing."""
    os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    torch.manual_seed(seed)
    torch.use_deterministic_algorithms(True, warn_only=True)
    torch.backends.cudnn.benchmark = False


def _distributed() -> tuple[int, int]:
    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


@torch.no_grad()
def predict(
    model: nn.Module,
    dataset: Dataset,
    batch_size: int = 128,
    device: str | torch.device = "cpu",
    channels_last: bool = True,
    indices: Sequence[int] | None = None,
) -> np.ndarray:
    """Eval-mode outputs (N, 9) for a PoseDataset (or the subset `indices`), in dataset order."""
    was_training = model.training
    model.eval()
    subset = dataset if indices is None else torch.utils.data.Subset(dataset, list(indices))
    pin = torch.device(device).type == "cuda"
    out = [
        model(to_input(x.to(device, non_blocking=pin), channels_last)).float().cpu()  # uint8 over the bus
        for x, _ in DataLoader(subset, batch_size=batch_size, shuffle=False, pin_memory=pin)
    ]
    model.train(was_training)
    return torch.cat(out).numpy() if out else np.zeros((0, 9), np.float32)


def predict_distributed(
    model: nn.Module, dataset: PoseDataset, batch_size: int, device: torch.device, channels_last: bool
) -> np.ndarray:
    """`predict` sharded over the ranks (rank r takes items r, r + world, ...), gathered on all ranks."""
    rank, world = _distributed()
    if world == 1:
        return predict(model, dataset, batch_size, device, channels_last)
    mine = predict(model, dataset, batch_size, device, channels_last, indices=range(rank, len(dataset), world))
    shards: list[Any] = [None] * world
    dist.all_gather_object(shards, mine)
    out = np.zeros((len(dataset), 9), np.float32)
    for r, shard in enumerate(shards):
        out[r::world] = shard
    return out


@dataclass(frozen=True)
class TrainConfig:
    """Optimiser and schedule. LR (`schedule`, pipeline/pose/optim.py): "cyclic" = CyclicLR "triangular2"
    between lr_base and lr_max with a half cycle of `cycle_epochs` epochs (the peak halves every cycle);
    "cosine" = linear warm-up from lr_base to lr_max over `warmup_epochs`, then a half cosine down to
    `lr_min` at the last step. `ema`: decay per step of the weights' moving average (0 = none);
    `max_minutes` stops training before an epoch that would end past the limit (None = no limit)."""

    epochs: int
    batch_size: int = 32
    lr_base: float = 1e-4
    lr_max: float = 1e-3
    cycle_epochs: float = 3.0
    schedule: str = "cyclic"
    lr_min: float = 1e-6
    warmup_epochs: float = 1.0
    ema: float = 0.0
    weight_decay: float = 0.0
    max_minutes: float | None = None
    channels_last: bool = True
    workers: int = 0
    seed: int = 0

    def __post_init__(self) -> None:
        if self.epochs < 1 or self.batch_size < 1:
            raise ValueError(f"epochs and batch_size must be >= 1, got {self.epochs}, {self.batch_size}")
        if not 0 < self.lr_base <= self.lr_max:
            raise ValueError(f"need 0 < lr_base <= lr_max, got {self.lr_base}, {self.lr_max}")
        if self.cycle_epochs <= 0 or self.warmup_epochs < 0:
            raise ValueError(
                f"need cycle_epochs > 0 and warmup_epochs >= 0, got {self.cycle_epochs}, {self.warmup_epochs}"
            )
        if self.schedule not in SCHEDULES:
            raise ValueError(f"schedule must be one of {', '.join(SCHEDULES)}, got {self.schedule!r}")
        if not 0 < self.lr_min <= self.lr_base:
            raise ValueError(f"need 0 < lr_min <= lr_base, got {self.lr_min}, {self.lr_base}")
        if not 0 <= self.ema < 1:
            raise ValueError(f"ema (decay per step) must be in [0, 1), got {self.ema}")


@dataclass
class EpochStats:
    """One epoch: training loss and running errors (train mode, augmented), validation errors (eval mode)."""

    epoch: int
    loss: float
    lr: float
    s_p: float
    s_r: float
    train_pos_m: float
    train_att_deg: float
    val_pos_m: float
    val_att_deg: float
    val_score: float
    images_per_s: float
    seconds: float
    val_adv_pos_m: float = math.nan  # with an adversary: validation subset under its PGD check
    val_adv_att_deg: float = math.nan
    score: float = math.nan  # what selects the checkpoint (val_score, + attacked position with an adversary)

    def as_dict(self) -> dict[str, float]:
        return dict(self.__dict__)


@dataclass
class FitResult:
    history: list[EpochStats]
    best_epoch: int
    best_score: float
    best_state: dict[str, torch.Tensor]
    seconds: float
    stopped_early: bool = False
    train_images_per_s: float = field(default=0.0)


class _Objective(nn.Module):
    """Model + loss in one module, so DDP also all-reduces the loss's learnable weights."""

    def __init__(self, model: nn.Module, loss: PoseLoss):
        super().__init__()
        self.model, self.loss = model, loss

    def forward(
        self, x: torch.Tensor, y: torch.Tensor, skip_rotation: int = 0, pairs: int = 0, beta: float = 0.0
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(loss, predictions of the len(y) fitted images): with `pairs` > 0 the last `pairs` inputs are attacked
        copies of the first ones and add beta x their consistency with them (Adversary.batch; one dropout mask
        per pair: PoseNet.forward_paired)."""
        if not pairs:
            pred = self.model(x)
            return self.loss(pred, y, skip_rotation), pred
        pred = self.model.forward_paired(x, pairs)
        clean = pred[: len(y)]
        return self.loss(clean, y, skip_rotation) + beta * self.loss.consistency(pred[len(y) :], clean[:pairs]), clean


def fit(
    model: nn.Module,
    loss: PoseLoss,
    train_set: PoseDataset,
    val_set: PoseDataset,
    cfg: TrainConfig,
    device: str | torch.device = "cpu",
    on_epoch: Callable[[EpochStats, bool, nn.Module], None] | None = None,
    progress: bool = True,
    adversary: Adversary | None = None,
) -> FitResult:
    """Train `model` in place; return the history and the best state (by the validation score).

    `on_epoch(stats, is_best, evaluated)` runs on every rank after each epoch (write files on rank 0 only);
    `evaluated` is the network validated (the EMA copy when `cfg.ema` > 0). `adversary`: train on its
    PGD-k examples and select on clean + attacked validation error.
    """
    device = torch.device(device)
    rank, world = _distributed()
    torch.manual_seed(cfg.seed)
    objective = _placed_objective(model, loss, cfg, device, world)
    loader, sampler = _loader(train_set, cfg, device, rank, world)
    opt, sched = _optimiser(model, loss, cfg, len(loader))
    ema = WeightEMA(model, cfg.ema) if cfg.ema > 0 else None
    evaluated = model if ema is None else ema.model
    history: list[EpochStats] = []
    best_score, best_epoch, best_state = math.inf, -1, copy.deepcopy(evaluated.state_dict())
    start, stopped_early, train_seconds, train_images = time.perf_counter(), False, 0.0, 0
    for epoch in range(cfg.epochs):
        if _out_of_time(cfg, history, start, device):
            stopped_early = True
            break
        t0 = time.perf_counter()
        if sampler is not None:
            sampler.set_epoch(epoch)
        train_set.set_epoch(epoch)
        step = _Step(objective, model, opt, sched, ema, adversary, epoch * len(loader))
        sums = _train_epoch(step, loader, cfg, device, epoch, world, progress and rank == 0, t0)
        epoch_train_seconds = time.perf_counter() - t0
        if world > 1:
            dist.all_reduce(sums)
        stats = _epoch_stats(
            evaluated, loss, val_set, cfg, device, epoch, sums, sched, epoch_train_seconds, t0, adversary
        )
        train_seconds += epoch_train_seconds
        train_images += int(sums[3].item())
        history.append(stats)
        is_best = stats.score < best_score
        if is_best:
            best_score, best_epoch = stats.score, epoch + 1
            best_state = {k: v.detach().cpu().clone() for k, v in evaluated.state_dict().items()}
        if on_epoch is not None:
            on_epoch(stats, is_best, evaluated)
    check_improved(best_epoch, len(history))
    rate = train_images / train_seconds if train_seconds else 0.0
    return FitResult(history, best_epoch, best_score, best_state, time.perf_counter() - start, stopped_early, rate)


def _placed_objective(
    model: nn.Module, loss: PoseLoss, cfg: TrainConfig, device: torch.device, world: int
) -> nn.Module:
    """The model (channels-last when `cfg.channels_last`) and the loss moved to `device`, as one objective module,
    wrapped in DistributedDataParallel when `world` > 1 ranks train."""
    model.to(device)
    loss.to(device)
    if cfg.channels_last:
        model.to(memory_format=torch.channels_last)
    objective: nn.Module = _Objective(model, loss)
    if world > 1:
        objective = nn.parallel.DistributedDataParallel(
            objective, device_ids=[device.index] if device.type == "cuda" else None
        )
    return objective


def _out_of_time(cfg: TrainConfig, history: list[EpochStats], start: float, device: torch.device) -> bool:
    """Whether `cfg.max_minutes` is set and another epoch as long as the last (none run: never) would end past it,
    `start` the fit's perf_counter start (s)."""
    return bool(
        cfg.max_minutes is not None and history and _should_stop(start, history[-1].seconds, cfg.max_minutes, device)
    )


def _loader(
    train_set: PoseDataset, cfg: TrainConfig, device: torch.device, rank: int, world: int
) -> tuple[DataLoader, DistributedSampler | None]:
    """The shuffled training batches (sharded over ranks under DDP) and their sampler (None alone)."""
    sampler = (
        DistributedSampler(train_set, world, rank, shuffle=True, seed=cfg.seed, drop_last=True) if world > 1 else None
    )
    gen = torch.Generator().manual_seed(cfg.seed)
    loader = DataLoader(
        train_set,
        batch_size=cfg.batch_size,
        shuffle=sampler is None,
        sampler=sampler,
        drop_last=True,
        num_workers=cfg.workers,
        generator=gen,
        pin_memory=device.type == "cuda",
        persistent_workers=False,
    )
    if len(loader) == 0:
        raise ValueError(
            f"the training set ({len(train_set)} images over {world} process(es)) is smaller than "
            f"one batch of {cfg.batch_size}"
        )
    return loader, sampler


def _optimiser(
    model: nn.Module, loss: PoseLoss, cfg: TrainConfig, steps: int
) -> tuple[torch.optim.Adam, torch.optim.lr_scheduler.LRScheduler]:
    """Adam on the model and the loss's weights, with the LR schedule of `cfg` (`steps` batches per epoch)."""
    # The loss's two weights get LOSS_WEIGHT_LR_FACTOR x the learning rate (no weight decay) so they reach
    # their balance (exp(-2 s) ~ 1 / error) within the first epochs instead of lagging the whole run.
    opt = torch.optim.Adam(
        [
            {"params": list(model.parameters()), "weight_decay": cfg.weight_decay, "lr": cfg.lr_base},
            {"params": list(loss.parameters()), "weight_decay": 0.0, "lr": LOSS_WEIGHT_LR_FACTOR * cfg.lr_base},
        ],
        lr=cfg.lr_base,
    )
    sched = make_scheduler(
        opt,
        cfg.schedule,
        cfg.epochs * steps,
        lr_base=cfg.lr_base,
        lr_max=cfg.lr_max,
        lr_min=cfg.lr_min,
        cycle=round(cfg.cycle_epochs * steps),
        warmup=round(cfg.warmup_epochs * steps),
    )
    return opt, sched


@dataclass
class _Step:
    """What one optimiser step needs: the objective (DDP-wrapped or not), the plain model (what the
    adversary attacks and the EMA averages), optimiser, schedule, EMA, adversary, and the global step."""

    objective: nn.Module
    model: nn.Module
    opt: torch.optim.Optimizer
    sched: Any
    ema: WeightEMA | None
    adversary: Adversary | None
    step: int

    def __call__(self, x: torch.Tensor, y: torch.Tensor, where: str) -> tuple[float, torch.Tensor]:
        """One step on the batch (x, y) (its PGD-k examples with an adversary) -> (loss, predictions)."""
        skip = pairs = 0
        if self.adversary is not None:
            x, skip, pairs = self.adversary.batch(self.model, x, y, self.step)
        value, pred = self.objective(x, y, skip, pairs, self.adversary.cfg.trades if pairs else 0.0)
        check_loss(value.item(), where)
        self.opt.zero_grad(set_to_none=True)
        value.backward()
        self.opt.step()
        self.sched.step()
        if self.ema is not None:
            self.ema.update(self.model)
        self.step += 1
        return value.item(), pred.detach()


def _train_epoch(
    step: _Step,
    loader: DataLoader,
    cfg: TrainConfig,
    device: torch.device,
    epoch: int,
    world: int,
    show: bool,
    t0: float,
) -> torch.Tensor:
    """One pass over this rank's batches -> float64 sums (loss * n, position error (m), attitude error
    (deg), n) of the rank; `show` draws a tqdm bar (images per second since `t0`)."""
    step.objective.train()
    sums = torch.zeros(4, dtype=torch.float64)  # loss * n, position error, attitude error, n
    bar = tqdm(
        loader, desc=f"epoch {epoch + 1}/{cfg.epochs}", unit="batch", disable=not show, leave=False, dynamic_ncols=True
    )
    for x, y in bar:
        # the pinned uint8 batch crosses to the device, then becomes float there
        x, y = to_input(x.to(device, non_blocking=True), cfg.channels_last), y.to(device, non_blocking=True)
        value, pred = step(x, y, f"epoch {epoch + 1}")
        n = len(y)
        pos, att = pose_errors(pred.cpu().numpy(), y.cpu().numpy())
        sums += torch.tensor([value * n, pos.sum(), att.sum(), n], dtype=torch.float64)
        seen = sums[3].item() * world
        bar.set_postfix(loss=f"{sums[0].item() / sums[3].item():.3f}", img_s=f"{seen / (time.perf_counter() - t0):.0f}")
    bar.close()
    return sums


def _epoch_stats(
    model: nn.Module,
    loss: PoseLoss,
    val_set: PoseDataset,
    cfg: TrainConfig,
    device: torch.device,
    epoch: int,
    sums: torch.Tensor,
    sched: Any,
    train_seconds: float,
    t0: float,
    adversary: Adversary | None,
) -> EpochStats:
    """The epoch's record: training sums (all ranks), the validation errors and SPEED score of `model`
    (the network validated), and with an adversary its attacked validation errors."""
    val_pred = predict_distributed(model, val_set, 2 * cfg.batch_size, device, cfg.channels_last)
    targets = val_set.targets.numpy()
    pos, att = pose_errors(val_pred, targets)
    score = speed_score(val_pred, targets)
    adv_pos = adv_att = math.nan
    selection = score
    if adversary is not None:
        adv_pred, adv_targets = adversary.validate(model, val_set, device)
        adv_pos_errors, adv_att_errors = pose_errors(adv_pred, adv_targets)
        adv_pos, adv_att = float(adv_pos_errors.mean()), float(adv_att_errors.mean())
        selection = score + adversary.selection_error(adv_pred, adv_targets)
    n = sums[3].item()
    return EpochStats(
        epoch=epoch + 1,
        loss=sums[0].item() / n,
        lr=float(sched.get_last_lr()[0]),
        s_p=loss.s_p.item(),
        s_r=loss.s_r.item(),
        train_pos_m=sums[1].item() / n,
        train_att_deg=sums[2].item() / n,
        val_pos_m=float(pos.mean()),
        val_att_deg=float(att.mean()),
        val_score=score,
        images_per_s=n / train_seconds,
        seconds=time.perf_counter() - t0,
        val_adv_pos_m=adv_pos,
        val_adv_att_deg=adv_att,
        score=selection,
    )


def _should_stop(start: float, last_epoch_seconds: float, max_minutes: float, device: torch.device) -> bool:
    """True when another epoch as long as the last would end past the limit (rank 0 decides for all)."""
    stop = torch.tensor(
        [float(time.perf_counter() - start + last_epoch_seconds > 60 * max_minutes)],
        device=device if device.type == "cuda" else "cpu",
    )
    if _distributed()[1] > 1:
        dist.broadcast(stop, src=0)
    return bool(stop.item())
