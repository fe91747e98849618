"""The block structure of the demo leg's structured hex grid, and how it scales with size.

The grid is an O-grid stacked along the limb: in each cross-section a core block of ``NU x NV``
cells (rows posterior -> anterior, columns lateral -> medial for the right leg) surrounded by
``NR`` rings of ``P = 2 (NU + NV)`` cells; ``NK`` slabs of cells are stacked from the ankle
(k = 0) to the thigh (k = NK). Every direction is split into named blocks (the notch, a ligament,
the patella rings, the joint slabs ...) whose cell counts scale with one resolution factor, so
the anatomy is the same at every size and region boundaries always fall on grid lines.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

#: Reference in-plane cell size (mm) at resolution factor 1.
REFERENCE_CELL = 10.0
#: Largest ratio of axial cell length to the bone-perimeter spacing in the shafts.
SHAFT_ASPECT = 7.0

# (name, minimum count, width used for scaling in mm, knee fraction start, end)
ROW_BLOCKS = (
    ("pcl", 1, 7.5, 0.00, 0.14),
    ("ugap", 0, 4.5, 0.14, 0.22),
    ("acl", 1, 10.0, 0.22, 0.40),
    ("wall", 2, 22.0, 0.40, 0.80),
    ("ant", 1, 11.0, 0.80, 1.00),
)
COL_BLOCKS = (
    ("lat_rim", 1, 9.0),
    ("lat_out", 1, 11.0),
    ("lat_nw", 1, 11.0),
    ("vgap1", 1, 4.0),
    ("lig", 1, 14.0),
    ("vgap2", 1, 4.0),
    ("med_nw", 1, 11.0),
    ("med_out", 1, 14.0),
    ("med_rim", 1, 9.0),
)
RING_BLOCKS = (("inner", 1, 12.0), ("mid", 1, 20.0), ("outer", 1, 18.0))
# (name, minimum count, nominal z start, end, size factor relative to the in-plane size)
SLAB_BLOCKS = (
    ("calf", 0, -400.0, -140.0, 0.0),  # count from the shaft aspect rule
    ("tibmeta", 6, -140.0, -55.0, 0.85),
    ("tub", 2, -55.0, -40.0, 0.5),
    ("tibcond", 2, -40.0, -24.0, 0.5),
    ("men", 1, -24.0, -19.0, 1.0),
    ("void", 1, -19.0, -14.0, 1e9),  # always one slab
    ("notch1", 3, -14.0, 2.0, 0.45),
    ("notch2", 1, 2.0, 6.0, 0.45),
    ("cond", 2, 6.0, 16.0, 0.45),
    ("pat", 4, 16.0, 45.0, 0.55),
    ("femmeta", 3, 45.0, 90.0, 0.8),
    ("thigh", 0, 90.0, 400.0, 0.0),
)
#: Knee-level column breakpoints (y, mm) of the right femur, lateral -> medial.
KNEE_COL_Y = (-43.0, -34.0, -22.0, -11.0, -7.0, 7.0, 11.0, 22.0, 36.0, 45.0)


@dataclass(frozen=True)
class Blocks:
    """Named consecutive blocks of cells along one grid direction."""

    names: tuple[str, ...]
    counts: tuple[int, ...]

    @property
    def total(self) -> int:
        return int(sum(self.counts))

    def range(self, *names: str) -> tuple[int, int]:
        """Cell index range ``[start, stop)`` covering the given consecutive blocks."""
        starts = np.concatenate([[0], np.cumsum(self.counts)])
        idx = sorted(self.names.index(n) for n in names)
        return int(starts[idx[0]]), int(starts[idx[-1] + 1])

    def start(self, name: str) -> int:
        return self.range(name)[0]

    def stop(self, name: str) -> int:
        return self.range(name)[1]

    def params(self, fractions: tuple[tuple[float, float], ...]) -> np.ndarray:
        """Node parameters ``(total + 1,)``: each block spans its fraction range uniformly."""
        out = [0.0]
        for (lo, hi), n in zip(fractions, self.counts, strict=True):
            if n:
                out.extend(lo + (hi - lo) * (np.arange(1, n + 1) / n))
        arr = np.array(out)
        arr[0] = fractions[0][0]
        return arr


@dataclass(frozen=True)
class Layout:
    """Block counts for one resolution factor.

    Attributes
    ----------
    factor : float
        The resolution factor (1 gives about 20,000 solids).
    rows, cols, rings, slabs : Blocks
        Cell blocks along the core rows (u), core columns (v), rings (r) and slabs (k).
    slab_z : tuple of (float, float)
        Nominal z range of every slab block.
    """

    factor: float
    rows: Blocks
    cols: Blocks
    rings: Blocks
    slabs: Blocks
    slab_z: tuple[tuple[float, float], ...]
    shaft_aspect: float = SHAFT_ASPECT

    @property
    def nu(self) -> int:
        return self.rows.total

    @property
    def nv(self) -> int:
        return self.cols.total

    @property
    def nr(self) -> int:
        return self.rings.total

    @property
    def nk(self) -> int:
        return self.slabs.total

    @property
    def perimeter(self) -> int:
        return 2 * (self.nu + self.nv)

    @property
    def n_cell_slots(self) -> int:
        """Cells of the full grid, void included."""
        return self.nk * (self.nu * self.nv + self.perimeter * self.nr)

    def row_fractions(self) -> tuple[tuple[float, float], ...]:
        return tuple((lo, hi) for _, _, _, lo, hi in ROW_BLOCKS)

    def col_fractions(self) -> tuple[tuple[float, float], ...]:
        y = np.array(KNEE_COL_Y)
        f = (y - y[0]) / (y[-1] - y[0])
        return tuple((float(a), float(b)) for a, b in itertools.pairwise(f))

    def nominal_z(self) -> np.ndarray:
        """Nominal z of every node layer, ``(nk + 1,)``."""
        out = [self.slab_z[0][0]]
        for (z0, z1), n in zip(self.slab_z, self.slabs.counts, strict=True):
            out.extend(z0 + (z1 - z0) * np.arange(1, n + 1) / n)
        return np.array(out)


def _count(minimum: int, width: float, factor: float, size: float = REFERENCE_CELL) -> int:
    return max(minimum, round(factor * width / size))


def make_layout(factor: float, shaft_aspect: float = SHAFT_ASPECT) -> Layout:
    """Block counts for a resolution factor (1 -> about 20,000 solid elements).

    The shaft slabs are sized from the bone perimeter spacing so that the cells next to the
    bones keep an aspect ratio of at most about ``shaft_aspect`` (default
    :data:`SHAFT_ASPECT`; the tetrahedral variants use a smaller one, since a tet cut from a long
    cell is a sliver).
    """
    rows = Blocks(
        tuple(b[0] for b in ROW_BLOCKS), tuple(_count(b[1], b[2], factor) for b in ROW_BLOCKS)
    )
    cols = Blocks(
        tuple(b[0] for b in COL_BLOCKS), tuple(_count(b[1], b[2], factor) for b in COL_BLOCKS)
    )
    rings = Blocks(
        tuple(b[0] for b in RING_BLOCKS), tuple(_count(b[1], b[2], factor) for b in RING_BLOCKS)
    )
    perimeter = 2 * (rows.total + cols.total)
    # smallest bone perimeter in a shaft: the tibia, 2 pi 12 mm, drawn as a bulged square
    spacing = 2 * np.pi * 12.0 * 0.97 / perimeter
    shaft_len = shaft_aspect * spacing
    knee_size = REFERENCE_CELL / factor
    counts = []
    for name, minimum, z0, z1, rel in SLAB_BLOCKS:
        length = z1 - z0
        if name == "void":
            counts.append(1)
        elif rel == 0.0:
            counts.append(max(2, int(np.ceil(length / shaft_len))))
        else:
            by_size = int(np.ceil(length / (rel * knee_size) - 0.25))
            by_aspect = int(np.ceil(length / shaft_len))
            counts.append(max(minimum, by_size, by_aspect))
    slabs = Blocks(tuple(b[0] for b in SLAB_BLOCKS), tuple(counts))
    return Layout(
        factor, rows, cols, rings, slabs, tuple((b[2], b[3]) for b in SLAB_BLOCKS), shaft_aspect
    )
