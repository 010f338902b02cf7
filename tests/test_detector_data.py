"""Issue 27, items 3 and 5: the detector's data without the confound (clean and attacked samples of the same
images, none seen by the pose network) and the same verdict on any machine (CPU instruction-set pins,
no timings in DVC outputs)."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import zarr

from pipeline.io.atomic import write_json
from pipeline.io.store import create_array, seal_zarr
from pipeline.shap import plan_sources, sample_plan
from stages.config import params as params_mod
from stages.config.cpu import ISA_ENV, PINS, isa_label, pin_cpu_isa

REPO = Path(__file__).resolve().parent.parent


# ---- the sample plan ------------------------------------------------------------------------------------------


def test_sample_plan_pairs_clean_and_attacked_on_the_same_images():
    pool = np.arange(1000, 1040)
    plan = sample_plan(12, 4, [0.5, 0.05, 0.01], pool, np.random.default_rng(0))
    clean = plan["eps"] == 0
    assert clean.sum() == 12 and all((plan["eps"] == np.float32(e)).sum() == 4 for e in (0.5, 0.05, 0.01))
    assert set(plan["index"]) <= set(pool)
    # every image clean once and attacked once at one eps: the two classes show the same images
    assert sorted(plan["index"][clean]) == sorted(plan["index"][~clean])
    assert len(set(plan["index"][clean])) == 12 and len(set(plan["index"][~clean])) == 12
    again = sample_plan(12, 4, [0.5, 0.05, 0.01], pool, np.random.default_rng(0))
    assert np.array_equal(plan["index"], again["index"]) and np.array_equal(plan["eps"], again["eps"])
    other = sample_plan(12, 4, [0.5, 0.05, 0.01], pool, np.random.default_rng(1))
    assert not np.array_equal(plan["index"], other["index"])


def test_sample_plan_with_unequal_classes_and_too_small_a_pool():
    plan = sample_plan(6, 5, [0.5, 0.05], np.arange(30), np.random.default_rng(0))  # 6 clean, 10 attacked
    clean = plan["eps"] == 0
    assert plan_sources(6, 5, 2) == 10 and len(set(plan["index"])) == 10
    assert set(plan["index"][clean]) <= set(plan["index"][~clean])  # the clean images are attacked too
    plan = sample_plan(10, 2, [0.5, 0.05], np.arange(30), np.random.default_rng(0))  # 10 clean, 4 attacked
    assert set(plan["index"][plan["eps"] > 0]) <= set(plan["index"][plan["eps"] == 0])
    with pytest.raises(ValueError, match="10 source images needed but the pool holds 9"):
        sample_plan(10, 1, [0.5], np.arange(9), np.random.default_rng(0))


def test_the_detector_split_has_enough_trajectories_of_its_own_seed():
    p = params_mod.build(params_mod.compose("default"))
    assert params_mod.detector_trajectories(p) * p.shap.frames >= plan_sources(
        p.shap.normal, p.shap.per_eps, len(p.shap.eps)
    )
    moved = params_mod.build(params_mod.compose("default", ["shap.seed=4001"]))
    assert params_mod.detect_render_fingerprint(moved) != params_mod.detect_render_fingerprint(p)
    assert params_mod.eval_render_fingerprint(moved) == params_mod.eval_render_fingerprint(p)
    assert p.shap.seed not in (params_mod.evaluation_seed(p), params_mod.validation_seed(p))


def _write_trajectories(folder: Path, p, n: int, seed: int) -> np.ndarray:
    """A stand-in detector split (what `rpod eval_render --detector` writes) of random images; returns them."""
    from pipeline.geometry.labels import pose_columns
    from pipeline.geometry.rotations import euler_to_matrix, matrix_to_6d, matrix_to_quat

    rng = np.random.default_rng(seed)
    h, w = p.render.height, p.render.width
    images = rng.integers(0, 256, (n, h, w, 3), dtype=np.uint8)
    create_array(
        zarr.open_group(str(folder / "images.zarr"), mode="w"),
        "images",
        shape=images.shape,
        chunks=(8, h, w, 3),
        dtype="uint8",
    )[:] = images
    seal_zarr(folder / "images.zarr")
    R, tz = euler_to_matrix(rng.uniform(-5, 5, (n, 3))), rng.uniform(10, 60, n)
    t = np.stack([np.zeros(n), np.zeros(n), tz], 1)
    pd.DataFrame(
        {
            "index": np.arange(n),
            "trajectory": np.arange(n) // p.shap.frames,
            "frame": np.arange(n) % p.shap.frames,
            **pose_columns(t, matrix_to_quat(R), matrix_to_6d(R)),
            "range": tz,
        }
    ).to_parquet(folder / "poses.parquet")
    write_json(
        folder / "meta.json", {"complete": True, "frames": n, "fingerprint": params_mod.detect_render_fingerprint(p)}
    )
    return images


def test_the_shap_stage_explains_only_images_the_pose_network_never_saw(tmp_path, monkeypatch):
    """The detector's sample plan has no image on both the pose-training and the detector side, and its
    clean and attacked samples share their source images (checked on the GAP features of what was explained)."""
    import torch
    from test_lab import stand_in_models
    from test_training import write_dataset

    from pipeline.shap import gap_features
    from stages import shap
    from stages.artifacts.data import load_split

    monkeypatch.chdir(tmp_path)
    torch.set_num_threads(1)
    p = write_dataset(
        tmp_path,
        n=40,
        overrides=[
            "shap.background=4",
            "shap.normal=8",
            "shap.per_eps=4",
            "shap.eps=[0.5,0.05]",
            "shap.frames=5",
            "shap.chunk=6",
        ],
    )
    stand_in_models(p)
    (tmp_path / "datasets/detect_render").mkdir()
    images = _write_trajectories(tmp_path / "datasets/detect_render", p, params_mod.detector_trajectories(p) * 5, 7)
    shap.main(p)
    store = zarr.open_group("datasets/shap.zarr", mode="r")
    eps, src = store["eps"][:], store["source_index"][:]
    clean = eps == 0
    assert clean.sum() == 8 and (~clean).sum() == 8 and src.max() < len(images)
    assert sorted(src[clean]) == sorted(src[~clean])  # the same images, clean and attacked
    assert dict(store.attrs)["counts"] == {"clean": 8, "per_eps": 4, "sources": 8, "shared": 8}
    from stages.artifacts.models import load_pose

    model = load_pose(p).model
    np.testing.assert_allclose(store["features"][:][clean], gap_features(model, images[src[clean]])[0], atol=1e-5)
    train = load_split(p, "train")  # what the pose network trained on
    seen = gap_features(model, np.asarray(train.images))[0]
    distance = np.abs(store["features"][:][:, None, :] - seen[None]).max(axis=2)
    assert distance.min() > 1e-3  # no explained image is a training image


# ---- the same verdict on any machine -------------------------------------------------------------------------


def test_cpu_isa_pin_is_set_when_absent_and_respected_when_set():
    env: dict[str, str] = {}
    assert pin_cpu_isa(env, "x86_64") == "avx2" and env == PINS["avx2"] and isa_label(env) == "avx2"
    mine = {"ATEN_CPU_CAPABILITY": "default"}
    pin_cpu_isa(mine, "x86_64")
    assert mine["ATEN_CPU_CAPABILITY"] == "default" and mine["ONEDNN_MAX_CPU_ISA"] == "AVX2"  # the user's wins
    assert "ATEN_CPU_CAPABILITY=default" in isa_label(mine)
    native = {ISA_ENV: "native"}
    assert pin_cpu_isa(native, "x86_64") == "native" and native == {ISA_ENV: "native"} and isa_label(native) == "native"
    arm: dict[str, str] = {}
    assert pin_cpu_isa(arm, "aarch64") == "native" and arm == {}
    with pytest.raises(ValueError, match=r"\$RPOD_CPU_ISA='avx9': choose one of avx2, native"):
        pin_cpu_isa({ISA_ENV: "avx9"}, "x86_64")


@pytest.mark.skipif(platform.machine().lower() not in ("x86_64", "amd64"), reason="the pins are for x86-64")
def test_rpod_pins_torch_before_it_loads():
    """torch, imported after the CLI module, runs the capped kernels; a variable the user set is kept."""
    probe = (
        "import os, stages.cli, torch; "
        "print(torch.backends.cpu.get_cpu_capability(), os.environ['ONEDNN_MAX_CPU_ISA'], os.environ['MKL_CBWR'])"
    )
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in ("ATEN_CPU_CAPABILITY", "ONEDNN_MAX_CPU_ISA", "MKL_CBWR", ISA_ENV)
    }
    env.update({"PYTHONPATH": str(REPO), "ONEDNN_MAX_CPU_ISA": "SSE41"})  # one the user set: kept
    out = subprocess.run(
        [sys.executable, "-c", probe], env=env, capture_output=True, text=True, check=True, cwd=REPO
    ).stdout.split()
    assert out == ["AVX2", "SSE41", "AVX2"]


@pytest.mark.skipif(platform.machine().lower() not in ("x86_64", "amd64"), reason="the pins are for x86-64")
def test_importing_stages_pins_numpy_before_it_loads():
    """`import stages` (which imports numpy) runs numpy's OpenBLAS on the AVX2 kernels and no AVX-512 loop (no
    AVX-512 dispatch target stays on; single AVX-512 extensions a CPU has, e.g. VPOPCNTDQ or VBMI on Zen 4, stay
    listed as CPU features but no loop is built for them alone), and every target the pin disables is one numpy
    dispatches (else numpy refuses to import)."""
    probe = (
        "import json, stages, numpy, threadpoolctl; "
        "from numpy.core._multiarray_umath import __cpu_dispatch__, __cpu_features__; "
        "print(json.dumps([sorted({i['architecture'] for i in threadpoolctl.threadpool_info() "
        "if i['internal_api'] == 'openblas'}), [k for k in __cpu_dispatch__ if 'AVX512' in k and __cpu_features__[k]], "
        "list(__cpu_dispatch__)]))"
    )
    env = {k: v for k, v in os.environ.items() if k not in (*PINS["avx2"], ISA_ENV)}
    env["PYTHONPATH"] = str(REPO)
    out = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True, check=True, cwd=REPO)
    blas, avx512_on, dispatched = json.loads(out.stdout)
    assert blas == ["Haswell"] and avx512_on == []
    assert set(PINS["avx2"]["NPY_DISABLE_CPU_FEATURES"].split()) <= set(dispatched)


def test_trajectory_renders_keep_timings_out_of_meta_json(tmp_path, monkeypatch):
    """eval_render --detector: the same params give byte-identical meta.json and poses (a stable DVC hash);
    the render time goes to reports/metrics/detect_render.json."""
    from stages import eval_render
    from stages.engine import trajectory_sets

    def fake_render(url, K, scene, R, t, chunk, es, label, **kw):  # stands in for Blender: zeros, 1.5 s
        create_array(
            zarr.open_group(url, mode="w"),
            "images",
            shape=(len(t), K.height, K.width, 3),
            chunks=(chunk, K.height, K.width, 3),
            dtype="uint8",
        )[:] = 0
        seal_zarr(url)
        return 1.5

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(trajectory_sets, "render_to_store", fake_render)
    p = params_mod.build(params_mod.compose("smoke", ["engine.workers=1"]))
    seen = []
    for _ in range(2):
        eval_render.main(p, detector=True)
        seen.append([(tmp_path / "datasets/detect_render" / f).read_bytes() for f in ("meta.json", "poses.parquet")])
    assert seen[0] == seen[1]
    meta = json.loads(seen[0][0])
    assert not {"seconds", "seconds_per_image", "workers"} & set(meta)
    assert meta["frames"] == params_mod.detector_trajectories(p) * p.shap.frames >= p.shap.normal
    timing = json.loads((tmp_path / "reports/metrics/detect_render.json").read_text())
    assert timing["sets"]["detect_render"]["seconds"] == 1.5 and timing["cpu_isa"]["cap"] == isa_label()
