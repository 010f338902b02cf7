"""Fault injection for the engine's tests: worker classes whose process dies on a job, once."""

from __future__ import annotations

import os
from pathlib import Path


def exits_once(worker_cls: type, marker: Path, nth: int = 1) -> type:
    """A subclass of `worker_cls` whose process hard-exits (no clean-up, as a killed machine) on its `nth`
    job (counted per process, after its constructor ran) while the file `marker` does not exist, creating
    it first: exactly one job attempt dies, which the engine must retry on a restarted worker. Defined in a
    function, Ray pickles it by value, so cluster workers need not import this test module."""
    path = str(marker)

    class ExitsOnce(worker_cls):  # type: ignore[misc, valid-type]
        jobs = 0

        def run(self, job):  # noqa: ANN001, ANN202  (the job and result of worker_cls)
            self.jobs += 1
            if self.jobs >= nth and not os.path.exists(path):
                open(path, "w").close()
                os._exit(1)
            return super().run(job)

    return ExitsOnce
