"""The strongest-attack suite for the pose regressor (issue 37): an "AutoAttack" for pose regression.

Members are `method/objective` pairs: methods `apgd` (pipeline/attacks/apgd.py, restarts cycling through the
random and background-lifting starts), `bpda` (APGD with the gradient passed through the black-level clamp as
the identity: plain APGD on a model without a clamp, where it is skipped when the suite has the apgd member
of the same objective), `square` (the gradient-free check, pipeline/attacks/square.py,
at `square_eps` only) and `pgd` (the project's PGD-n baseline: pipeline/attacks/gradient.py, random start,
last iterate, steps of 2.5 eps / n); objectives from pipeline/attacks/objectives.py. Every member's image is
stored as 8 bits before it is scored (pipeline/attacks/stored.py).

Scored per frame, eps and member (all on the stored image): position error (m), range error = |error along
the true line of sight| (m), lateral error = its norm across (m), attitude error (deg), and the shift from
the clean estimate: |along the line of sight| (m), across it (m), attitude change (deg). Nested in eps: an
image within eps_j of x is within eps_i >= eps_j of it, so the worst case at eps_i is the max over every
member at every eps_j <= eps_i (and the clean image): it cannot drop as eps grows. The per-frame capacity
(`frame_capacity`: the largest shift along and across the line of sight and of the attitude, per frame and
eps) is what the integrity bound consumes.
"""

from __future__ import annotations

import contextlib
import dataclasses
import time
import zlib
from dataclasses import dataclass
from typing import Any, Callable, Iterator, Sequence

import numpy as np
import torch
from torch import Tensor, nn

from pipeline.attacks.apgd import apgd
from pipeline.attacks.bpda import black_level
from pipeline.attacks.gradient import _eval_mode, check_eps, pgd
from pipeline.attacks.objectives import OBJECTIVES, along_across, geodesic_deg, get_objective, line_of_sight, position
from pipeline.attacks.square import square
from pipeline.attacks.starts import STARTS
from pipeline.attacks.stored import Found, evaluate
from pipeline.stats import mean_interval

METHODS = ("apgd", "bpda", "square", "pgd")
ERRORS = ("position_m", "range_m", "lateral_m", "attitude_deg")  # against the truth
SHIFTS = ("along_m", "across_m", "attitude_deg")  # against the clean estimate


@dataclass(frozen=True)
class SuiteConfig:
    """members: `method/objective` pairs (module doc); steps, restarts: of apgd, bpda and pgd (each restart
    a fresh start); starts: the start kinds apgd and bpda cycle through over restarts (random | lift);
    queries, p_init: of square; square_eps: the one eps square runs at (None: every eps); seed: every
    random draw; batch_size: frames per attack batch (part of the seeding)."""

    members: tuple[str, ...]
    steps: int = 100
    restarts: int = 5
    starts: tuple[str, ...] = ("random", "lift")
    queries: int = 1000
    p_init: float = 0.8
    square_eps: float | None = None
    seed: int = 0
    batch_size: int = 32

    def __post_init__(self) -> None:
        if not self.members:
            raise ValueError("an attack suite needs at least one member")
        for m in self.members:
            method, _, objective = m.partition("/")
            if method not in METHODS or objective not in OBJECTIVES:
                raise ValueError(
                    f"suite member {m!r} must be method/objective with a method of {', '.join(METHODS)} "
                    f"and an objective of {', '.join(OBJECTIVES)}"
                )
        if min(self.steps, self.restarts, self.queries, self.batch_size) < 1:
            raise ValueError(
                f"suite steps, restarts, queries and batch_size must be >= 1, got {self.steps}, "
                f"{self.restarts}, {self.queries}, {self.batch_size}"
            )
        if not self.starts or any(s not in STARTS for s in self.starts):
            raise ValueError(f"suite starts must be some of {', '.join(STARTS)}, got {self.starts}")
        if self.square_eps is not None:
            check_eps(self.square_eps)

    def doubled(self) -> "SuiteConfig":
        """The same suite with twice the steps, restarts and queries (the stability check)."""
        return dataclasses.replace(self, steps=2 * self.steps, restarts=2 * self.restarts, queries=2 * self.queries)


