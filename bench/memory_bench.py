"""Peak memory of reading a 2,000,000-node deck (issue: reliability, large inputs).

``python -m bench.memory_bench`` writes bench/results/memory.json and prints the figures. The deck
is a structured grid (126^3 nodes, hexes + boundary quads) written by ``write_model``; the read
runs in a fresh subprocess whose peak resident set size (``ru_maxrss``) is reported next to the
deck's size on disk.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path

from bench.io_bench import structured_model
from bench.machine import machine_description

ROOT = Path(__file__).resolve().parent.parent

_CHILD = r"""
import json, resource, sys, time
from kneegui.io.lsdyna import read_deck
t = time.perf_counter()
m = read_deck(sys.argv[1])
print(json.dumps({"read_s": time.perf_counter() - t, "nodes": m.n_nodes,
                  "elements": m.n_elements,
                  "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def run(n: int = 126) -> dict:
    """Write an n^3-node deck and read it in a subprocess; return size, time and peak RSS."""
    from kneegui.io.lsdyna import write_model

    with tempfile.TemporaryDirectory() as tmp:
        deck = Path(tmp) / "big.k"
        write_model(structured_model(n), deck)
        size_mb = deck.stat().st_size / 1e6
        proc = subprocess.run(
            [sys.executable, "-c", _CHILD, str(deck)],
            capture_output=True,
            text=True,
            check=True,
            cwd=ROOT,
        )
    res = json.loads(proc.stdout)
    res["deck_mb"] = round(size_mb, 1)
    res["rss_per_deck_mb"] = round(res["peak_rss_mb"] / size_mb, 2)
    return res


def main() -> int:
    res = run()
    out = {"result": res, "machine": machine_description()}
    (ROOT / "bench" / "results").mkdir(parents=True, exist_ok=True)
    (ROOT / "bench" / "results" / "memory.json").write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps(res, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
