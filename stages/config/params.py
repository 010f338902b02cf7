"""Params: compose profiles into params.yaml, load and validate it for a stage."""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import Any

import yaml

from pipeline.io.atomic import atomic_write_text
from stages.errors import StageError
from stages.config.schema import DEVICE, Params, ParamsError, build

ROOT = Path(__file__).resolve().parents[2]
CONF_DIR = ROOT / "conf"
PARAMS_FILE = Path("params.yaml")
# The value of an unset external input (render.mesh, render.source, lab.mesh, lab.real_data): a tracked
# folder, because dvc.yaml lists these params' paths as deps and a dep must exist (null cannot be one).
NONE = "inputs/none"


def profiles() -> list[str]:
    """Names of the profiles in conf/profile/."""
    return sorted(p.stem for p in (CONF_DIR / "profile").glob("*.yaml"))


def compose(profile: str = "default", overrides: list[str] | None = None) -> dict[str, Any]:
    """Compose conf/config.yaml with one profile (and optional Hydra overrides) via Hydra."""
    if profile not in profiles():
        raise ParamsError(f"unknown profile {profile!r}; choose one of {', '.join(profiles())} (conf/profile/)")
    from hydra import compose as hydra_compose, initialize_config_dir
    from omegaconf import OmegaConf

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base=None):
        cfg = hydra_compose(config_name="config", overrides=[f"profile={profile}", *(overrides or [])])
    return OmegaConf.to_container(cfg, resolve=True)  # type: ignore[return-value]


def render_key(params: dict[str, Any]) -> dict[str, Any]:
    """The `render` params as fingerprints hash them: unset external inputs (null or inputs/none) as
    null, an unset SPEED source left out, and no scale-out settings (they do not change the images)."""
    r = {k: v for k, v in params["render"].items() if k != "workers"}
    r["mesh"] = given(r.get("mesh"))
    if given(r.get("source")) is None:
        r.pop("source", None), r.pop("source_test", None)
    return r


def render_fingerprint(params: dict[str, Any]) -> str:
    """Hash of everything that decides the rendered images (`seed`, `camera`, `render`): the render
    stage stamps it into datasets/render/meta.json; every reader of the renders compares it."""
    key = json.dumps({"seed": params["seed"], "camera": params["camera"], "render": render_key(params)}, sort_keys=True)
    return hashlib.sha256(key.encode()).hexdigest()[:16]


def check_render_fingerprint(meta: dict[str, Any], params: dict[str, Any], path: Path | str) -> None:
    """Refuse renders (meta.json at `path`) made with other `seed`/`camera`/`render` params than params.yaml."""
    if meta.get("fingerprint") != render_fingerprint(params):
        raise ParamsError(f"{path} was rendered with other seed/camera/render params than params.yaml "
                          f"(fingerprint {meta.get('fingerprint')!r}, params give {render_fingerprint(params)!r}); "
                          f"re-run `rpod render` (or `dvc repro`)")


def write_params(params: dict[str, Any], path: Path = PARAMS_FILE) -> None:
    atomic_write_text(path, yaml.safe_dump(params, sort_keys=False, default_flow_style=None, width=100))


def load(path: Path = PARAMS_FILE) -> dict[str, Any]:
    """Read params.yaml and check it against stages.config.schema (unknown keys refused with a suggestion)."""
    path = Path(path)
    if not path.exists():
        raise ParamsError(f"{path} not found: run `rpod params default` (or another profile) first")
    try:
        params = yaml.safe_load(path.read_text())
    except yaml.YAMLError as e:
        raise ParamsError(f"{path} is not valid YAML: {e}") from None
    if not isinstance(params, dict):
        raise ParamsError(f"{path} must hold a mapping of sections")
    build(params)   # unknown keys, types and ranges of every section (stages.config.schema), checked once here
    return params


def typed(params: dict[str, Any]) -> Params:
    """The typed view (stages.config.schema.Params) of params that `load` returned."""
    return build(params)


# ----------------------------------------------------------------------------- params -> library objects
def given(value: str | None) -> str | None:
    """An external-input param's path, or None when it is unset: null, or a path ending in `inputs/none`."""
    if value is None or Path(value).parts[-2:] == tuple(NONE.split("/")):
        return None
    return str(value)


