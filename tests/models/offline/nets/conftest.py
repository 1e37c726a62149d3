"""One torch thread and a fixed seed for the nets tests.

These nets run many tiny ops (a ConvLSTM step is a 13-row convolution); with two OpenMP
threads on a busy 2-core machine each op can wait ~30 ms at a barrier, 100× its compute.
One thread keeps the suite fast and its timings independent of the machine's load.
"""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import torch


@pytest.fixture(autouse=True, scope="package")
def _one_torch_thread() -> Iterator[None]:
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture(autouse=True)
def _seeded_torch() -> None:
    """Every test draws its weights and inputs from seed 0, whatever ran before it in the process: with pytest-xdist
    the order differs from run to run, and a tiny net (4 channels) drew weights whose ReLUs all died at its last
    position, so no gradient reached the input."""
    torch.manual_seed(0)
