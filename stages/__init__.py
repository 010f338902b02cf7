"""`rpod` commands, one per DVC stage. A missing input's error names the dvc.yaml stage that writes it."""

# First, before numpy and torch load (pipeline.io below imports numpy): their CPU kernels capped at AVX2
# (stages/config/cpu.py). A bad $RPOD_CPU_ISA is left to stages/cli.py, which reports it in one line.
from stages.config.cpu import pin_cpu_isa

try:
    pin_cpu_isa()
except ValueError:
    pass

from pipeline.io.errors import set_missing_hint  # noqa: E402
from stages.artifacts.dvc import make_hint  # noqa: E402

set_missing_hint(make_hint)
