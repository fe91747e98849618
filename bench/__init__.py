"""Benchmark harness: each module has ``run(...) -> dict`` and a ``main()`` for ``python -m``."""

import kneegui.reproducible  # noqa: F401  (before numpy: the same kernels on every machine)