def _members(methods: Sequence[str], objectives: Sequence[str]) -> tuple[str, ...]:
    return tuple(f"{m}/{o}" for m in methods for o in objectives)


# FULL: every objective with both gradients and Square, for CUDA or its own stage. LEAN: what the default
# profile can afford on 2 CPU cores, chosen on the committed models (benchmarks/attack_suite.py, reports/
# benchmarks.md): past the clamp (eps > 0.07) the robust model's worst cases come from bpda members and need
# more than one objective to find the basin, and range_near finds more position error than range_far. On a
# model without a clamp LEAN is apgd on position, attitude and range_near.
FULL = SuiteConfig(
    members=_members(["apgd", "bpda"], OBJECTIVES) + _members(["square"], ["position", "attitude"]),
    steps=100,
    restarts=5,
    queries=1000,
    square_eps=0.05,
)
LEAN = SuiteConfig(
    members=_members(["apgd"], ["position", "attitude"]) + _members(["bpda"], ["position", "range_near", "attitude"]),
    steps=50,
    restarts=1,
    starts=("lift",),
)
PGD50 = SuiteConfig(members=("pgd/position",), steps=50, restarts=1)  # the attack of the PGD-50 tables


@dataclass(frozen=True)
class SuiteResult:
    """A suite's run over N frames: `errors[k]` (M, E, N) per member, eps and frame (k in ERRORS; NaN where the
    member did not run: square off its eps), `shifts[k]` (M, E, N) likewise (k in SHIFTS), `clean[k]` (N,)
    the clean errors, `target_range_m` (N,) the true range ||t_gt||, `seconds` and `cpu_seconds` (M, E) the wall and
    process CPU time per frame of each member at each eps (scoring included), over the whole run."""

    eps: tuple[float, ...]
    members: tuple[str, ...]
    errors: dict[str, np.ndarray]
    shifts: dict[str, np.ndarray]
    clean: dict[str, np.ndarray]
    target_range_m: np.ndarray
    seconds: np.ndarray
    cpu_seconds: np.ndarray

    @property
    def frames(self) -> int:
        return len(self.target_range_m)

    def select(self, frames: np.ndarray) -> "SuiteResult":
        """The same run restricted to `frames` (indices or a boolean mask over the N frames): e.g. a
        subsample, or the frames of one background."""
        return SuiteResult(
            self.eps,
            self.members,
            {k: v[..., frames] for k, v in self.errors.items()},
            {k: v[..., frames] for k, v in self.shifts.items()},
            {k: v[frames] for k, v in self.clean.items()},
            self.target_range_m[frames],
            self.seconds,
            self.cpu_seconds,
        )

    def worst(self, key: str) -> np.ndarray:
        """(E, N) the suite's nested worst case of error `key` (ERRORS) per eps and frame."""
        return nested_worst(self.errors[key], self.clean[key])

    def worst_shift(self, key: str) -> np.ndarray:
        """(E, N) the suite's nested largest shift `key` (SHIFTS) per eps and frame."""
        return nested_worst(self.shifts[key])


@dataclass(frozen=True)
class Capacity:
    """Per frame (N) and eps (E, increasing): the largest shift of the estimate from the clean estimate that
    the suite reached, along the true line of sight (|.|, m), across it (m) and of the attitude (deg);
    `target_range_m` (N,) the true range of each frame (m)."""

    eps: tuple[float, ...]
    target_range_m: np.ndarray
    along_m: np.ndarray
    across_m: np.ndarray
    attitude_deg: np.ndarray


def nested_worst(values: np.ndarray, floor: np.ndarray | None = None) -> np.ndarray:
    """(M, E, N) values per member, increasing eps and frame -> (E, N): the max over members (NaN = not run)
    and over every eps up to each eps, and over `floor` (N,) when given (the clean image's value)."""
    worst = np.maximum.accumulate(np.where(np.isnan(values), -np.inf, values).max(axis=0), axis=0)
    worst = worst if floor is None else np.maximum(worst, floor[None, :])
    if not np.isfinite(worst).all():
        raise ValueError("a frame has no value at an eps: no member ran there")
    return worst


