"""The strongest-attack suite (issue 37) on tiny stand-in pose regressors: objectives, APGD, the lifting start,
BPDA, Square, 8-bit storage, nesting in eps, rows and capacity."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from torch import nn

from pipeline.attacks.apgd import apgd, checkpoints
from pipeline.attacks.bpda import bpda_forward
from pipeline.attacks.objectives import OBJECTIVES, attitude, lateral, position, range_far, range_near
from pipeline.attacks.square import square, window_share
from pipeline.attacks.starts import lift_level, lifting_start
from pipeline.attacks.stored import levels
from pipeline.attacks.strongest import (
    PGD50,
    SuiteConfig,
    SuiteResult,
    exact_math,
    frame_capacity,
    join_eps,
    nested_worst,
    ratio_rows,
    run_member,
    run_suite,
    sanity_rows,
    suite_rows,
)
from pipeline.formats.suite import part_key, read_suite_part, write_suite_part
from pipeline.geometry.rotations import matrix_to_6d, quat_to_6d, rotvec_to_matrix
from pipeline.io.errors import DataError
from pipeline.pose.metrics import pose_errors


class ToyPose(nn.Module):
    """A small conv regressor to 9 outputs (position near (0, 0, 30) m, 6-D rotation near identity), with an
    optional black-level clamp max(x - t, 0) in front, read at every call as PoseNet does."""

    def __init__(self, black_level: float = 0.0, seed: int = 0) -> None:
        super().__init__()
        torch.manual_seed(seed)
        self.black_level = black_level
        self.net = nn.Sequential(
            nn.Conv2d(3, 8, 3, padding=1),
            nn.BatchNorm2d(8),
            nn.ReLU(),
            nn.Conv2d(8, 8, 3, stride=2, padding=1),
            nn.ReLU(),
            nn.Conv2d(8, 8, 3, padding=1),
            nn.ReLU(),
            nn.AdaptiveAvgPool2d(2),
            nn.Flatten(),
            nn.Linear(32, 9),
        )
        with torch.no_grad():
            self.net[-1].weight.mul_(100.0)
            self.net[-1].bias.copy_(torch.tensor([0.0, 0.0, 30.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0]))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(torch.relu(x - self.black_level) if self.black_level > 0 else x)


pytestmark = pytest.mark.usefixtures("one_thread")  # tests/conftest.py


def frames(n: int = 6, seed: int = 0, black: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """uint8 (n, 12, 16, 3) images (a bright target on a black background, or noise with pixels at 0 and 255)
    and (n, 9) true poses about 30 m ahead."""
    rng = np.random.default_rng(seed)
    if black:
        images = np.zeros((n, 12, 16, 3), np.uint8)
        images[:, 4:8, 6:10] = rng.integers(60, 255, (n, 4, 4, 3))
    else:
        images = rng.integers(0, 256, (n, 12, 16, 3)).astype(np.uint8)
        images[:, :2] = 0
        images[:, -2:] = 255
    q = rng.normal(size=(n, 4)) * [1, 0.1, 0.1, 0.1]
    t = np.c_[rng.normal(0, 2, (n, 2)), rng.uniform(20, 40, n)]
    return images, np.c_[t, quat_to_6d(q / np.linalg.norm(q, axis=1, keepdims=True))]


def as_tensors(images: np.ndarray, targets: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    return torch.from_numpy(images).permute(0, 3, 1, 2).float() / 255, torch.tensor(targets, dtype=torch.float32)


# --- objectives ----------------------------------------------------------------------------------------------


def _pose_pairs(angles: list[float], seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """(pred, target) float64 (B, 9): random true rotations, predictions turned by `angles` (rad) about random
    axes, their 6-D columns scaled and skewed (Gram-Schmidt must undo it), random positions."""
    rng = np.random.default_rng(seed)
    r_gt = np.stack([rotvec_to_matrix(rng.normal(size=3)) for _ in angles])
    axes = rng.normal(size=(len(angles), 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    r_pred = r_gt @ np.stack([rotvec_to_matrix(a * ax) for a, ax in zip(angles, axes)])
    six = matrix_to_6d(r_pred)
    six[:, :3] *= 1.7
    six[:, 3:] = 0.6 * six[:, 3:] + 0.2 * six[:, :3]
    pred = np.c_[rng.normal(0, 1, (len(angles), 2)), rng.uniform(10, 60, len(angles)), six]
    target = np.c_[rng.normal(0, 1, (len(angles), 2)), rng.uniform(10, 60, len(angles)), matrix_to_6d(r_gt)]
    return torch.tensor(pred, requires_grad=True), torch.tensor(target)


def test_attitude_objective_value_and_gradient_against_finite_differences():
    angles = [0.3, 1.0, 2.0, 3.0, 1e-3, math.pi - 1e-3]
    pred, target = _pose_pairs(angles)
    value = attitude(pred, target)
    assert np.allclose(value.detach().numpy(), np.rad2deg(angles), atol=1e-7)
    assert np.allclose(value.detach().numpy(), pose_errors(pred.detach().numpy(), target.numpy())[1], atol=1e-5)
    assert torch.autograd.gradcheck(lambda p: attitude(p, target), (pred,), eps=1e-7, atol=1e-5, rtol=1e-4)
    # central differences by hand on one sample near pi (the direction that changes the angle most)
    (g,) = torch.autograd.grad(attitude(pred, target)[-1], pred)
    d = g[-1] / g[-1].norm()
    h = 1e-6
    fd = (attitude(pred + h * d, target)[-1] - attitude(pred - h * d, target)[-1]) / (2 * h)
    assert abs(float(fd.detach()) - float(g[-1].norm())) < 1e-4 * float(g[-1].norm())


@pytest.mark.parametrize("angle", [0.0, math.pi])
def test_attitude_objective_is_finite_at_0_and_pi(angle):
    pred, target = _pose_pairs([angle])
    if angle == 0.0:  # exactly the same rotation, not a Gram-Schmidt round trip of it: gradient exactly 0
        pred = torch.cat([pred[:, :3], target[:, 3:]], 1).detach().requires_grad_(True)
    value = attitude(pred, target)
    (g,) = torch.autograd.grad(value.sum(), pred)
    assert abs(float(value.detach()) - math.degrees(angle)) < 1e-5
    assert torch.isfinite(g).all()
    if angle == 0.0:
        assert float(g.abs().max()) < 1e-12
    else:  # the cone's slope beside pi, as at pi - 1e-3
        near, target = _pose_pairs([math.pi - 1e-3])
        (g_near,) = torch.autograd.grad(attitude(near, target).sum(), near)
        assert float(g.norm()) < 2 * float(g_near.norm())


def test_position_objectives_split_along_and_across_the_line_of_sight():
    pred, target = _pose_pairs([0.1] * 5, seed=3)
    pos, far, near, lat = (f(pred, target) for f in (position, range_far, range_near, lateral))
    assert torch.allclose(pos**2, far**2 + lat**2)
    assert torch.equal(far, -near)
    u = target[:, :3] / target[:, :3].norm(dim=1, keepdim=True)
    assert torch.allclose(far, ((pred[:, :3] - target[:, :3]) * u).sum(1))
    z_axis = torch.tensor([[0.0, 0.0, 2.0]]).repeat(5, 1)
    assert torch.allclose(range_far(pred, target, z_axis), pred[:, 2] - target[:, 2])
    assert torch.allclose(lateral(pred, target, z_axis), (pred[:, :2] - target[:, :2]).norm(dim=1))
    with pytest.raises(ValueError, match=r"\(B, 9\)"):
        position(pred[:, :8], target[:, :8])
    with pytest.raises(ValueError, match="line of sight"):
        range_far(pred, target, z_axis[:3])


# --- 8-bit storage and the attacks' contract -----------------------------------------------------------------


@pytest.mark.parametrize(
    "member", ["apgd/position", "apgd/attitude", "bpda/range_near", "square/lateral", "pgd/range_far"]
)
@pytest.mark.parametrize("eps", [0.01, 0.1])
def test_every_stored_image_is_within_eps_in_grey_levels_and_scored_as_stored(member, eps):
    images, targets = frames()
    x, y = as_tensors(images, targets)
    model = ToyPose(black_level=0.07)
    model.train()
    cfg = SuiteConfig(members=(member,), steps=8, restarts=2, queries=20)
    found = run_member(model, member, x, y, eps, cfg, torch.Generator().manual_seed(0))
    assert model.training, "the attack must restore the model's mode"
    assert found.images.dtype == torch.uint8 and found.images.shape == x.shape
    clean = torch.from_numpy(images).permute(0, 3, 1, 2).int()
    moved = (found.images.int() - clean).abs()
    assert int(moved.max()) <= levels(eps) and int(moved.max()) >= 1
    model.eval()
    with torch.no_grad():
        rescored = OBJECTIVES[member.split("/")[1]](model(found.images.float() / 255), y)
    assert torch.allclose(found.values, rescored, atol=1e-5)


def test_levels_round_to_the_nearest_grey_level():
    assert [levels(e) for e in (0.001, 0.01, 0.05, 0.1, 0.2, 1.0)] == [1, 3, 13, 26, 51, 255]


@pytest.mark.parametrize(
    "bad",
    [
        dict(eps=0.0),
        dict(eps=1.5),
        dict(x=torch.full((2, 3, 4, 4), 0.5001)),
        dict(x=torch.full((2, 3, 4, 4), float("nan"))),
        dict(x=torch.zeros(2, 4, 4)),
        dict(y=torch.zeros(2, 6)),
        dict(y=torch.full((2, 9), float("nan"))),
    ],
)
def test_attacks_refuse_bad_inputs_in_one_line(bad):
    args = {"x": torch.zeros(2, 3, 4, 4), "y": torch.ones(2, 9), "eps": 0.05, **bad}
    for attack in (apgd, square):
        with pytest.raises(ValueError) as err:
            attack(ToyPose(), args["x"], args["y"], args["eps"], position)
        assert "\n" not in str(err.value)


def test_apgd_checkpoints_follow_the_published_schedule():
    # p_j = 0, 0.22, 0.41, 0.57, 0.70, 0.80, 0.87, 0.93, 0.99 of 100 iterations (0-based steps below)
    assert checkpoints(100) == [21, 40, 56, 69, 79, 86, 92, 98]
    assert checkpoints(5) == [0, 1, 2, 3, 4]


def test_square_window_share_halves_on_the_rescaled_schedule():
    assert window_share(0.8, 0, 1000) == 0.8
    assert window_share(0.8, 2, 1000) == 0.4  # query 20 of 10,000 after rescaling
    assert window_share(0.8, 999, 1000) == 0.8 / 2**9


# --- the clamp: lifting start and BPDA -------------------------------------------------------------------------


def test_lifting_start_puts_dark_pixels_just_above_the_clamp_within_eps():
    images, _ = frames(black=True)
    x = torch.from_numpy(images).permute(0, 3, 1, 2).float() / 255
    start = lifting_start(x, 0.1, 0.07, torch.Generator().manual_seed(0))
    assert lift_level(0.07) == 18 / 255
    dark = x < 0.07
    assert torch.all(start[dark] == 18 / 255) and torch.all((start - x).abs() <= 0.1 + 1e-7)
    low = lifting_start(x, 0.03, 0.07, torch.Generator().manual_seed(0))
    assert torch.allclose(low[dark], x[dark] + 0.03)  # out of reach: lifted by eps


def test_bpda_forward_is_the_model_and_its_gradient_passes_the_clamp():
    images, targets = frames(black=True)
    x, y = as_tensors(images, targets)
    model = ToyPose(black_level=0.07).eval()
    with bpda_forward(model) as forward:
        xg = x.clone().requires_grad_(True)
        out = forward(xg)
        position(out, y).sum().backward()
    assert model.black_level == 0.07
    assert torch.equal(out.detach(), model(x))
    xp = x.clone().requires_grad_(True)
    position(model(xp), y).sum().backward()
    dark = x < 0.07
    assert float(xp.grad[dark].abs().max()) == 0.0
    assert float((xg.grad[dark] != 0).float().mean()) > 0.9


@pytest.mark.parametrize("objective", ["position", "attitude"])
def test_lifting_start_finds_larger_errors_than_the_random_start_above_the_clamp(objective):
    images, targets = frames(n=8, black=True)
    x, y = as_tensors(images, targets)
    model = ToyPose(black_level=0.07)
    f = OBJECTIVES[objective]
    with torch.no_grad():
        clean = f(model.eval()(x), y)
    runs = {
        kind: apgd(
            model, x, y, 0.1, f, generator=torch.Generator().manual_seed(1), steps=20, restarts=2, starts=(kind,)
        ).values
        - clean
        for kind in ("random", "lift")
    }
    assert float(runs["lift"].mean()) > 1.5 * float(runs["random"].mean())
    assert float((runs["lift"] > runs["random"]).float().mean()) >= 0.75


# --- the suite -----------------------------------------------------------------------------------------------

SMALL = SuiteConfig(
    members=("apgd/position", "apgd/range_far", "apgd/range_near", "apgd/attitude"), steps=20, restarts=2, batch_size=4
)


def test_suite_worst_case_beats_pgd50_on_a_toy_model():
    images, targets = frames(n=8, black=True)
    model = ToyPose(black_level=0.07)
    suite = run_suite(model, images, targets, [0.01, 0.1], SMALL)
    baseline = run_suite(model, images, targets, [0.01, 0.1], PGD50)
    for key in ("position_m", "attitude_deg"):
        assert np.all(suite.worst(key) >= baseline.errors[key][0] - 1e-6)
    # past the clamp (eps 0.1) the lifting start moves the position much farther than PGD-50's random start
    harm = {
        name: r.errors["position_m"][:, 1].max(0).mean() - r.clean["position_m"].mean()
        for name, r in (("suite", suite), ("pgd", baseline))
    }
    assert harm["suite"] > 1.5 * harm["pgd"] > 0
    # the attitude objective: PGD-50 on the position hardly moves the attitude
    assert suite.worst("attitude_deg")[1].mean() > baseline.errors["attitude_deg"][0, 1].mean() + 2.0


def test_nesting_makes_the_worst_case_monotone_in_eps():
    values = np.array([[[3.0, 1.0], [2.0, 5.0], [1.0, 0.5]], [[0.5, 0.2], [np.nan, 0.1], [2.5, 0.4]]])
    assert np.array_equal(nested_worst(values), [[3.0, 1.0], [3.0, 5.0], [3.0, 5.0]])
    assert np.array_equal(nested_worst(values, floor=np.array([4.0, 0.0])), [[4.0, 1.0], [4.0, 5.0], [4.0, 5.0]])
    images, targets = frames(n=4, black=True)
    result = run_suite(
        ToyPose(black_level=0.07),
        images,
        targets,
        [0.02, 0.05, 0.1, 0.2],
        SuiteConfig(members=("pgd/position", "pgd/attitude"), steps=3, restarts=1),
    )
    for key in ("position_m", "attitude_deg"):
        assert np.all(np.diff(result.worst(key), axis=0) >= 0)
        assert np.all(result.worst(key) >= result.clean[key])
    for key in ("along_m", "across_m", "attitude_deg"):
        assert np.all(np.diff(result.worst_shift(key), axis=0) >= 0)
    with pytest.raises(ValueError, match="increasing"):
        run_suite(ToyPose(), images, targets, [0.05, 0.01], SMALL)


def test_suite_rows_capacity_and_sanity():
    images, targets = frames(n=5, black=True)
    model = ToyPose(black_level=0.07)
    cfg = SuiteConfig(
        members=("apgd/position", "bpda/attitude", "square/position"),
        steps=4,
        restarts=1,
        queries=10,
        square_eps=0.1,
        batch_size=3,
    )
    result = run_suite(model, images, targets, [0.05, 0.1], cfg)
    assert result.members == cfg.members
    assert np.isnan(result.errors["position_m"][2, 0]).all() and not np.isnan(result.errors["position_m"][2, 1]).any()
    rows = suite_rows(result)
    assert [(r["attack"], r["eps"]) for r in rows] == [
        ("clean", 0.0),
        ("apgd/position", 0.05),
        ("bpda/attitude", 0.05),
        ("suite", 0.05),
        ("apgd/position", 0.1),
        ("bpda/attitude", 0.1),
        ("square/position", 0.1),
        ("suite", 0.1),
    ]
    suite_01 = rows[-1]
    assert suite_01["pos_m"] == pytest.approx(result.worst("position_m")[1].mean())
    assert suite_01["pos_ci"][0] <= suite_01["pos_m"] <= suite_01["pos_ci"][1] and suite_01["n"] == 5
    assert all(r["ok"] for r in sanity_rows(result))
    assert all(r["seconds_per_frame"] > 0 and r["cpu_seconds_per_frame"] > 0 for r in rows[1:])
    first = result.select(np.array([0, 2]))
    assert first.frames == 2 and np.array_equal(first.worst("position_m"), result.worst("position_m")[:, [0, 2]])
    cap = frame_capacity(result)
    assert cap.along_m.shape == cap.across_m.shape == cap.attitude_deg.shape == (2, 5)
    assert np.allclose(cap.target_range_m, np.linalg.norm(targets[:, :3], axis=1))
    # every member's shift is within the capacity; the capacity is some member's shift
    assert np.all(np.nan_to_num(result.shifts["along_m"], nan=0) <= cap.along_m[None] + 1e-12)
    assert np.allclose(cap.attitude_deg[1], np.nanmax(result.shifts["attitude_deg"].reshape(-1, 5), axis=0))
    # without a clamp bpda is apgd: skipped beside the apgd member of its objective; square_eps must be one of the eps
    assert run_suite(ToyPose(), images, targets, [0.1], cfg).members == cfg.members
    both = dataclasses.replace(cfg, members=("apgd/position", "bpda/position", "bpda/attitude"))
    assert run_suite(ToyPose(), images, targets, [0.1], both).members == ("apgd/position", "bpda/attitude")
    with pytest.raises(ValueError, match="square_eps"):
        run_suite(model, images, targets, [0.05], cfg)


def test_ratio_rows_flag_a_move_of_more_than_5_percent():
    def result(scale: float) -> SuiteResult:
        e = np.array([[[1.0, 3.0], [2.0, 4.0]]]) * scale
        return SuiteResult(
            (0.01, 0.05),
            ("apgd/position",),
            {"position_m": e, "attitude_deg": 10 * e},
            {},
            {"position_m": np.zeros(2), "attitude_deg": np.zeros(2)},
            np.array([20.0, 30.0]),
            np.zeros((1, 2)),
            np.zeros((1, 2)),
        )

    rows = ratio_rows(result(1.04), result(1.0))
    assert [r["ratio"] for r in rows] == pytest.approx([1.04] * 4) and all(r["ok"] for r in rows)
    assert not any(r["ok"] for r in ratio_rows(result(1.06), result(1.0)))


def test_suite_is_deterministic_and_doubled_doubles():
    images, targets = frames(n=4)
    a = run_suite(ToyPose(), images, targets, [0.05], SMALL)
    b = run_suite(ToyPose(), images, targets, [0.05], SMALL)
    assert all(np.array_equal(a.errors[k], b.errors[k]) for k in a.errors)
    d = SMALL.doubled()
    assert (d.steps, d.restarts, d.queries, d.members) == (40, 4, 2 * SMALL.queries, SMALL.members)
    with pytest.raises(ValueError, match="method/objective"):
        SuiteConfig(members=("apgd/range",))


def test_a_run_is_the_same_whether_its_eps_parts_are_computed_or_handed_back(tmp_path):
    images, targets = frames(n=6)
    model, cfg = ToyPose(black_level=0.07), dataclasses.replace(SMALL, steps=5, restarts=1)
    kept = {}

    def keep(e, compute):
        kept[e] = compute()
        return kept[e]

    whole = run_suite(model, images, targets, [0.01, 0.1], cfg, part=keep)
    assert sorted(kept) == [0.01, 0.1] and all(p.eps == (e,) for e, p in kept.items())
    key = "k" * 64
    for e, p in kept.items():
        write_suite_part(tmp_path / f"{e:g}.npz", p, key, "cpu")
    assert read_suite_part(tmp_path / "0.1.npz", "other") is None and read_suite_part(tmp_path / "no.npz", key) is None

    def stored(e, compute):
        return read_suite_part(tmp_path / f"{e:g}.npz", key)[0]

    again = run_suite(model, images, targets, [0.01, 0.1], cfg, part=stored)
    assert again.eps == whole.eps and again.members == whole.members
    for k in whole.errors:
        assert np.array_equal(again.errors[k], whole.errors[k], equal_nan=True)
    assert np.array_equal(join_eps([kept[0.01], kept[0.1]]).worst("position_m"), whole.worst("position_m"))
    with pytest.raises(ValueError, match="does not match the suite"):
        run_suite(model, images, targets, [0.01, 0.1], cfg, part=lambda e, compute: kept[0.01])
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(DataError, match="bad.npz: not a readable suite part"):
        read_suite_part(tmp_path / "bad.npz", key)


def test_part_keys_name_the_model_the_frames_and_the_settings():
    images, targets = frames(n=4)
    key = part_key("a" * 64, images, targets, SMALL)
    assert key == part_key("a" * 64, images.copy(), targets.copy(), SMALL)
    assert key != part_key("b" * 64, images, targets, SMALL)
    assert key != part_key("a" * 64, images[::-1], targets, SMALL)
    assert key != part_key("a" * 64, images, targets, dataclasses.replace(SMALL, batch_size=8))


def test_exact_math_turns_off_autocast_and_tf32_and_restores_them():
    model = ToyPose()
    model.amp = True
    before = torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32
    with exact_math(model):
        assert model.amp is False and not torch.backends.cudnn.allow_tf32 and not torch.backends.cuda.matmul.allow_tf32
    assert model.amp is True and (torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32) == before
