"""Space backgrounds (pipeline/render/backgrounds.py): the per-frame draw, the Earth's place in the image, the
composite under the target's alpha, and the render stages with render.background on and off."""

import json

import numpy as np
import pandas as pd
import pytest

from pipeline.geometry.camera import Intrinsics, reference_intrinsics
from pipeline.render.backgrounds import FrameBackground, backdrop, composite, draw, earth, kind, pose_key
from pipeline.render.settings import BackgroundSettings
from stages.config import params as params_mod
from stages.config.params import load

K160 = reference_intrinsics(fy=640.0).scaled(160, 90)
SUN_DOWN = np.array([0.0, 1.0, 0.0])  # sunlight travelling towards image-down (camera frame): the Earth below lit
CLAMP = 0.07  # the robust model's black level (pipeline/pose/model.py), pixel units


def frame(nadir, seed=0):
    n = np.asarray(nadir, dtype=np.float64)
    return FrameBackground(tuple(n / np.linalg.norm(n)), seed)


def test_share_is_binomial_nested_and_deterministic():
    """Each frame is drawn on its own: the share of non-black frames is within 4 binomial standard deviations of
    `share`; the same (seed, key) gives the same draw; a larger share keeps every frame a smaller one drew."""
    n, keys = 2000, range(2000)
    drawn = {share: [draw(BackgroundSettings(share=share), np.eye(3), 7, k) for k in keys] for share in (0.0, 0.3, 0.6)}
    assert all(f is None for f in drawn[0.0])
    for share in (0.3, 0.6):
        on = sum(f is not None for f in drawn[share])
        assert abs(on - share * n) < 4 * np.sqrt(n * share * (1 - share)), (share, on)
    assert all(b is not None and a == b for a, b in zip(drawn[0.3], drawn[0.6]) if a is not None)
    again = [draw(BackgroundSettings(share=0.3), np.eye(3), 7, k) for k in keys]
    assert again == drawn[0.3]
    other_seed = [draw(BackgroundSettings(share=0.3), np.eye(3), 8, k) for k in keys]
    assert other_seed != drawn[0.3]


def test_nadir_follows_the_camera_attitude_within_the_jitter():
    """The nadir in the camera frame is R_cam^T nadir_world, tilted by at most nadir_jitter_deg."""
    nadir = np.array([0.0, 0.848, 0.530]) / np.linalg.norm([0.0, 0.848, 0.530])
    rolled = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # camera x (image right) = world +y
    exact = draw(BackgroundSettings(share=1.0, nadir=tuple(nadir), nadir_jitter_deg=0.0), rolled, 0, 3)
    assert np.allclose(exact.nadir, [0.848, 0.0, 0.530] / np.hypot(0.848, 0.530))  # the Earth on the right
    s = BackgroundSettings(share=1.0, nadir=tuple(nadir), nadir_jitter_deg=10.0)
    tilts = [np.degrees(np.arccos(np.clip(np.dot(draw(s, np.eye(3), 0, k).nadir, nadir), -1, 1))) for k in range(500)]
    assert max(tilts) <= 10.0 + 1e-9 and max(tilts) > 9.0 and min(tilts) < 3.0


def test_the_limb_lies_where_the_geometry_puts_it():
    """Boresight 32 deg below the local horizontal at 1336 km: the limb (the horizon's dip is acos(R/(R+h)) =
    34.2 deg) lies 2.2 deg below the image centre, row cy + fy tan(2.24 deg) = 52.8 at 160x90; sky above it,
    Earth below it, the limb's pixels antialiased; a camera rolled by 180 deg sees the Earth at the top."""
    s = BackgroundSettings(share=1.0)
    f = frame([0.0, 0.848, 0.530])
    _, coverage = earth(K160, s, f, SUN_DOWN, 6.0, np.random.default_rng(0))
    dip = np.degrees(np.arccos(6371.0 / (6371.0 + 1336.0)))
    row = K160.cy + K160.fy * np.tan(np.radians(dip - np.degrees(np.arcsin(0.530 / np.hypot(0.848, 0.530)))))
    col = coverage[:, 80]
    assert (col[: int(row) - 1] == 0).all() and (col[int(row) + 2 :] == 1).all()
    assert 0 < col[int(round(row))] < 1  # the limb pixel is partly covered
    centred = Intrinsics(160, 90, K160.fx, K160.fy, 79.5, 44.5)
    _, up = earth(centred, s, f, SUN_DOWN, 6.0, np.random.default_rng(0))
    _, down = earth(centred, s, frame([0.0, -0.848, 0.530]), -SUN_DOWN, 6.0, np.random.default_rng(0))
    assert np.array_equal(down, up[::-1, ::-1]) and up[-1].all()  # a rolled camera: the Earth at the top


