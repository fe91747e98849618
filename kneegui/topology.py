"""Element topology: the one place that states node order, edges, faces and corners.

Every other module (quality, mesh improvement, relaxation, the demo generator, the viewer)
imports these tables and helpers; where a consumer needs another order it derives it from the
tables here by a stated rule instead of keeping a second literal.

Node ordering conventions (LS-DYNA's, which VTK shares except for the wedge):

- ``hex8``: 0-3 bottom face counter-clockwise seen from the top, 4-7 the top face above them
  (reference coordinates :data:`HEX_REFERENCE_COORDS`).
- ``wedge6``: triangle 0,1,2 counter-clockwise seen from triangle 3,4,5; edges i -> i+3.
  (VTK's wedge lists the base triangle clockwise: :mod:`kneegui.io.vtu` swaps 1<->2 and 4<->5.)
- ``pyramid5``: quad base 0-3 counter-clockwise seen from apex 4.
- ``tet4``: triangle 0,1,2 counter-clockwise seen from apex 3. ``tet10``: 4 corners + 6 mid-edge
  nodes (0-1, 1-2, 2-0, 0-3, 1-3, 2-3).
- ``quad4``/``tri3`` shells, ``beam2`` and ``discrete`` two-node elements.

A positive element therefore has ``((x1 - x0) x (x2 - x0)) . (x_top - x0) > 0``.

Global cell index: the position of an element in the concatenation of a model's blocks in
their mapping order (:func:`block_offsets`); :mod:`kneegui.io.vtu`, the viewer and
``QualityResult.concatenated`` all use it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kneegui.errors import raise_if_cancelled


class ElementBlock(Protocol):
    """What these tables read of an element block (:class:`kneegui.model.ElementBlock` is one;
    the model sits above this module and imports it, so it is named by shape, not imported)."""

    conn: NDArray[np.int64]
    part_ids: NDArray[np.int64]


# ---------------------------------------------------------------------- element types
#: Nodes per element, for every element type the model holds.
NODES_PER_ELEMENT: dict[str, int] = {
    "hex8": 8,
    "wedge6": 6,
    "pyramid5": 5,
    "tet4": 4,
    "tet10": 10,
    "quad4": 4,
    "tri3": 3,
    "beam2": 2,
    "discrete": 2,
}
ELEMENT_TYPES: tuple[str, ...] = tuple(NODES_PER_ELEMENT)
SOLID_TYPES: tuple[str, ...] = ("hex8", "wedge6", "pyramid5", "tet4", "tet10")
SHELL_TYPES: tuple[str, ...] = ("quad4", "tri3")
LINE_TYPES: tuple[str, ...] = ("beam2", "discrete")
#: Corner (vertex) nodes of each solid or shell type: the leading connectivity columns that
#: carry the geometry (a 10-node tet's first 4; its mid-edge nodes follow).
CORNER_NODES: dict[str, int] = {
    "hex8": 8,
    "wedge6": 6,
    "pyramid5": 5,
    "tet4": 4,
    "tet10": 4,
    "quad4": 4,
    "tri3": 3,
}

# ---------------------------------------------------------------------- tables
#: Reference coordinates (xi, eta, zeta) in {0, 1} of the hex's nodes: the node order itself.
HEX_REFERENCE_COORDS: tuple[tuple[int, int, int], ...] = (
    (0, 0, 0),
    (1, 0, 0),
    (1, 1, 0),
    (0, 1, 0),
    (0, 0, 1),
    (1, 0, 1),
    (1, 1, 1),
    (0, 1, 1),
)

_HEX_EDGES = (
    (0, 1),
    (1, 2),
    (2, 3),
    (3, 0),
    (4, 5),
    (5, 6),
    (6, 7),
    (7, 4),
    (0, 4),
    (1, 5),
    (2, 6),
    (3, 7),
)
#: Edges of each element type as pairs of local node numbers (this module's node order); a
#: 10-node tet's edges run through its mid-edge nodes.
ELEMENT_EDGES: dict[str, tuple[tuple[int, int], ...]] = {
    "hex8": _HEX_EDGES,
    "wedge6": ((0, 1), (1, 2), (2, 0), (3, 4), (4, 5), (5, 3), (0, 3), (1, 4), (2, 5)),
    "pyramid5": ((0, 1), (1, 2), (2, 3), (3, 0), (0, 4), (1, 4), (2, 4), (3, 4)),
    "tet4": ((0, 1), (1, 2), (2, 0), (0, 3), (1, 3), (2, 3)),
    "tet10": (
        (0, 4),
        (4, 1),
        (1, 5),
        (5, 2),
        (2, 6),
        (6, 0),
        (0, 7),
        (7, 3),
        (1, 8),
        (8, 3),
        (2, 9),
        (9, 3),
    ),
    "quad4": ((0, 1), (1, 2), (2, 3), (3, 0)),
    "tri3": ((0, 1), (1, 2), (2, 0)),
    "beam2": ((0, 1),),
    "discrete": ((0, 1),),
}
#: Faces of each solid type as local node cycles, outward for a positive element (a 10-node
#: tet's faces by their corner nodes).
SOLID_FACES: dict[str, tuple[tuple[int, ...], ...]] = {
    "hex8": ((0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)),
    "wedge6": ((0, 2, 1), (3, 4, 5), (0, 1, 4, 3), (1, 2, 5, 4), (2, 0, 3, 5)),
    "pyramid5": ((0, 3, 2, 1), (0, 1, 4), (1, 2, 4), (2, 3, 4), (3, 0, 4)),
    "tet4": ((0, 2, 1), (0, 1, 3), (1, 2, 3), (2, 0, 3)),
    "tet10": ((0, 2, 1), (0, 1, 3), (1, 2, 3), (2, 0, 3)),
}
#: Faces of every solid and shell type (a shell is its own single face, in node order).
ELEMENT_FACES: dict[str, tuple[tuple[int, ...], ...]] = {
    **SOLID_FACES,
    "quad4": ((0, 1, 2, 3),),
    "tri3": ((0, 1, 2),),
}
#: Corners of each element type as (corner, a, b, c): the corner determinant is
#: ``det(p[a] - p[i], p[b] - p[i], p[c] - p[i])`` (positive for a valid element); for quad shells
#: ``c`` is -1 and the element's mean normal takes its place. A 10-node tet uses its corners.
CORNER_TRIPLES: dict[str, tuple[tuple[int, int, int, int], ...]] = {
    "hex8": (
        (0, 1, 3, 4),
        (1, 2, 0, 5),
        (2, 3, 1, 6),
        (3, 0, 2, 7),
        (4, 7, 5, 0),
        (5, 4, 6, 1),
        (6, 5, 7, 2),
        (7, 6, 4, 3),
    ),
    "wedge6": ((0, 1, 2, 3), (1, 2, 0, 4), (2, 0, 1, 5), (3, 5, 4, 0), (4, 3, 5, 1), (5, 4, 3, 2)),
    "pyramid5": ((0, 1, 3, 4), (1, 2, 0, 4), (2, 3, 1, 4), (3, 0, 2, 4)),
    "tet4": ((0, 1, 2, 3),),
    "tet10": ((0, 1, 2, 3),),
    "quad4": ((0, 1, 3, -1), (1, 2, 0, -1), (2, 3, 1, -1), (3, 0, 2, -1)),
}

#: Node order that turns a mirrored element positive again (a model mirrored through a plane has
#: every element inside out): each base face walked the other way round, corresponding top nodes
#: likewise, apexes kept. VTK lists the wedge's triangles this way round (:mod:`kneegui.io.vtu`).
MIRRORED_NODE_ORDER: dict[str, tuple[int, ...]] = {
    "hex8": (0, 3, 2, 1, 4, 7, 6, 5),
    "wedge6": (0, 2, 1, 3, 5, 4),
    "pyramid5": (0, 3, 2, 1, 4),
    "tet4": (0, 2, 1, 3),
    "tet10": (0, 2, 1, 3, 6, 5, 4, 7, 9, 8),
    "quad4": (0, 3, 2, 1),
    "tri3": (0, 2, 1),
}


def hex_faces_parametric() -> tuple[tuple[int, int, int, int], ...]:
    """The hex's faces (:data:`SOLID_FACES` order) as parametric cycles instead of outward ones.

    Rule: each face starts at its node of smallest reference coordinates and runs first along
    the earlier of its two parametric directions (xi before eta before zeta): ``origin,
    +first, +first+second, +second``. Opposite faces then run parallel. The quality kernels
    measure unsigned face metrics on these cycles; their rounding depends on where a cycle
    starts, so the rule is fixed here once.
    """
    ref = np.array(HEX_REFERENCE_COORDS)
    index = {tuple(r): i for i, r in enumerate(HEX_REFERENCE_COORDS)}
    out = []
    for face in SOLID_FACES["hex8"]:
        pts = ref[list(face)]
        fixed = int(np.flatnonzero(np.all(pts == pts[0], axis=0))[0])
        first, second = (d for d in range(3) if d != fixed)
        origin = np.zeros(3, dtype=int)
        origin[fixed] = pts[0, fixed]
        step1, step2 = np.eye(3, dtype=int)[first], np.eye(3, dtype=int)[second]
        cycle = (origin, origin + step1, origin + step1 + step2, origin + step2)
        out.append(tuple(index[tuple(int(v) for v in c)] for c in cycle))
    return tuple(out)


# ---------------------------------------------------------------------- block bookkeeping
def block_offsets(blocks: Mapping[str, ElementBlock]) -> dict[str, int]:
    """Global cell index of the first element of each block (blocks in their mapping order)."""
    offsets, start = {}, 0
    for etype, block in blocks.items():
        offsets[etype] = start
        start += len(block)
    return offsets


def _part_rows(block: ElementBlock, wanted: NDArray[np.int64] | None) -> NDArray[np.int64]:
    if wanted is None:
        return np.arange(len(block), dtype=np.int64)
    return np.flatnonzero(np.isin(block.part_ids, wanted))


def _wanted(part_ids: Iterable[int] | None) -> NDArray[np.int64] | None:
    if part_ids is None:
        return None
    return np.array(sorted(set(int(p) for p in part_ids)), dtype=np.int64)


# ---------------------------------------------------------------------- index arrays
def sorted_unique(values: ArrayLike) -> NDArray:
    """``np.unique(values)`` for integer (or bool) arrays, by sorting.

    The same array as ``np.unique`` (flattened, sorted, duplicates removed). NumPy 2.3 and
    newer find the unique values of a plain ``np.unique`` call with a hash table, which on
    large index arrays is 2-14x slower than sorting (4M node indices: 1.6 s against 0.26 s);
    the repositioner's and the relaxation's node and edge sets are such arrays. Other dtypes
    go to ``np.unique`` (it treats NaN specially).
    """
    a = np.asarray(values)
    if a.dtype.kind not in "iub":
        return np.unique(a)
    s = np.sort(a, axis=None)
    if len(s) < 2:
        return s
    keep = np.empty(len(s), dtype=bool)
    keep[0] = True
    np.not_equal(s[1:], s[:-1], out=keep[1:])
    return s[keep]


# ---------------------------------------------------------------------- faces and corners
def row_groups(rows: NDArray[np.int64]) -> NDArray[np.int64]:
    """For each row of a 2-D integer array, an index shared by exactly the equal rows
    (0, 1, ... in the rows' lexicographic order; via lexsort)."""
    if len(rows) == 0:
        return np.zeros(0, dtype=np.int64)
    order = np.lexsort(rows.T[::-1])
    srt = rows[order]
    new_group = np.ones(len(rows), dtype=bool)
    new_group[1:] = np.any(srt[1:] != srt[:-1], axis=1)
    out = np.empty(len(rows), dtype=np.int64)
    out[order] = np.cumsum(new_group) - 1
    return out


def row_multiplicity(rows: NDArray[np.int64]) -> NDArray[np.int64]:
    """How many times each row of a 2-D integer array occurs in it (via lexsort)."""
    group = row_groups(rows)
    return np.bincount(group)[group] if len(group) else group


def _used_once(faces: NDArray[np.int64]) -> NDArray[np.bool_]:
    """Mask of the faces (rows of node indices) whose node set occurs only once.

    Sorted rows are packed two node indices per int64 key (node indices below 2**31), so the
    lexicographic sort runs over two keys instead of three or four columns.
    """
    key = np.sort(faces, axis=1)
    if len(key) == 0 or int(key[:, -1].max()) >= 2**31:
        return row_multiplicity(key) == 1
    packed = [(key[:, j] << 32) | key[:, j + 1] for j in range(0, key.shape[1] - 1, 2)]
    if key.shape[1] % 2:
        packed.append(key[:, -1])
    return row_multiplicity(np.stack(packed, axis=1)) == 1


def boundary_faces(
    blocks: Mapping[str, ElementBlock],
    part_ids: Iterable[int] | None = None,
    *,
    with_cells: bool = False,
) -> tuple[NDArray[np.int64], ...]:
    """Faces of the solid mesh that belong to exactly one solid element.

    Parameters
    ----------
    blocks : mapping of str to ElementBlock
        Element blocks; only solid types are used (taken in :data:`SOLID_TYPES` order).
    part_ids : iterable of int, optional
        Restrict the solid mesh to these parts taken together (default: every solid).
    with_cells : bool
        Also return the global cell index (:func:`block_offsets`) of each face's element.

    Returns
    -------
    quads : (q, 4) ndarray of int64
        Boundary quad faces (node indices), outward for positive elements.
    tris : (t, 3) ndarray of int64
        Boundary triangles (tet10 faces by their corner nodes).
    quad_cells, tri_cells : (q,), (t,) ndarray of int64
        Only with ``with_cells``: the element each face belongs to.
    """
    wanted = _wanted(part_ids)
    offsets = block_offsets(blocks)
    chunks: dict[int, list[tuple[NDArray[np.int64], NDArray[np.int64]]]] = {4: [], 3: []}
    for etype in SOLID_TYPES:
        block = blocks.get(etype)
        if block is None or len(block) == 0:
            continue
        rows = _part_rows(block, wanted)
        conn = block.conn[rows]
        for face in SOLID_FACES[etype]:
            chunks[len(face)].append((conn[:, list(face)], offsets[etype] + rows))
    faces, cells = {}, {}
    for k, parts in chunks.items():
        if not parts:
            faces[k] = np.zeros((0, k), dtype=np.int64)
            cells[k] = np.zeros(0, dtype=np.int64)
            continue
        f = np.concatenate([p[0] for p in parts]).astype(np.int64, copy=False)
        once = _used_once(f)
        faces[k] = f[once]
        cells[k] = np.concatenate([p[1] for p in parts]).astype(np.int64)[once]
    if with_cells:
        return faces[4], faces[3], cells[4], cells[3]
    return faces[4], faces[3]


#: :func:`corner_tetrahedra` fills its array this many elements at a time, asking ``cancel``
#: before each chunk.
CORNER_ELEMENT_CHUNK = 1 << 18


def corner_tetrahedra(
    blocks: Mapping[str, ElementBlock],
    masks: Mapping[str, NDArray[np.bool_]] | None = None,
    cancel: Callable[[], bool] | None = None,
) -> NDArray[np.int64]:
    """(C, 4) node indices of the corner tetrahedra of the solid elements.

    Each row is a :data:`CORNER_TRIPLES` entry ``(corner, a, b, c)`` of one element, so its
    signed volume is the element's corner determinant / 6; elements in :data:`SOLID_TYPES`
    order, corners in table order.

    Parameters
    ----------
    blocks : mapping of element type to ElementBlock
    masks : mapping of element type to (m,) bool, optional
        Which elements of each block to take (default: all).
    cancel : callable, optional
        Asked before every :data:`CORNER_ELEMENT_CHUNK` elements (a whole-body model's knee:
        millions of corners, over a second); True raises :class:`~kneegui.errors.Cancelled`.
    """
    picked = []
    for etype in SOLID_TYPES:
        block = blocks.get(etype)
        if block is None or len(block.conn) == 0:
            continue
        conn = block.conn if masks is None else block.conn[masks[etype]]
        picked.append((conn, np.array(CORNER_TRIPLES[etype])))
    out = np.empty((sum(len(c) * len(t) for c, t in picked), 4), dtype=np.int64)
    row = 0
    for conn, table in picked:
        for start in range(0, len(conn), CORNER_ELEMENT_CHUNK):
            raise_if_cancelled(cancel, "cancelled while listing the corner tetrahedra")
            corners = conn[start : start + CORNER_ELEMENT_CHUNK][:, table].reshape(-1, 4)
            out[row : row + len(corners)] = corners
            row += len(corners)
    return out


# ---------------------------------------------------------------------- degenerate solids
def _wedge_patterns() -> list[tuple[tuple[int, int], tuple[int, int], tuple[int, ...]]]:
    """For each way an 8-node hex collapses into a wedge, the two merged edges and the wedge order.

    A wedge stored as a hex has two opposite edges of one face merged (that face becomes a line).
    The two faces that contain exactly one merged edge are the wedge's triangles; their third
    direction gives the i -> i+3 edges. Orientation follows the hex: a positive hex gives a
    positive wedge.
    """
    # the hex's outward faces with the bottom one reversed: face 0 is then counter-clockwise
    # seen from inside, the sense in which the node order lists the bottom face
    faces = [SOLID_FACES["hex8"][0][::-1], *SOLID_FACES["hex8"][1:]]
    faces[0] = faces[0][-1:] + faces[0][:-1]  # start at node 0: (0, 1, 2, 3)
    opposite = {0: 1, 1: 0, 2: 4, 4: 2, 3: 5, 5: 3}
    edges = set(_HEX_EDGES)
    edges |= {(b, a) for a, b in edges}
    patterns = []
    for fi, face in enumerate(faces):
        for k in (0, 1):
            e1 = (face[k], face[k + 1])
            e2 = (face[(k + 2) % 4], face[(k + 3) % 4])
            # triangle faces: the two other faces containing e1 and e2 respectively
            tri_faces = []
            for e in (e1, e2):
                for fj, f in enumerate(faces):
                    if fj != fi and e[0] in f and e[1] in f:
                        tri_faces.append(fj)
            fa, fb = tri_faces
            if opposite[fa] != fb:  # pragma: no cover - a fact of the hex table
                raise AssertionError("hex face table is inconsistent")
            # map each node of face fa to its neighbour on face fb along the connecting edges
            fa_nodes, fb_nodes = faces[fa], faces[fb]
            partner = {a: next(b for b in fb_nodes if (a, b) in edges) for a in fa_nodes}
            # walk face fa counter-clockwise seen from fb: faces 1..5 are listed outward and
            # need reversal, face 0 is already listed that way
            ring = list(fa_nodes)
            if fa != 0:
                ring = ring[::-1]
            merged = e1 if e1[0] in ring and e1[1] in ring else e2
            # drop the second node of the merged edge (it equals the first)
            drop = merged[1]
            tri = [n for n in ring if n != drop]
            order = tuple(tri + [partner[n] for n in tri])
            patterns.append((e1, e2, order))
    return patterns


_WEDGE_PATTERNS = _wedge_patterns()


def split_degenerate_solids(
    conn8: NDArray[np.int64],
) -> dict[str, tuple[NDArray[np.int64], NDArray[np.int64]]]:
    """Recognise 8-node solids with repeated nodes as wedges, pyramids or tetrahedra.

    Parameters
    ----------
    conn8 : (M, 8) ndarray of int
        Node ids or indices of 8-node solids as written in the deck.

    Returns
    -------
    dict
        ``etype -> (rows, conn)``: for each recognised type, the row numbers into ``conn8`` and
        the rebuilt connectivity in this module's node order. Rows that fit no pattern (for
        example an element collapsed to a plane) stay ``hex8`` so that quality checks flag them.
    """
    conn8 = np.asarray(conn8)
    m = len(conn8)
    # every degenerate pattern merges at least one hex edge: count distinct nodes only there
    merged = np.zeros(m, dtype=bool)
    for a, b in _HEX_EDGES:
        merged |= conn8[:, a] == conn8[:, b]
    n_distinct = np.full(m, 8, dtype=np.int64)
    rows_merged = np.flatnonzero(merged)
    if len(rows_merged):
        srt = np.sort(conn8[rows_merged], axis=1)
        n_distinct[rows_merged] = 1 + np.count_nonzero(srt[:, 1:] != srt[:, :-1], axis=1)
    result: dict[str, tuple[NDArray[np.int64], NDArray[np.int64]]] = {}
    assigned = n_distinct == 8
    # wedges: exactly 6 distinct nodes and a known merged-edge pattern
    cand = np.flatnonzero(n_distinct == 6)
    wedge_rows, wedge_conn = [], []
    if len(cand):
        c = conn8[cand]
        done = np.zeros(len(cand), dtype=bool)
        for e1, e2, order in _WEDGE_PATTERNS:
            hit = ~done & (c[:, e1[0]] == c[:, e1[1]]) & (c[:, e2[0]] == c[:, e2[1]])
            if hit.any():
                wedge_rows.append(cand[hit])
                wedge_conn.append(c[hit][:, list(order)])
                done |= hit
    if wedge_rows:
        rows = np.concatenate(wedge_rows)
        result["wedge6"] = (rows, np.concatenate(wedge_conn))
        assigned[rows] = True
    # pyramids: 5 distinct, top face fully merged to one apex (pattern 1,2,3,4,5,5,5,5)
    cand = np.flatnonzero(n_distinct == 5)
    if len(cand):
        c = conn8[cand]
        top_merged = (c[:, 4] == c[:, 5]) & (c[:, 5] == c[:, 6]) & (c[:, 6] == c[:, 7])
        if top_merged.any():
            rows = cand[top_merged]
            result["pyramid5"] = (rows, conn8[rows][:, [0, 1, 2, 3, 4]])
            assigned[rows] = True
    # tetrahedra: 4 distinct nodes, in order of first appearance (1,2,3,3,4,4,4,4 -> 1,2,3,4)
    cand = np.flatnonzero(n_distinct == 4)
    if len(cand):
        c = conn8[cand]
        first = np.ones_like(c, dtype=bool)
        for j in range(1, 8):
            first[:, j] = np.all(c[:, :j] != c[:, j : j + 1], axis=1)
        tets = c[first].reshape(-1, 4)
        result["tet4"] = (cand, tets)
        assigned[cand] = True
    rest = np.flatnonzero(assigned & (n_distinct == 8))
    rest = np.concatenate([rest, np.flatnonzero(~assigned)])
    rest.sort()
    if len(rest) or m == 0:
        result["hex8"] = (rest, conn8[rest])
    return result
