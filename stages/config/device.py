"""The torch side of params: CPU threads, the device (`threads`, `device`) and torchrun's process group."""

from __future__ import annotations

import os
from typing import Any

from stages.config.schema import Params
from stages.errors import StageError


def torch_setup(params: Params, processes: int = 1, local_rank: int | None = None) -> Any:
    """A torch stage's start: torch's CPU threads from `threads` (null: every core, shared among `processes`
    torchrun processes), then the device (`torch_device`: a missing CUDA GPU stops the stage before any work)."""
    import torch

    n = params.threads
    torch.set_num_threads(max(1, (os.cpu_count() or 1) // processes) if n is None else n)
    return torch_device(params, local_rank)


def torch_device(params: Params, local_rank: int | None = None) -> Any:
    """The torch.device of every torch stage, from the `device` param (checked by stages.config.schema):
    auto = the CUDA GPU when torch sees one, else the CPU. Under torchrun, a CUDA process takes GPU
    `local_rank`. StageError when CUDA is asked for and torch sees no GPU (or fewer than the index)."""
    import torch

    value = params.device
    cuda = torch.cuda.is_available()
    if value == "cpu" or (value == "auto" and not cuda):
        return torch.device("cpu")
    if not cuda:
        raise StageError(
            f"params.yaml device: {value!r} asks for a CUDA GPU but torch {torch.__version__} sees none; "
            f"set device: auto or cpu"
        )
    index = local_rank if local_rank is not None else int(value.partition(":")[2] or 0)
    if index >= torch.cuda.device_count():
        raise StageError(f"params.yaml device: GPU {index} asked for but torch sees {torch.cuda.device_count()}")
    return torch.device("cuda", index)


def distributed(params: Params) -> tuple[int, int, Any]:
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
