"""A stage's outputs move into place together or not at all: `rpod attack` failing at its last write (the
figure) leaves adv.zarr, the metrics and the report of the previous run, never a new adv.zarr beside old
metrics (the issue's "adv.zarr says eps [0.3], attack.json 0.5/0.05")."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
import zarr
from test_faults import run_dir, trained  # noqa: F401  (a finished tiny `rpod train` as the working folder)

from stages.artifacts.paths import ADV, ATTACK_FIGURE, ATTACK_METRICS, ATTACK_REPORT
from stages.config.params import load


def _outputs() -> dict[str, bytes]:
    files = [ATTACK_METRICS, ATTACK_REPORT, ATTACK_FIGURE, *sorted(p for p in ADV.rglob("*") if p.is_file())]
    return {str(p): Path(p).read_bytes() for p in files}


def test_a_failed_attack_keeps_all_previous_outputs(run_dir, monkeypatch):  # noqa: F811
    from stages import attack

    attack.main(load())
    before = _outputs()
    assert json.loads(Path(ATTACK_METRICS).read_text())["eps"].keys() == {"0.5", "0.05"}
    params = yaml.safe_load(Path("params.yaml").read_text())
    params["attack"]["eps"] = [0.3]
    Path("params.yaml").write_text(yaml.safe_dump(params))

    def killed(*args: object) -> None:
        raise RuntimeError("killed while writing the figure")

    monkeypatch.setattr(attack, "save_figure", killed)
    with pytest.raises(RuntimeError, match="killed"):
        attack.main(load())
    assert _outputs() == before
    assert zarr.open_group(str(ADV), mode="r").attrs["eps"] == [0.5, 0.05]
    assert not [p for p in Path("datasets").iterdir() if p.name.startswith(".")]  # no temporary left
    assert not [p for p in Path("reports").rglob(".*")]
