"""The smaller faults of issue 42 (item 10): a key given twice in params.yaml, duplicated eps entries, values a
report claims but did not use, and late or misleading errors; each refused with one line naming what is wrong."""
from __future__ import annotations

import pytest

from pipeline.io.errors import DataError


def test_a_key_given_twice_in_params_yaml_is_refused(tmp_path):
    """The issue's probe: yaml keeps the last of two equal keys silently, so an edit above a forgotten line was lost."""
    from stages.config import params as params_mod

    params_mod.write_params(params_mod.compose("smoke"), tmp_path / "params.yaml")
    text = (tmp_path / "params.yaml").read_text()
    assert params_mod.load(tmp_path / "params.yaml").seed == 0
    (tmp_path / "params.yaml").write_text(text.replace("seed: 0\n", "seed: 0\nseed: 7\n", 1))
    with pytest.raises(DataError, match=r"params.yaml: key 'seed' is given twice \(line \d+\); keep one"):
        params_mod.load(tmp_path / "params.yaml")