def _generator(seed: int, eps: float, member: str, first: int) -> torch.Generator:
    """The CPU generator of one member at one eps on the batch starting at frame `first`."""
    state = np.random.SeedSequence([seed, int(round(eps * 1e6)), zlib.crc32(member.encode()), first])
    return torch.Generator().manual_seed(int(state.generate_state(1)[0]))


def _pgd(
    model: nn.Module,
    x: Tensor,
    y: Tensor,
    eps: float,
    objective: Any,
    generator: torch.Generator,
    los: Tensor | None,
    steps: int,
    restarts: int,
) -> Found:
    """PGD-`steps` on the objective's sum, last iterate stored and scored; the best of `restarts` runs."""

    def run() -> Found:
        z = pgd(
            model, x, y, eps, lambda pred, target: objective(pred, target, los).sum(), steps=steps, generator=generator
        )
        u8, value, _ = evaluate(model, z, x, y, objective, los)
        return Found(u8, value)

    found = run()
    for _ in range(1, restarts):
        found = found.best(run())
    return found


def run_member(
    model: nn.Module,
    member: str,
    x: Tensor,
    y: Tensor,
    eps: float,
    config: SuiteConfig,
    generator: torch.Generator,
    los: Tensor | None = None,
) -> Found:
    """One `method/objective` member on clean x (B, 3, H, W, 8-bit grid) with true poses y (B, 9) at eps (model
    in eval mode during the attack, its mode restored)."""
    method, _, name = member.partition("/")
    objective = get_objective(name)
    with _eval_mode(model):
        if method == "square":
            return square(
                model, x, y, eps, objective, generator=generator, los=los, queries=config.queries, p_init=config.p_init
            )
        if method == "pgd":
            return _pgd(model, x, y, eps, objective, generator, los, config.steps, config.restarts)
        return apgd(
            model,
            x,
            y,
            eps,
            objective,
            generator=generator,
            los=los,
            steps=config.steps,
            restarts=config.restarts,
            starts=config.starts,
            bpda=method == "bpda",
        )


