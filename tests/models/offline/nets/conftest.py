"""One torch thread for the nets tests.

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