def test_kind_says_what_the_frame_shows():
    s = BackgroundSettings(share=1.0)
    below = frame([0.0, 0.848, 0.530])
    assert kind(K160, s, None, SUN_DOWN) == "black"
    assert kind(K160, s, below, SUN_DOWN) == "earth"
    assert kind(K160, s, below, -SUN_DOWN) == "space"  # the Earth in view is its night side
    assert kind(K160, s, frame([0.0, 1.0, 0.0]), SUN_DOWN) == "space"  # straight down: below the view


def test_composite_keeps_the_target_and_blends_without_seams():
    """Where alpha = 1 the target's pixel is its own whatever lies behind; where alpha = 0 it is the backdrop;
    an edge pixel is the alpha blend of the two (between them: no dark or bright fringe of premultiplied alpha)."""
    s = BackgroundSettings(share=1.0, stars=0.05)
    f = frame([0.0, 0.848, 0.530], seed=11)
    rng = np.random.default_rng(0)
    straight = rng.uniform(0, 255, (90, 160, 3)).astype(np.float32)
    alpha = np.zeros((90, 160), np.float32)
    alpha[:, :50] = 1.0
    alpha[:, 50:100] = rng.integers(0, 256, (90, 50)) / 255.0
    out = composite(straight, alpha, K160, s, f, SUN_DOWN, 6.0).astype(np.float64)
    back = 255.0 * backdrop(K160, s, f, SUN_DOWN, 6.0, np.random.default_rng(f.seed))
    assert back[60:].min() > CLAMP * 255 and back.max() <= 255  # the Earth fills the bottom, above the clamp
    assert np.array_equal(out[:, :50], np.rint(straight[:, :50]))
    assert np.array_equal(out[:, 100:], np.rint(back[:, 100:]))
    edge = slice(50, 100)
    lo = np.minimum(straight[:, edge], back[:, edge]) - 0.5
    hi = np.maximum(straight[:, edge], back[:, edge]) + 0.5
    assert ((out[:, edge] >= lo) & (out[:, edge] <= hi)).all()
    a = alpha[:, edge, None]
    assert np.abs(out[:, edge] - (straight[:, edge] * a + back[:, edge] * (1 - a))).max() <= 0.5


def test_stars_stay_behind_the_earth_and_the_offset_lifts_the_sky_above_the_clamp():
    s = BackgroundSettings(share=1.0, stars=0.5)
    f = frame([0.0, 0.848, 0.530], seed=5)
    rng = np.random.default_rng(f.seed)
    _, coverage = earth(K160, s, f, -SUN_DOWN, 6.0, rng)  # the night side: black Earth
    sky = backdrop(K160, s, f, -SUN_DOWN, 6.0, np.random.default_rng(f.seed))
    assert sky[coverage == 0].max() > 0.05  # stars in the sky
    assert sky[coverage == 1].max() == 0  # none through the night-side Earth
    black = np.zeros((90, 160, 3), np.float32)
    none = np.zeros((90, 160), np.float32)
    dark = BackgroundSettings(share=1.0, nadir=(0.0, -1.0, 0.0))  # the Earth behind the camera's back
    assert composite(black, none, K160, dark, frame([0.0, -1.0, 0.0]), SUN_DOWN, 6.0).max() == 0
    rng = np.random.default_rng(1)  # over an all-black backdrop: scene.py's black frame, byte for byte
    straight = rng.integers(0, 256, (90, 160, 3)).astype(np.float32)
    alpha = (rng.integers(0, 256, (90, 160)) / 255.0).astype(np.float32)
    on_black = np.clip(np.rint(straight * alpha[..., None]), 0, 255).astype(np.uint8)
    assert np.array_equal(composite(straight, alpha, K160, dark, frame([0.0, -1.0, 0.0]), SUN_DOWN, 6.0), on_black)
    lifted = BackgroundSettings(share=1.0, black_offset=0.1)
    out = composite(black, none, K160, lifted, frame([0.0, -1.0, 0.0]), SUN_DOWN, 6.0)
    assert (out == round(0.1 * 255)).all() and out.min() > CLAMP * 255
    noisy = BackgroundSettings(share=1.0, black_offset=0.1, noise_std=0.01)
    out = composite(black, none, K160, noisy, frame([0.0, -1.0, 0.0], seed=2), SUN_DOWN, 6.0) / 255.0
    assert abs(out.mean() - 0.1) < 0.002 and 0.007 < out.std() < 0.013


