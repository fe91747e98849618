"""Print how many fuzz cases the robustness suite ran (quoted in docs/reliability.md)."""

from __future__ import annotations

import sys


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    module = sys.modules.get("test_deck_fuzz")
    counts = getattr(module, "FUZZ_COUNTS", None)
    if not counts:
        for name, mod in sys.modules.items():
            if name.endswith("test_deck_fuzz") and hasattr(mod, "FUZZ_COUNTS"):
                counts = mod.FUZZ_COUNTS
                break
    if counts:
        total = sum(counts.values())
        parts = ", ".join(f"{k}: {v}" for k, v in sorted(counts.items()))
        terminalreporter.write_line(f"fuzz cases run: {total} ({parts})")
