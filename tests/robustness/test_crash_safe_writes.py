"""Killing the process mid-export leaves either the old deck or the complete new one."""

from __future__ import annotations

import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from kneegui.io.lsdyna import read_deck, write_model
from kneegui.model import ElementBlock, Model, Part

WRITER = r"""
import sys
import numpy as np
from kneegui.io.lsdyna import read_deck, write_deck
src, out = sys.argv[1], sys.argv[2]
model = read_deck(src)
k = 0
print("ready", flush=True)
while True:
    k += 1
    write_deck(model.with_coords(model.coords + k), out, allow_overwrite_input=False)
"""


def grid_model(n: int) -> Model:
    g = np.arange(n, dtype=float)
    x, y, z = np.meshgrid(g, g, g, indexing="ij")
    coords = np.column_stack([x.ravel(), y.ravel(), z.ravel()])
    idx = np.arange(n**3).reshape(n, n, n)
    c = idx[:-1, :-1, :-1].ravel()
    hexes = np.column_stack(
        [c, c + n * n, c + n * n + n, c + n, c + 1, c + n * n + 1, c + n * n + n + 1, c + n + 1]
    )
    block = ElementBlock("hex8", np.arange(1, len(hexes) + 1), np.ones(len(hexes)), hexes)
    return Model(np.arange(1, n**3 + 1), coords, {"hex8": block}, {1: Part(1, "grid")})


@pytest.mark.parametrize("delay", [0.15, 0.4, 0.9])
def test_sigkill_mid_export_leaves_old_or_complete_file(tmp_path, delay):
    src = write_model(grid_model(40), tmp_path / "src.k")
    out = tmp_path / "out" / "posed.k"
    out.parent.mkdir()
    old = b"*KEYWORD\n$ the previous export\n*END\n"
    out.write_bytes(old)
    proc = subprocess.Popen(
        [sys.executable, "-c", WRITER, str(src), str(out)], stdout=subprocess.PIPE, text=True
    )
    assert proc.stdout.readline().strip() == "ready"
    time.sleep(delay)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    data = out.read_bytes()
    if data == old:
        return
    model = read_deck(out)  # complete: it reads, has every node, ends with *END
    assert model.n_nodes == 40**3
    assert data.rstrip().endswith(b"*END")
    shift = model.coords[0, 0]  # every node moved by the same whole number k
    base = read_deck(src).coords
    assert shift == round(shift) and shift >= 1
    np.testing.assert_allclose(model.coords, base + shift)
