"""`rpod` commands, one per DVC stage. A missing input's error names the dvc.yaml stage that writes it."""

from pipeline.io.errors import set_missing_hint
from stages.artifacts.dvc import make_hint

set_missing_hint(make_hint)