def _score(
    pred: Tensor, target: Tensor, clean: Tensor, u: Tensor
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """(errors (ERRORS) against the truth, shifts (SHIFTS) from the clean estimate) of (B, 9) estimates,
    per frame; u (B, 3) the unit lines of sight."""
    along, across = along_across(pred[:, :3] - target[:, :3], u)
    s_along, s_across = along_across(pred[:, :3] - clean[:, :3], u)
    errors = {
        "position_m": position(pred, target),
        "range_m": along.abs(),
        "lateral_m": across,
        "attitude_deg": geodesic_deg(pred[:, 3:], target[:, 3:]),
    }
    shifts = {"along_m": s_along.abs(), "across_m": s_across, "attitude_deg": geodesic_deg(pred[:, 3:], clean[:, 3:])}
    return (
        {k: v.detach().cpu().numpy() for k, v in errors.items()},
        {k: v.detach().cpu().numpy() for k, v in shifts.items()},
    )


def _check_run(
    images: np.ndarray, targets: np.ndarray, eps: Sequence[float], los: np.ndarray | None
) -> tuple[float, ...]:
    if images.dtype != np.uint8 or images.ndim != 4 or images.shape[-1] != 3:
        raise ValueError(f"suite images must be uint8 (N, H, W, 3), got {images.dtype} {images.shape}")
    if targets.shape != (len(images), 9) or not np.isfinite(targets).all():
        raise ValueError(f"suite targets must be finite (N, 9) = ({len(images)}, 9), got {targets.shape}")
    if los is not None and (np.shape(los) != (len(images), 3) or not np.isfinite(los).all()):
        raise ValueError(f"suite lines of sight must be finite (N, 3) = ({len(images)}, 3), got {np.shape(los)}")
    eps = tuple(check_eps(e) for e in eps)
    if not eps or any(b <= a for a, b in zip(eps, eps[1:])):
        raise ValueError(f"suite eps must be a non-empty strictly increasing list (nesting), got {list(eps)}")
    return eps


def run_suite(
    model: nn.Module,
    images: np.ndarray,
    targets: np.ndarray,
    eps: Sequence[float],
    config: SuiteConfig,
    *,
    device: str | torch.device = "cpu",
    los: np.ndarray | None = None,
    part: Callable[[float, Callable[[], SuiteResult]], SuiteResult] | None = None,
    progress: str | None = None,
) -> SuiteResult:
    """The suite `config` on clean uint8 images (N, H, W, 3) with true poses `targets` (N, 9: camera-frame
    position in m, 6-D rotation) at every eps of the increasing list `eps` (L-inf, pixel units); `los` (N, 3)
    camera-frame lines of sight (default: the true target directions). Attacks run on `device` (the draws on
    the CPU; on CUDA under the network's own precision, bf16 with its `amp`); every score (clean and attacked)
    in exact float32 (`exact_math`). Model in eval mode (its mode restored). On a model without a clamp a `bpda`
    member is skipped when the suite has the `apgd` member of its objective; `square` members run at
    `config.square_eps` only (a ValueError when it is not in `eps`).

    The run is one run per eps, in increasing eps (each member's draws depend on its eps and batch only, so the
    result is the same as one pass): `part(e, compute)` returns the run at eps e, by default `compute()`; a
    caller may return a stored run of that eps instead (a cache: same model, frames, config and eps, one eps;
    the clean errors are the first eps's). `progress`: a tqdm bar with that description over the frames x eps."""
    images, targets = np.asarray(images), np.asarray(targets, np.float64)
    eps = _check_run(images, targets, eps, los)
    _check_square(config, eps)
    members = _members_run(model, config)
    bar = _bar(progress, len(eps) * len(images))
    try:

        def compute(e: float) -> SuiteResult:
            return _run_eps(model, images, targets, e, members, config, device, los, bar)

        parts = []
        for e in eps:
            found = compute(e) if part is None else part(e, lambda e=e: compute(e))
            if found.eps != (e,) or found.members != members or found.frames != len(images):
                raise ValueError(f"the suite's run at eps {e:g} does not match the suite (eps, members or frames)")
            parts.append(found)
            if bar is not None:
                bar.n = len(parts) * len(images)
                bar.refresh()
    finally:
        if bar is not None:
            bar.close()
    return join_eps(parts)


def join_eps(parts: Sequence[SuiteResult]) -> SuiteResult:
    """One run over the eps of `parts` (runs of the same members on the same frames, each at its own eps, in
    increasing eps); the clean errors and ranges are the first part's."""
    first = parts[0]
    return SuiteResult(
        tuple(e for p in parts for e in p.eps),
        first.members,
        {k: np.concatenate([p.errors[k] for p in parts], axis=1) for k in ERRORS},
        {k: np.concatenate([p.shifts[k] for p in parts], axis=1) for k in SHIFTS},
        first.clean,
        first.target_range_m,
        np.concatenate([p.seconds for p in parts], axis=1),
        np.concatenate([p.cpu_seconds for p in parts], axis=1),
    )


def _run_eps(
    model: nn.Module,
    images: np.ndarray,
    targets: np.ndarray,
    e: float,
    members: tuple[str, ...],
    config: SuiteConfig,
    device: str | torch.device,
    los: np.ndarray | None,
    bar: Any,
) -> SuiteResult:
    """The suite's `members` at one eps over every frame, batch by batch (`run_suite`)."""
    n, shape = len(images), (len(members), 1, len(images))
    errors = {k: np.full(shape, np.nan) for k in ERRORS}
    shifts = {k: np.full(shape, np.nan) for k in SHIFTS}
    clean = {k: np.zeros(n) for k in ERRORS}
    seconds, cpu_seconds = np.zeros(shape[:2]), np.zeros(shape[:2])
    with _eval_mode(model):
        for lo in range(0, n, config.batch_size):
            hi = min(lo + config.batch_size, n)
            x = torch.from_numpy(images[lo:hi]).permute(0, 3, 1, 2).to(device).float() / 255.0
            y = torch.from_numpy(targets[lo:hi]).float().to(device)
            los_b = None if los is None else torch.from_numpy(np.asarray(los[lo:hi], np.float32)).to(device)
            u = line_of_sight(y.double(), None if los_b is None else los_b.double())
            with torch.no_grad(), exact_math(model):
                p0 = model(x).double()
            for k, v in _score(p0, y.double(), p0, u)[0].items():
                clean[k][lo:hi] = v
            for mi, member in enumerate(members):
                if _off_square_eps(member, e, config):
                    continue
                t0, c0 = time.perf_counter(), time.process_time()
                found = run_member(model, member, x, y, e, config, _generator(config.seed, e, member, lo), los_b)
                with torch.no_grad(), exact_math(model):
                    err, shift = _score(model(found.images.float() / 255.0).double(), y.double(), p0, u)
                seconds[mi, 0] += (time.perf_counter() - t0) / n
                cpu_seconds[mi, 0] += (time.process_time() - c0) / n
                for k in ERRORS:
                    errors[k][mi, 0, lo:hi] = err[k]
                for k in SHIFTS:
                    shifts[k][mi, 0, lo:hi] = shift[k]
            if bar is not None:
                bar.update(hi - lo)
    return SuiteResult(
        (e,), members, errors, shifts, clean, np.linalg.norm(targets[:, :3], axis=1), seconds, cpu_seconds
    )


@contextlib.contextmanager
def exact_math(model: nn.Module) -> Iterator[None]:
    """Float32 without shortcuts inside: the network's bf16 autocast off (its `amp` attribute, when it has one)
    and TF32 off for CUDA convolutions and matrix products (no effect on the CPU); all restored after."""
    amp = getattr(model, "amp", None)
    flags = torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32
    if amp is not None:
        model.amp = False
    torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = False
    try:
        yield
    finally:
        torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = flags
        if amp is not None:
            model.amp = amp


def _bar(desc: str | None, total: int) -> Any:
    """A tqdm bar of `total` frames described `desc` (None: no bar)."""
    if desc is None:
        return None
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="frame", dynamic_ncols=True)


