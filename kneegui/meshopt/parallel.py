"""Fixed-part parallelism for the optimisers' compiled kernels, the same result on any machine.

A kernel's sum over elements is split into :data:`PARTS` fixed ranges, each summed into its own
buffer, and the parts are then added in order. The parts run in one compiled ``prange`` loop
(numba's thread pool: a few microseconds to start, where a Python thread pool took about 90 per
call, thousands of calls per export); the split depends only on the problem, never on the
machine's core count or the number of threads, so the last bits of every sum, and with them
every decision the solvers take, are the same on one core as on eight.
"""

from __future__ import annotations

import threading

import numpy as np
from numpy.typing import NDArray

#: Number of fixed parts a kernel's elements are split into.
PARTS = 4
#: Below this many elements a kernel runs as one part (threads would cost more than they save).
PARALLEL_MIN_ELEMENTS = 2000
#: Held while a ``parallel=True`` kernel runs: numba's built-in thread pool (its fallback where
#: no OpenMP or TBB runtime is found) must not be entered by two threads at once.
PARALLEL_KERNEL_LOCK = threading.Lock()


def part_bounds(total: int, parts: int = PARTS) -> NDArray[np.int64]:
    """``parts + 1`` increasing bounds splitting ``range(total)`` into near-equal ranges."""
    return np.linspace(0, total, parts + 1).round().astype(np.int64)


def add_in_order(values: NDArray[np.float64]) -> float:
    """The parts' values added in index order (the sum does not depend on the thread count)."""
    total = 0.0
    for value in values:
        total += float(value)
    return total
