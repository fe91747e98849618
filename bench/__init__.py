"""Benchmark harness: each module has ``run(...) -> dict`` and a ``main()`` for ``python -m``."""
