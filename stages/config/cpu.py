"""The CPU instruction set torch's kernels may use, pinned so that a result does not depend on the machine.

torch picks its kernels by CPU when it loads: ATen's vectorised ops (`ATEN_CPU_CAPABILITY`), oneDNN's
convolutions (`ONEDNN_MAX_CPU_ISA`) and MKL's BLAS (`MKL_CBWR`, conditional numerical reproducibility)
each take the widest instructions the CPU has. AVX-512 and AVX2 kernels add in another order, so the
same seed trained another pose model on a machine without AVX-512 (issue 27). numpy does the same: its
OpenBLAS picks a kernel set by CPU (`OPENBLAS_CORETYPE`: Zen and Haswell run the same AVX2 kernels,
bit for bit; SkylakeX runs AVX-512 ones) and its own loops dispatch AVX-512 paths where the CPU has
them (`NPY_DISABLE_CPU_FEATURES`): attitude means and detector thresholds then differed in the 16th
digit between an AVX-512 and an AVX2 machine. `rpod` therefore caps all five at AVX2, which every
x86-64 CPU of the last decade has, before numpy and torch are imported (`pin_cpu_isa`, called first
thing by stages/__init__.py, so by every `rpod` command, script and test that imports `stages`); what the
torch cap costs and buys is measured by benchmarks/cpu_isa.py (reports/benchmarks.md, "## CPU
instruction set").

`RPOD_CPU_ISA` picks the cap: `avx2` (default) or `native` (no cap: torch's own choice, the fastest).
A variable the user set themselves wins over the cap. Other architectures (arm64) are left alone.
Blender's Cycles needs no pin: its CPU kernels are SSE4.2 and AVX2 only and it takes AVX2 wherever
the CPU has it. Only the standard library here: this module runs before anything heavy is imported.
"""

from __future__ import annotations

import os
import platform
import sys
from collections.abc import MutableMapping

ISA_ENV = "RPOD_CPU_ISA"
DEFAULT = "avx2"
# numpy 1.26's dispatched AVX-512 targets (`numpy.core._multiarray_umath.__cpu_dispatch__`); disabling one
# the CPU lacks is allowed, one numpy does not dispatch is an error at import
NUMPY_AVX512 = "AVX512F AVX512CD AVX512_KNL AVX512_KNM AVX512_SKX AVX512_CLX AVX512_CNL AVX512_ICL"
# cap -> the variables it sets (when the user has not); "native" sets none
PINS: dict[str, dict[str, str]] = {
    "avx2": {
        "ATEN_CPU_CAPABILITY": "avx2",
        "ONEDNN_MAX_CPU_ISA": "AVX2",
        "MKL_CBWR": "AVX2",
        "OPENBLAS_CORETYPE": "Haswell",
        "NPY_DISABLE_CPU_FEATURES": NUMPY_AVX512,
    },
    "native": {},
}
X86 = ("x86_64", "amd64", "i686", "x86")


def pin_cpu_isa(environ: MutableMapping[str, str] = os.environ, machine: str | None = None) -> str:
    """Set the cap's variables in `environ` where they are unset; returns the cap applied ("native" off
    x86). A bad RPOD_CPU_ISA is a ValueError naming it (the CLI prints it as one line)."""
    cap = environ.get(ISA_ENV, DEFAULT).strip().lower()
    if cap not in PINS:
        raise ValueError(f"${ISA_ENV}={environ[ISA_ENV]!r}: choose one of {', '.join(PINS)}")
    if (machine or platform.machine()).lower() not in X86:
        return "native"
    for key, value in PINS[cap].items():
        environ.setdefault(key, value)
    return cap


def isa_label(environ: MutableMapping[str, str] = os.environ) -> str:
    """What the kernels ran with, for reports/metrics/*.json and scripts/variance.py: "avx2" when every
    variable of that cap holds its value, "native" when none is set, else the variables as set."""
    names = sorted({k for pins in PINS.values() for k in pins})
    given = {k: environ[k] for k in names if k in environ}
    for cap, pins in PINS.items():
        if given == pins:
            return cap
    return ",".join(f"{k}={v}" for k, v in given.items())


def isa_stamp() -> dict[str, str | None]:
    """The `cpu_isa` stamp of every reports/metrics/*.json: the cap (`isa_label`) and the kernels torch's
    ATen runs ("AVX2", "AVX512", ...; None in a process that never loaded torch)."""
    torch = sys.modules.get("torch")
    kernels = torch.backends.cpu.get_cpu_capability() if torch is not None else None
    return {"cap": isa_label(), "kernels": kernels}