def torch_setup(params: dict[str, Any], processes: int = 1, local_rank: int | None = None):
    """A torch stage's start: torch's CPU threads from `threads` (null: every core, shared among `processes`
    torchrun processes), then the device (`torch_device`: a missing CUDA GPU stops the stage before any work)."""
    import torch

    n = params["threads"]
    torch.set_num_threads(max(1, (os.cpu_count() or 1) // processes) if n is None else int(n))
    return torch_device(params, local_rank)


def torch_device(params: dict[str, Any], local_rank: int | None = None):
    """The torch.device of every torch stage, from the `device` param: auto = the CUDA GPU when torch
    sees one, else the CPU. Under torchrun, a CUDA process takes GPU `local_rank`. StageError when
    CUDA is asked for and torch sees no GPU (or fewer than the index)."""
    import torch

    value = str(params["device"])
    if not DEVICE.fullmatch(value):
        raise StageError(f"params.yaml device must be auto, cpu, cuda or cuda:N, got {value!r}")
    cuda = torch.cuda.is_available()
    if value == "cpu" or (value == "auto" and not cuda):
        return torch.device("cpu")
    if not cuda:
        raise StageError(f"params.yaml device: {value!r} asks for a CUDA GPU but torch {torch.__version__} sees none; "
                         f"set device: auto or cpu")
    index = local_rank if local_rank is not None else int(value.partition(":")[2] or 0)
    if index >= torch.cuda.device_count():
        raise StageError(f"params.yaml device: GPU {index} asked for but torch sees {torch.cuda.device_count()}")
    return torch.device("cuda", index)


def distributed(params: dict[str, Any]) -> tuple[int, int, Any]:
    """(rank, world size, device) of this process after `torch_setup`. Under torchrun (WORLD_SIZE > 1) the
    process group is initialised: NCCL on CUDA (one GPU per process: GPU LOCAL_RANK), gloo on the CPU."""
    import torch
    import torch.distributed as dist

    world = int(os.environ.get("WORLD_SIZE", "1"))
    device = torch_setup(params, world, int(os.environ.get("LOCAL_RANK", "0")) if world > 1 else None)
    if world == 1:
        return 0, 1, device
    if device.type == "cuda":
        torch.cuda.set_device(device)
    dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
    return dist.get_rank(), world, device


def intrinsics(params: dict[str, Any]):
    """The render camera: K from params.camera at its reference size, scaled to render.width x height."""
    from pipeline.geometry.camera import Intrinsics

    c, r = params["camera"], params["render"]
    try:
        return Intrinsics(c["ref_width"], c["ref_height"], c["fx"], c["fy"], c["cx"], c["cy"]).scaled(
            int(r["width"]), int(r["height"]))
    except ValueError as e:
        raise StageError(f"params.yaml camera/render: {e}") from None


def scene_settings(render: dict[str, Any]):
    """The Blender scene settings of a `render` params section."""
    from pipeline.render.scene import SceneSettings

    return SceneSettings(mesh=given(render["mesh"]), mesh_scale=float(render["mesh_scale"]),
                         sun_direction=tuple(float(v) for v in render["sun_direction"]),
                         sun_strength=float(render["sun_strength"]), samples=int(render["samples"]),
                         denoiser=str(render["denoiser"]), denoise_quality=str(render["denoise_quality"]),
                         threads=int(render["threads"]))


def check_attack_params(section: dict[str, Any], where: str) -> None:
    """Check an eps list and attack method (`<where>.eps`, `<where>.method`) before any work."""
    from pipeline.attacks.gradient import ATTACKS, check_eps

    eps = section.get("eps")
    if not isinstance(eps, list) or not eps:
        raise StageError(f"params.yaml {where}.eps must be a non-empty list of numbers in (0, 1]")
    for e in eps:
        try:
            check_eps(e)
        except (TypeError, ValueError):
            raise StageError(f"params.yaml {where}.eps: {e!r} is not in (0, 1] (pixels are in [0, 1])") from None
    if section.get("method") not in ATTACKS:
        raise StageError(f"params.yaml {where}.method: unknown attack {section.get('method')!r}; "
                          f"choose one of {', '.join(ATTACKS)}")


def make_attack(attack: dict[str, Any], method: str, seed: int):
    """The attack named `method` with the iterative options of the `attack` params section."""
    import torch

    from pipeline.attacks.gradient import LOSSES, get_attack

    if attack["loss"] not in LOSSES:
        raise StageError(f"params.yaml attack.loss: unknown loss {attack['loss']!r}; choose one of {', '.join(LOSSES)}")
    try:
        return get_attack(method, steps=int(attack["steps"]), step_size=attack["step_size"],
                          random_start=bool(attack["random_start"]), momentum=float(attack["momentum"]),
                          generator=torch.Generator().manual_seed(seed))
    except ValueError as e:
        raise StageError(f"params.yaml attack: {e}") from None


def mockup(p: dict[str, Any]) -> tuple[str | None, float]:
    """(mesh file or None = procedural target, metres per mesh unit) of the mock-up rendered at lab.scale x
    its size, i.e. at the size of the real target. Relative paths are resolved against the working folder."""
    lab, r = p["lab"], p["render"]
    if given(lab["mesh"]) is None:   # the main target, built at 1/scale: rendered at scale x it is the main mesh
        mesh, unit = given(r["mesh"]), float(r["mesh_scale"])
    else:
        mesh, unit = lab["mesh"], float(lab["mesh_scale"]) * float(lab["scale"])
    if mesh is None:
        return None, unit
    path = Path(mesh).resolve()
    if not path.is_file():
        key = "render.mesh" if given(lab["mesh"]) is None else "lab.mesh"
        raise StageError(f"params.yaml {key}: mock-up mesh file {mesh} not found")
    return str(path), unit


def retrain_reason(p: dict[str, Any]) -> str | None:
    """Why the lab stage must train its own models, or None when it may reuse the main ones."""
    lab, r = p["lab"], p["render"]
    if lab["retrain"] == "always":
        return "lab.retrain is always"
    mesh, unit = mockup(p)
    main = None if given(r["mesh"]) is None else str(Path(r["mesh"]).resolve())
    if mesh != main or abs(unit - float(r["mesh_scale"])) > 1e-9 * max(unit, 1.0):
        return (f"the mock-up (lab.mesh {lab['mesh']}, {lab['mesh_scale']:g} m per unit, x{lab['scale']:g}) is not "
                f"the main target (render.mesh {r['mesh']}, {r['mesh_scale']:g} m per unit)")
    return None
