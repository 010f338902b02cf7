"""`render.device` (issue 38, item 6): Cycles on the CPU, on a CUDA / OptiX GPU, or the GPU when bpy sees one; `auto`
falls back to the CPU with a note on a machine without one, `gpu` is refused there, the CPU path is unchanged and the
choice is recorded in the render metadata."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("bpy")

from pipeline.geometry.camera import reference_intrinsics  # noqa: E402
from pipeline.render.scene import Renderer, SceneSettings, check_settings, gpu_backend, resolve_device  # noqa: E402

K = reference_intrinsics().scaled(48, 27)


def _never() -> str | None:
    raise AssertionError("the GPU probe must not run for render.device cpu")


def test_the_device_is_resolved_as_asked():
    assert resolve_device("cpu", _never).device == "CPU"
    cuda = resolve_device("auto", lambda: "CUDA")
    assert (cuda.device, cuda.backend, cuda.note) == ("GPU", "CUDA", None)
    assert resolve_device("gpu", lambda: "OPTIX").record("gpu") == {
        "requested": "gpu",
        "used": "gpu",
        "backend": "OPTIX",
        "note": None,
    }
    fallback = resolve_device("auto", lambda: None)
    assert fallback.device == "CPU" and "no OptiX or CUDA device" in fallback.note
    with pytest.raises(ValueError, match="bpy sees no OptiX or CUDA device"):
        resolve_device("gpu", lambda: None)
    with pytest.raises(ValueError, match="cpu, gpu, auto"):
        resolve_device("metal", lambda: None)
    with pytest.raises(ValueError, match="device must be one of"):
        check_settings(K, SceneSettings(device="tpu"))


@pytest.mark.skipif(gpu_backend() is not None, reason="this machine has a GPU that bpy sees")
def test_on_a_cpu_only_machine_auto_falls_back_to_the_cpu_and_gives_the_cpu_images():
    """The real probe finds no GPU here: auto renders on the CPU, pixel for pixel as the default; gpu is refused."""
    from stages.engine.chunks import device_record
    from stages.errors import StageError

    assert device_record(SceneSettings(device="auto"))["used"] == "cpu"
    with pytest.raises(StageError, match="render.device: render device gpu: bpy sees no"):
        device_record(SceneSettings(device="gpu"))
    images = {}
    for device in ("cpu", "auto"):
        with Renderer(K, SceneSettings(samples=2, device=device)) as r:
            images[device] = r.render(np.eye(3), np.array([0.0, 0.0, 20.0]))
            assert r.cycles.device == "CPU"
    assert np.array_equal(images["cpu"], images["auto"]) and images["cpu"].max() > 0


def test_the_default_device_leaves_fingerprints_and_metadata_as_they_were():
    from stages.config import params as params_mod
    from stages.config.schema import build

    default = build(params_mod.compose("default", []))
    auto = build(params_mod.compose("default", ["render.device=auto"]))
    assert default.render.device == "cpu" and "device" not in params_mod.render_record(default.render)
    assert params_mod.render_record(auto.render)["device"] == "auto"
    assert params_mod.render_fingerprint(auto) != params_mod.render_fingerprint(default)
    assert build(params_mod.compose("paper", [])).render.device == "auto"
