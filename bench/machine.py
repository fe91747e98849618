"""Describe the machine a benchmark ran on."""

from __future__ import annotations

from kneegui.reproducible import dispatch_state

import os
import platform

import numpy as np
import scipy


def machine_description() -> dict[str, object]:
    """CPU model, core count, memory, Python and library versions, and the numerical kernels
    in use (:func:`kneegui.reproducible.dispatch_state`)."""
    cpu = platform.processor() or "unknown"
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    mem_gb = 0.0
    try:
        with open("/proc/meminfo") as fh:
            mem_gb = int(fh.readline().split()[1]) / 1024**2
    except (OSError, ValueError, IndexError):
        pass
    return {
        "cpu": cpu,
        "cores": os.cpu_count() or 0,
        "memory_gb": round(mem_gb, 1),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "os": platform.platform(),
        "numerics": dispatch_state(),
    }
