"""Fixtures shared by several test modules."""

from __future__ import annotations

import os
from typing import Iterator

import pytest
import torch

# Under pytest-xdist (`make test` runs two workers), each worker's in-process torch gets its share of the cores:
# two workers with two threads each on a 2-core machine would fight for them.
if os.environ.get("PYTEST_XDIST_WORKER"):
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    torch.set_num_threads(max(1, cores // int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))))

# The longest files (each a whole smoke pipeline or two, minutes) run first: `make test` hands whole files to its
# workers in this order (--dist loadfile --no-loadscope-reorder), so none of them is left to end the run alone.
FIRST = ("test_e2e_smoke.py", "test_e2e_speed.py")


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Move the tests of FIRST to the front, each file's tests in their own order."""
    items.sort(key=lambda item: item.path.name not in FIRST)


@pytest.fixture(scope="module")
def one_thread() -> Iterator[None]:
    """Torch on one thread for a module: small models train and attack several times faster, above all on a
    busy machine (`pytestmark = pytest.mark.usefixtures("one_thread")`)."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