def test_pose_key_matches_poses_to_1e_9():
    R, t = np.eye(3), np.array([0.1, -0.2, 30.0])
    assert pose_key(R, t) == pose_key(R + 1e-12, t - 1e-12)
    assert pose_key(R, t) != pose_key(R, t + np.array([0, 0, 1e-6]))
    assert 0 <= pose_key(R, t) < 2**63


# ---------------------------------------------------------------------------- Blender and the render stages
@pytest.fixture
def scene():
    """pipeline.render.scene (Blender), or the test skipped where bpy is missing."""
    pytest.importorskip("bpy")
    from pipeline.render import scene

    return scene


TINY = [
    "render.width=48",
    "render.height=27",
    "render.frames_per_sequence=3",
    "render.samples=2",
    "render.chunk=4",
    "render.previews=1",
    "engine.workers=1",
]
ON = [
    "render.background.share=0.5",
    "render.background.stars=0.05",
    "render.background.black_offset=0.1",
    "render.background.noise_std=0.005",
    "render.sun_direction=[-0.5,0.3,1.0]",
]


@pytest.mark.slow
def test_the_target_keeps_its_pixels_over_any_background(scene):
    """One pose rendered on black and over the Earth (default and background settings alike give the same black
    frame): the pixels the target covers (alpha = 1) are the same bytes, the sky around it is not black."""
    K = reference_intrinsics(fy=640.0).scaled(48, 27)
    R, t = np.eye(3), np.array([0.0, 0.0, 12.0])
    s = BackgroundSettings(share=1.0, stars=0.05)
    sun = (0.0, 1.0, 0.5)  # light travelling down and away: the Earth below in daylight
    with scene.Renderer(K, scene.SceneSettings(samples=2, sun_direction=sun)) as r:
        plain = r.render(R, t)
    with scene.Renderer(K, scene.SceneSettings(samples=2, sun_direction=sun, background=s)) as r:
        black, alpha = r.render_with_alpha(R, t)
        over = r.render(R, t, frame([0.0, 0.848, 0.530], seed=4))
    assert np.array_equal(plain, black)
    solid = alpha == 1
    assert solid.sum() > 50 and np.array_equal(over[solid], black[solid])
    assert (over[alpha == 0] > CLAMP * 255).mean() > 0.3 and not black[alpha == 0].any()


def _render(workdir, overrides):
    """`rpod render` and `rpod label` in workdir with the tiny params -> (images, poses, labels, meta)."""
    from pipeline.io.store import open_zarr
    from stages import label, render

    params_mod.write_params(params_mod.compose("smoke", TINY + overrides))
    render.main(load())
    label.main(load())
    out = workdir / "datasets/render"
    return (
        open_zarr(out / "images.zarr")["images"][:],
        pd.read_parquet(out / "poses.parquet"),
        pd.read_parquet(workdir / "datasets/labels.parquet"),
        json.loads((out / "meta.json").read_text()),
    )


@pytest.mark.slow
def test_render_stage_with_backgrounds_on_and_off(tmp_path, monkeypatch, scene):
    """Off (share 0; the profiles render a quarter of the frames over a background): no `background` column, no
    background in meta.json, the same fingerprint as params without the section. On: a `background` column (black,
    space, earth) in poses and labels, the non-black frames the drawn ones; the same images for another chunk
    length; the frames of a black kind are black around the target and the others lifted above the clamp by the
    black offset."""
    monkeypatch.chdir(tmp_path)
    images, poses, labels, meta = _render(tmp_path, ["render.background.share=0"])
    assert "background" not in poses and "background" not in labels and "background" not in meta["render"]
    assert "## Backgrounds" not in (tmp_path / "reports/dataset.md").read_text()
    without = params_mod.compose("smoke", TINY)
    before = {
        k: v
        for k, v in without["render"].items()
        if k not in ("background", "source", "source_test", "target_attitude", "device")  # device: cpu
    }
    assert meta["fingerprint"] == params_mod.fingerprint(
        {"seed": without["seed"], "camera": without["camera"], "render": {**before, "mesh": None}}
    )  # as before it
    on, poses, labels, meta = _render(tmp_path, ON)
    assert meta["render"]["background"]["share"] == 0.5
    assert set(poses.background) <= {"black", "space", "earth"} and (poses.background == "earth").any()
    assert labels.background.tolist() == poses.sort_values("index").background.tolist()
    card = (tmp_path / "reports/dataset.md").read_text()
    assert "## Backgrounds" in card and f"| black        | {(labels.background == 'black').sum()}" in card
    black = (poses.background == "black").to_numpy()
    assert 0 < black.sum() < len(poses)
    corner = on[:, :2, :2].reshape(len(on), -1)
    assert not corner[black].any() and (corner[~black] >= CLAMP * 255).all()
    again, *_ = _render(tmp_path, ON + ["render.chunk=5"])
    assert np.array_equal(on, again)


