"""A demo deck made larger far from the knee: issue 24's memory target is for a 2M-node deck.

``python -m bench.far_block SRC_DIR OUT_DIR`` copies the demo in ``SRC_DIR`` (``demo_leg.k`` and
``demo_leg.setup.json`` from ``kneegui demo``) to ``OUT_DIR`` and adds, through an
``*INCLUDE``, a block of hexahedra 3 m from the knee in a part the setup does not name (so it
stays where it is, as the rest of a whole-body model does). The demo generator's largest leg has
1,764,929 nodes; with the default 63 nodes a side the block adds 250,047 nodes and 238,328
hexahedra, 2,014,976 nodes in all. ``python -m bench.export_bench OUT_DIR`` then measures it.
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

#: Ids of the block's part, first node and first element (above any the demo uses).
PART_ID, FIRST_ID = 990_001, 90_000_001
#: Edge length of the block's cubes and its distance from the knee (mm).
SPACING_MM, OFFSET_MM = 5.0, 3000.0


def far_block(nodes_per_side: int) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """The block's node coordinates (N, 3) and its hexahedra (E, 8), as indices into them."""
    n = int(nodes_per_side)
    if n < 2:
        raise ValueError(f"the block needs at least 2 nodes a side, got {n}")
    g = np.arange(n) * SPACING_MM
    x, y, z = np.meshgrid(g, g, g, indexing="ij")
    xyz = np.stack([x.ravel() + OFFSET_MM, y.ravel(), z.ravel()], axis=1)
    c = np.arange(n**3).reshape(n, n, n)[:-1, :-1, :-1].ravel()
    dx, dy = n * n, n
    hexes = np.stack(
        [c, c + dx, c + dx + dy, c + dy, c + 1, c + dx + 1, c + dx + dy + 1, c + dy + 1], axis=1
    )
    return xyz, hexes


def far_block_deck(nodes_per_side: int) -> str:
    """The block as an LS-DYNA include: ``*PART``, ``*NODE`` and ``*ELEMENT_SOLID`` cards."""
    xyz, hexes = far_block(nodes_per_side)
    ids = FIRST_ID + np.arange(len(xyz))
    lines = ["*KEYWORD", "*PART", "far-away tissue (stays where it is)"]
    lines += [f"{PART_ID:10d}{1:10d}{1:10d}", "*NODE"]
    rows = zip(ids.tolist(), xyz.tolist(), strict=True)
    lines += [f"{i:8d}{a:16.6f}{b:16.6f}{c:16.6f}" for i, (a, b, c) in rows]
    lines.append("*ELEMENT_SOLID")
    node_ids = ids[hexes]
    for k, row in enumerate(node_ids.tolist()):
        lines.append(f"{FIRST_ID + k:8d}{PART_ID:8d}" + "".join(f"{v:8d}" for v in row))
    lines.append("*END")
    return "\n".join(lines) + "\n"


def add_far_block(src: Path, out: Path, nodes_per_side: int = 63) -> Path:
    """Copy the demo in ``src`` to ``out`` with the far block included; returns the deck."""
    deck = (src / "demo_leg.k").read_text(encoding="latin-1")
    body = deck.rstrip()
    if not body.endswith("*END"):
        raise ValueError(f"{src / 'demo_leg.k'} does not end with *END")
    out.mkdir(parents=True, exist_ok=True)
    (out / "far_block.k").write_text(far_block_deck(nodes_per_side), encoding="latin-1")
    main = out / "demo_leg.k"
    main.write_text(body[: -len("*END")] + "*INCLUDE\nfar_block.k\n*END\n", encoding="latin-1")
    shutil.copyfile(src / "demo_leg.setup.json", out / "demo_leg.setup.json")
    return main


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.far_block", description=__doc__)
    parser.add_argument("src", type=Path, help="folder from `kneegui demo`")
    parser.add_argument("out", type=Path, help="folder to write the larger deck to")
    parser.add_argument("--nodes-per-side", type=int, default=63)
    args = parser.parse_args(argv)
    deck = add_far_block(args.src, args.out, args.nodes_per_side)
    print(deck)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
