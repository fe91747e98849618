"""Fixed-part parallelism for the optimisers' compiled kernels, the same result on any machine.

A kernel's sum over elements is split into :data:`PARTS` fixed ranges, each summed into its own
buffer on up to as many threads (the kernels are compiled with ``nogil``), and the parts are
then added in order. The split depends only on the problem, never on the machine's core count,
so the last bits of every sum, and with them every decision the solvers take, are the same on
one core as on eight.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

import numpy as np
from numpy.typing import NDArray

#: Number of fixed parts a kernel's elements are split into.
PARTS = 4
#: Below this many elements a kernel runs as one part (threads would cost more than they save).
PARALLEL_MIN_ELEMENTS = 2000

T = TypeVar("T")
_POOL: list[ThreadPoolExecutor] = []
_POOL_LOCK = threading.Lock()


def _pool() -> ThreadPoolExecutor:
    with _POOL_LOCK:
        if not _POOL:
            threads = max(1, min(os.cpu_count() or 1, PARTS))
            _POOL.append(ThreadPoolExecutor(threads, thread_name_prefix="kneegui-kernel"))
        return _POOL[0]


def part_bounds(total: int, parts: int = PARTS) -> NDArray[np.int64]:
    """``parts + 1`` increasing bounds splitting ``range(total)`` into near-equal ranges."""
    return np.linspace(0, total, parts + 1).round().astype(np.int64)


def run_parts(work: Callable[[int], T], parts: int = PARTS) -> list[T]:
    """``[work(0), ..., work(parts - 1)]``, run on the shared pool (in any order, on any thread);
    the caller combines the results in index order."""
    return list(_pool().map(work, range(parts)))