def _check_square(config: SuiteConfig, eps: Sequence[float]) -> None:
    """A ValueError when the suite has `square` members and its `square_eps` is not one of `eps`."""
    if (
        config.square_eps is not None
        and any(m.startswith("square/") for m in config.members)
        and not any(np.isclose(config.square_eps, e) for e in eps)
    ):
        raise ValueError(f"square_eps {config.square_eps} is not one of the suite's eps {list(eps)}")


def _members_run(model: nn.Module, config: SuiteConfig) -> tuple[str, ...]:
    """The suite's members, less a `bpda` member beside the `apgd` member of its objective on a model without a
    clamp (the same attack)."""
    return tuple(
        m
        for m in config.members
        if not (m.startswith("bpda/") and black_level(model) <= 0 and "apgd/" + m.partition("/")[2] in config.members)
    )


def _off_square_eps(member: str, e: float, config: SuiteConfig) -> bool:
    """Whether `member` is a `square` member, which runs at `config.square_eps` only, and eps `e` is not it."""
    return bool(member.startswith("square/") and config.square_eps is not None and not np.isclose(config.square_eps, e))


def frame_capacity(result: SuiteResult) -> Capacity:
    """The per-frame attacker capacity of a suite run (nested in eps; `Capacity`)."""
    return Capacity(
        result.eps,
        result.target_range_m,
        result.worst_shift("along_m"),
        result.worst_shift("across_m"),
        result.worst_shift("attitude_deg"),
    )


def _stats(values: np.ndarray) -> dict[str, Any]:
    """{mean, ci} of per-frame errors (non-negative), the 95% interval of pipeline.stats.mean_interval (floor 0)."""
    mean, lo, hi = mean_interval(values, floor=0.0)
    return {"mean": mean, "ci": [lo, hi]}