@pytest.mark.slow
def test_workers_render_the_same_frames_in_any_order(tmp_path, scene):
    """Chunks rendered by separate workers, in reverse order, give the images of one worker in order."""
    from pipeline.geometry.trajectories import approach_sequences, flatten
    from pipeline.io.store import reopen_array
    from stages.engine.chunks import FrameRange, RenderSetup, RenderWorker, create_store, frame_backgrounds

    K = reference_intrinsics(fy=640.0).scaled(32, 18)
    settings = scene.SceneSettings(samples=1, background=BackgroundSettings(share=0.5, stars=0.05, noise_std=0.01))
    seqs = approach_sequences(2, seed=1)[:4]
    _, _, R, t = flatten(seqs)
    draws, _ = frame_backgrounds(K, settings, R, np.concatenate([s.R_cam for s in seqs]), 9)
    out = {}
    for name, order in (("in order", [(0, 4), (4, 8)]), ("reversed", [(4, 8), (0, 4)])):
        url = str(tmp_path / f"{name}.zarr")
        create_store(url, len(t), K.height, K.width, 4)
        setup = RenderSetup(K, settings, R, t, url, None, tuple(draws))
        for lo, hi in order:
            worker = RenderWorker(setup)  # a fresh worker (Blender scene) per chunk
            worker.run(FrameRange(lo, hi))
            worker.close()
        out[name] = reopen_array(url, "images")[:]
    assert np.array_equal(out["in order"], out["reversed"]) and out["in order"].any()
    assert any(d is None for d in draws) and any(d is not None for d in draws)


def test_bad_background_params_are_one_line():
    """The settings refuse a bad value when built (one line naming it), and params.yaml's section, composed from
    them, refuses it naming the key."""
    with pytest.raises(ValueError, match=r"background.nadir must be a non-zero 3-vector") as e:
        BackgroundSettings(share=0.5, nadir=(0.0, 0.0, 0.0))
    assert "\n" not in str(e.value)
    from stages.config.schema import build
    from stages.config.sections import ParamsError

    with pytest.raises(ParamsError, match=r"^params.yaml render.background.share must be in \[0, 1\], got 1.5$"):
        build(params_mod.compose("smoke", ["render.background.share=1.5"]))
    with pytest.raises(ParamsError, match=r"^params.yaml render.background.nadir must be a non-zero 3-vector"):
        build(params_mod.compose("smoke", ["render.background.nadir=[0,0,0]"]))


@pytest.mark.slow
def test_the_guidance_loop_renders_each_pose_over_its_own_draw(scene):
    """Off, the guidance loop's images are the renderer's black ones; on, a pose's image is the same every time
    it is rendered (the loop's image cache relies on it), its draw keyed by the pose with the camera at R^T."""
    from stages.engine.guidance_worker import pose_renderer

    K = reference_intrinsics(fy=640.0).scaled(32, 18)
    R, t = np.eye(3), np.array([0.5, 0.0, 15.0])
    with scene.Renderer(K, scene.SceneSettings(samples=1)) as r:
        assert np.array_equal(pose_renderer(r, 5)(R, t), r.render(R, t))
    s = BackgroundSettings(share=1.0, stars=0.05, black_offset=0.1, noise_std=0.01)
    with scene.Renderer(K, scene.SceneSettings(samples=1, background=s)) as r:
        render = pose_renderer(r, 5)
        first = render(R, t)
        assert np.array_equal(first, render(R, t)) and first.min() > CLAMP * 255
        assert np.array_equal(first, r.render(R, t, draw(s, R.T, 5, pose_key(R, t))))
        assert not np.array_equal(first, render(R, t + np.array([0.0, 0.0, 1e-3])))  # another pose, another draw
