"""Hydra plugin module that DVC imports before `dvc exp run -S` composes params.yaml (.dvc/config:
`hydra.plugins_path = stages/config`): every composition in that process is checked against the params
schema as `rpod params` checks it (stages.config.compose.checked), so an unknown name or a bad value stops
`dvc exp run` at once with the stages' one-line message instead of Hydra's hint or a later stage error; an
accepted one is said in one line on stderr (the profile and the overrides), also under `--dry`.

Hydra (pinned, 1.3.8) has no public hook after composition, so this wraps
`ConfigLoaderImpl.load_configuration`; tests/test_dvc_ux.py runs DVC's own composition through it.
"""

from __future__ import annotations

import sys
from typing import Any

from dvc.exceptions import InvalidArgumentError
from hydra._internal.config_loader_impl import ConfigLoaderImpl
from omegaconf import DictConfig, OmegaConf, open_dict

from stages.config.compose import checked
from stages.config.params import CONF_STAMP, conf_sha
from stages.config.sections import ParamsError

_load = ConfigLoaderImpl.load_configuration


def _checked_load(
    self: ConfigLoaderImpl, config_name: str | None, overrides: list[str], *args: Any, **kwargs: Any
) -> DictConfig:
    """Hydra's composition, refused with DVC's one-line error unless the params schema accepts it."""

    def compose(some: list[str]) -> dict[str, Any]:
        cfg = _load(self, config_name, some, *args, **kwargs)
        with open_dict(cfg):
            cfg.pop("hydra", None)
        return OmegaConf.to_container(cfg, resolve=True)  # type: ignore[return-value]

    try:
        composed = checked(compose, list(overrides))
    except ParamsError as e:
        raise InvalidArgumentError(str(e)) from None
    print(
        f"params.yaml <- profile {composed.get('profile_name')!r}"  # what the run (or --dry) will use
        + (f" with {' '.join(overrides)}" if overrides else ""),
        file=sys.stderr,
    )
    cfg = _load(self, config_name, overrides, *args, **kwargs)
    sha = conf_sha()
    if sha is not None:  # the conf/ it was composed from, as `rpod params` stamps it (stages check it)
        with open_dict(cfg):
            cfg[CONF_STAMP] = sha
    return cfg


ConfigLoaderImpl.load_configuration = _checked_load  # type: ignore[method-assign]
