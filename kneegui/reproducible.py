"""The same export on every x86-64 machine with AVX2: numpy's and OpenBLAS's CPU dispatch pinned.

numpy picks its SIMD kernels by the CPU when it is imported. On a CPU with AVX-512 its
``exp``, ``log``, ``power``, ``arccos``, ``arcsin``, ``arctan2``, ``cbrt`` ... (Intel's SVML)
differ in the last bit from its AVX2 kernels for up to half of the arguments (0.04-51 % of
200,000 random ones, by function, on 4 December), and its default ``argsort`` orders ties
otherwise. OpenBLAS picks its kernels (SkylakeX, Haswell, Zen, ...) by the CPU too, and each
sums in its own order. The export is a chain of iterative solvers whose decisions (a line
search step taken or halved, a round ended, a node found inside a bone) follow those bits: the
coarse demo's export at 90 deg wrote one deck with numpy's AVX-512 kernels, another with its
AVX2 ones and a third with OpenBLAS's Haswell kernels in place of its SkylakeX ones (issue 23,
item 6: a variant passed its volume bound on one machine and failed it on another).

:func:`pin_numeric_dispatch` runs when this module is imported (first thing
:mod:`kneegui` does). Before numpy is loaded it
turns numpy's AVX-512 targets off (``NPY_DISABLE_CPU_FEATURES``) and, where the CPU has AVX2
and FMA, sets OpenBLAS's kernels to Haswell (``OPENBLAS_CORETYPE``): every x86-64 machine from
2013 on (x86-64-v3) then runs the same kernels, as Intel MKL's conditional numerical
reproducibility (``MKL_CBWR=AVX2``) does for MKL. Numba-compiled kernels need no pin: compiled
without fast-math they give the same bits for any target CPU (checked on 4 December: Haswell
code and this machine's Zen 4 code wrote the same deck). Values set by the user win;
``KNEEGUI_NATIVE_DISPATCH=1`` turns the pin off (the AVX-512 kernels are a little faster). If
numpy was imported before kneegui the pin cannot act; :func:`dispatch_state` says so, and the
pose report records it (``numerics``). Other CPU families (aarch64) and machines without AVX2
run other kernels and may follow other paths.
"""

from __future__ import annotations

import os
import platform
import sys
from typing import Any

#: numpy's AVX-512 dispatch targets: numpy 2.4's names, then older releases'. A name numpy does
#: not know is ignored; none of them is ever part of the baseline of an x86-64 wheel.
NUMPY_AVX512_TARGETS: tuple[str, ...] = (
    "X86_V4",
    "AVX512F",
    "AVX512CD",
    "AVX512_KNL",
    "AVX512_KNM",
    "AVX512_SKX",
    "AVX512_CLX",
    "AVX512_CNL",
    "AVX512_ICL",
    "AVX512_SPR",
)
#: OpenBLAS kernels used on every CPU with AVX2 and FMA.
OPENBLAS_CORETYPE = "Haswell"
#: Environment variable that turns the pin off (``1``).
OPT_OUT = "KNEEGUI_NATIVE_DISPATCH"
#: The variables the pin sets.
PINNED_VARIABLES: tuple[str, ...] = ("NPY_DISABLE_CPU_FEATURES", "OPENBLAS_CORETYPE")
#: Those the user had set before kneegui was imported (their values win over the pin).
USER_SETTINGS: dict[str, str] = {}


def _cpu_flags() -> set[str]:
    """The CPU's feature flags from /proc/cpuinfo (empty where there is none)."""
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as f:
            for line in f:
                if line.startswith("flags"):
                    return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


def pin_numeric_dispatch() -> bool:
    """Pin numpy's and OpenBLAS's kernels to the AVX2 ones, if numpy is not loaded yet.

    Returns
    -------
    bool
        Whether the environment was set (False: opted out, not x86-64, or too late).
    """
    if os.environ.get(OPT_OUT) == "1" or "numpy" in sys.modules:
        return False
    if platform.machine().lower() not in ("x86_64", "amd64"):
        return False
    USER_SETTINGS.update({k: os.environ[k] for k in PINNED_VARIABLES if k in os.environ})
    os.environ.setdefault("NPY_DISABLE_CPU_FEATURES", " ".join(NUMPY_AVX512_TARGETS))
    if {"avx2", "fma"} <= _cpu_flags():
        os.environ.setdefault("OPENBLAS_CORETYPE", OPENBLAS_CORETYPE)
    return True


def dispatch_state() -> dict[str, Any]:
    """What this process's numerics run on: numpy's active AVX-512 targets, the OpenBLAS core
    asked for, whether the export's kernels are the pinned ones (``pinned``), and the dispatch
    variables the user had set before kneegui (``user_settings``: they win over the pin)."""
    import numpy as np

    try:
        from numpy._core._multiarray_umath import __cpu_dispatch__, __cpu_features__
    except ImportError:  # numpy < 2
        from numpy.core._multiarray_umath import __cpu_dispatch__, __cpu_features__
    avx512 = [t for t in __cpu_dispatch__ if t in NUMPY_AVX512_TARGETS and __cpu_features__.get(t)]
    coretype = os.environ.get("OPENBLAS_CORETYPE")
    x86 = platform.machine().lower() in ("x86_64", "amd64")
    blas_pinned = coretype == OPENBLAS_CORETYPE or not {"avx2", "fma"} <= _cpu_flags()
    return {
        "numpy": np.__version__,
        "numpy_avx512_targets": avx512,
        "openblas_coretype": coretype,
        "pinned": x86 and not avx512 and blas_pinned,
        "user_settings": dict(USER_SETTINGS),
    }


pin_numeric_dispatch()
