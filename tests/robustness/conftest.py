"""Print how many fuzz cases the robustness suite ran (quoted in docs/reliability.md)."""

from __future__ import annotations

import sys


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    # every fuzz module keeps a FUZZ_COUNTS dict: the reader's and the whole path's
    counts: dict[str, int] = {}
    for name, module in list(sys.modules.items()):
        if name.rsplit(".", 1)[-1].endswith("_fuzz") and hasattr(module, "FUZZ_COUNTS"):
            for key, value in module.FUZZ_COUNTS.items():
                counts[key] = counts.get(key, 0) + value
    if counts:
        total = sum(counts.values())
        parts = ", ".join(f"{k}: {v}" for k, v in sorted(counts.items()))
        terminalreporter.write_line(f"fuzz cases run: {total} ({parts})")