def _row(attack: str, eps: float, columns: dict[str, np.ndarray], seconds: tuple[float, float]) -> dict[str, Any]:
    """A table row in the keys of pipeline.pose.robustness.attack_table (pos_m, pos_ci, att_deg, att_ci) plus
    range and lateral errors and the (wall, CPU) seconds per frame."""
    row: dict[str, Any] = {"attack": attack, "eps": float(eps), "n": int(len(columns["position_m"]))}
    for key, short in (
        ("position_m", "pos_m"),
        ("attitude_deg", "att_deg"),
        ("range_m", "range_m"),
        ("lateral_m", "lateral_m"),
    ):
        s = _stats(columns[key])
        row[short], row[short.rsplit("_", 1)[0] + "_ci"] = s["mean"], s["ci"]
    return {**row, "seconds_per_frame": seconds[0], "cpu_seconds_per_frame": seconds[1]}


def suite_rows(result: SuiteResult) -> list[dict[str, Any]]:
    """Table rows: the clean images (attack `clean`, eps 0), then per eps each member that ran (attack = its
    name, its own errors) and the suite's nested worst case (attack `suite`); errors as means over frames
    with 95% intervals: pos_m/pos_ci, att_deg/att_ci, range_m/range_ci, lateral_m/lateral_ci; the wall and CPU
    seconds per frame of the member (of every member at that eps for `suite`)."""
    rows = [_row("clean", 0.0, result.clean, (0.0, 0.0))]
    for ei, e in enumerate(result.eps):
        for mi, member in enumerate(result.members):
            if not np.isnan(result.errors["position_m"][mi, ei]).any():
                rows.append(
                    _row(
                        member,
                        e,
                        {k: result.errors[k][mi, ei] for k in ERRORS},
                        (result.seconds[mi, ei], result.cpu_seconds[mi, ei]),
                    )
                )
        rows.append(
            _row(
                "suite",
                e,
                {k: result.worst(k)[ei] for k in ERRORS},
                (result.seconds[:, ei].sum(), result.cpu_seconds[:, ei].sum()),
            )
        )
    return rows


def sanity_rows(result: SuiteResult) -> list[dict[str, Any]]:
    """Per eps and error (position_m, attitude_deg): the suite's mean worst case, the strongest member's mean
    and name, and `ok`: the worst case is >= every member's on every frame and does not drop as eps grows."""
    rows = []
    for key in ("position_m", "attitude_deg"):
        worst = result.worst(key)
        monotone = bool((np.diff(worst, axis=0) >= 0).all())
        for ei, e in enumerate(result.eps):
            ran = ~np.isnan(result.errors[key][:, ei, 0])
            means = np.where(ran, result.errors[key][:, ei].mean(axis=1), -np.inf)
            top = int(np.argmax(means))
            above = bool(np.all(result.errors[key][ran, ei] <= worst[ei][None, :]))
            rows.append(
                {
                    "eps": e,
                    "error": key,
                    "suite": float(worst[ei].mean()),
                    "strongest": result.members[top],
                    "strongest_mean": float(means[top]),
                    "ok": above and monotone,
                }
            )
    return rows


def ratio_rows(result: SuiteResult, reference: SuiteResult, tolerance: float = 0.05) -> list[dict[str, Any]]:
    """Per eps and error (position_m, attitude_deg): the mean worst case of `result` over that of `reference`
    (the same frames and eps: e.g. the suite run with doubled steps and restarts over the suite, or the lean
    suite over the full one) and `ok` = the ratio within 1 +- tolerance."""
    if result.eps != reference.eps or not np.array_equal(result.target_range_m, reference.target_range_m):
        raise ValueError("ratio rows need two runs over the same frames and eps")
    rows = []
    for key in ("position_m", "attitude_deg"):
        a, b = result.worst(key).mean(axis=1), reference.worst(key).mean(axis=1)
        for e, va, vb in zip(result.eps, a, b):
            rows.append(
                {
                    "eps": e,
                    "error": key,
                    "result": float(va),
                    "reference": float(vb),
                    "ratio": float(va / vb),
                    "ok": bool(abs(va / vb - 1) < tolerance),
                }
            )
    return rows
