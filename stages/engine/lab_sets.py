"""The synthetic lab recordings of `rpod lab` and `rpod heldout`: the lab's cameras (`cameras`: the synthetic K at the
reference size and the ZED's) and rendering lab-like sequences into the real-data layout (`render_lab`: the mock-up
through the ZED's geometry with the domain shift), fanned out over the engine's Blender scenes.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.formats.recordings import write_recording
from pipeline.seeds import seed_for
from stages.config.build import mockup, scene_settings
from stages.config.schema import Params
from stages.engine import pool as engine
from stages.engine.chunks import render_poses
from stages.errors import StageError

LAB_CHUNK = 30  # frames per render job of the synthetic lab sequences (stages/engine/pool.py)


def cameras(p: Params) -> tuple[Any, Any]:
    """(K_syn at the reference size (480x270), K_zed at 1920x1080) from params."""
    from pipeline.geometry.camera import Intrinsics

    c, z = p.camera, p.lab.zed
    try:
        return (
            Intrinsics(c.ref_width, c.ref_height, c.fx, c.fy, c.cx, c.cy),
            Intrinsics(z.width, z.height, z.fx, z.fy, z.cx, z.cy),
        )
    except ValueError as e:
        raise StageError(f"params.yaml camera / lab.zed: {e}") from None


def render_lab(p: Params, dest: Path, seed: int | None = None) -> list[dict[str, Any]]:
    """Render lab.sequences with the lab camera and the domain shift into dest/<seq>/ (lab layout), the
    frames fanned out over the engine's workers and the domain shift drawn in frame order. `seed`: the draws'
    seed (lateral offsets, clock offsets, the domain shift's noise); default the "lab" stream of `lab.seed`. A lab has no Earth
    or stars behind the mock-up and its frames are segmented to black by their masks: render.background does
    not apply (render_poses renders on black).

    Returns per sequence the exact lab labels (for checking the loader round trip).
    """
    from pipeline.evaluation.lab import synthetic_recording
    from pipeline.geometry.rotations import quat_to_matrix
    from pipeline.images import shift_recording

    lab, r = p.lab, p.render
    ds = lab.domain_shift
    _, K_zed = cameras(p)
    k_cal = 1.0 + float(ds.calib_error)  # the true lens differs from the calibration used for labels
    K_lab = K_zed.scaled(r.width, r.height)
    K_true = dataclasses.replace(K_lab, fx=K_lab.fx * k_cal, fy=K_lab.fy * k_cal)
    mesh, mesh_scale = mockup(p)  # the mock-up at scale x its size (= the real target's size)
    settings = dataclasses.replace(
        scene_settings(r),
        mesh=mesh,
        mesh_scale=mesh_scale,
        sun_direction=tuple(float(v) for v in ds.sun_direction),
        sun_strength=float(ds.sun_strength),
    )
    rng = np.random.default_rng(seed_for(lab.seed, "lab") if seed is None else seed)
    scale, n, truth, es = float(lab.scale), lab.frames, [], engine.engine_settings(p)
    with engine.session(es):
        for i, (z0, z1) in enumerate(lab.sequences):
            lateral = tuple(rng.uniform(-0.03, 0.03, 2) * float(z1))  # lab m, target off-centre
            rec = synthetic_recording(
                float(z0),
                float(z1),
                n,
                float(lab.fps),
                float(lab.mocap_hz),
                np.array([1.0, 0, 0, 0]),
                lateral=lateral,
                clock_offset=float(rng.uniform(0, 1 / float(lab.mocap_hz))),
                camera_body=lab.bodies.camera,
                target_body=lab.bodies.target,
            )
            # the 1/scale mock-up at the lab label t looks like the full-size target at scale * t
            rgb, alpha = render_poses(
                K_true, settings, quat_to_matrix(rec.q), scale * rec.t, LAB_CHUNK, es, f"lab render seq{i + 1}"
            )
            images, masks = shift_recording(rgb, alpha, float(ds.noise_std), float(ds.blur_sigma), rng)
            write_recording(dest / f"seq{i + 1}", rec.camera, rec.mocap, images, masks)
            truth.append({"name": f"seq{i + 1}", "t_lab": rec.t, "q": rec.q, "z_range": (float(z0), float(z1))})
    return truth
