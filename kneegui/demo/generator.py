"""Assemble the demo leg: parts, elements, landmarks and the joint setup, and write it out."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from kneegui.demo import grid as g
from kneegui.demo import tetmesh
from kneegui.demo.design import DemoDesign
from kneegui.demo.layout import SHAFT_ASPECT, Layout, make_layout
from kneegui.demo.repair import QualityTargets, repair_quality
from kneegui.demo.sliding import detach_soft_tissue
from kneegui.demo.welded import weld_joint
from kneegui.errors import KneeguiError
from kneegui.io.atomic import atomic_write_text
from kneegui.model import ElementBlock, Model, NodeSet, Part
from kneegui.topology import MIRRORED_NODE_ORDER

DECK_NAME = "demo_leg.k"
SETUP_NAME = "demo_leg.setup.json"
MIN_ELEMENTS, MAX_ELEMENTS = 1_000, 5_000_000
SIDES = ("right", "left")
ELEMENT_TYPES = ("hex", "tet", "mixed", "tet10")
JOINTS = ("sliding", "welded")
UNITS = {"mm": 1.0, "m": 1e-3}
FLEXION_RANGE_DEG = (0.0, 20.0)
#: Shaft cell aspect of the variants with tetrahedra: a tet cut from a long cell is a sliver.
TET_SHAFT_ASPECT = 3.0
#: Repair passes at most (each grows its patch around the elements still failing).
REPAIR_ROUNDS = 3


@dataclass(frozen=True)
class Variant:
    """How the demo leg is meshed (docs/demo-leg.md, "Variants").

    Attributes
    ----------
    element_type : {"hex", "tet", "mixed", "tet10"}
        ``hex``: every solid a hexahedron (the default); ``tet``: a conforming BCC-lattice
        tetrahedral mesh (:mod:`kneegui.demo.tetmesh`); ``mixed``: tetrahedral flesh, hexahedral
        bones, ligaments and menisci; ``tet10``: ``tet`` with 10-node tets.
    joint : {"sliding", "welded"}
        ``sliding``: soft tissue on coincident nodes of the bones around the knee (the default,
        :mod:`kneegui.demo.sliding`); ``welded``: one volume of flesh sharing nodes with both bones
        and filling the joint gap (:mod:`kneegui.demo.welded`).
    unit : {"mm", "m"}
        Length unit of the deck and of the setup's coordinates.
    """

    element_type: str = "hex"
    joint: str = "sliding"
    unit: str = "mm"

    def __post_init__(self) -> None:
        for name, value, allowed in (
            ("element type", self.element_type, ELEMENT_TYPES),
            ("joint", self.joint, JOINTS),
            ("unit", self.unit, tuple(UNITS)),
        ):
            if value not in allowed:
                raise KneeguiError(f"{name} must be one of {', '.join(allowed)}, got {value!r}")

    @property
    def has_tets(self) -> bool:
        return self.element_type != "hex"

    @property
    def shaft_aspect(self) -> float:
        return TET_SHAFT_ASPECT if self.has_tets else SHAFT_ASPECT


@dataclass(frozen=True)
class PartSpec:
    """One part of the demo: id, title stem, role, element kind and what it is made of."""

    pid: int
    stem: str
    role: str
    kind: str  # "solid" or a shell kind: cortical, skin, capsule, tendon
    label: int  # grid label of the solids (or the bone a cortical shell covers)
    secid: int
    region: str = ""  # flesh: thigh / knee / calf


PARTS: tuple[PartSpec, ...] = (
    PartSpec(700001, "LX-Bone-Femur-Cortical", "femur", "cortical", g.FEMUR, 2),
    PartSpec(700002, "LX-Bone-Femur-Trabecular", "femur", "solid", g.FEMUR, 1),
    PartSpec(700003, "LX-Bone-Tibia-Cortical", "tibia", "cortical", g.TIBIA, 2),
    PartSpec(700004, "LX-Bone-Tibia-Trabecular", "tibia", "solid", g.TIBIA, 1),
    PartSpec(700005, "LX-Bone-Fibula-Cortical", "fibula", "cortical", g.FIBULA, 2),
    PartSpec(700006, "LX-Bone-Fibula-Trabecular", "fibula", "solid", g.FIBULA, 1),
    PartSpec(700007, "LX-Bone-Patella-Cortical", "patella", "cortical", g.PATELLA, 2),
    PartSpec(700008, "LX-Bone-Patella-Trabecular", "patella", "solid", g.PATELLA, 1),
    PartSpec(700011, "LX-Flesh-Thigh", "flesh", "solid", g.FLESH, 1, "thigh"),
    PartSpec(700012, "LX-Flesh-Knee", "flesh", "solid", g.FLESH, 1, "knee"),
    PartSpec(700013, "LX-Flesh-Calf", "flesh", "solid", g.FLESH, 1, "calf"),
    PartSpec(700020, "LX-Skin", "skin", "skin", -1, 3),
    PartSpec(700031, "LX-Lig-ACL", "ligament", "solid", g.ACL, 1),
    PartSpec(700032, "LX-Lig-PCL", "ligament", "solid", g.PCL, 1),
    PartSpec(700033, "LX-Lig-MCL", "ligament", "solid", g.MCL, 1),
    PartSpec(700034, "LX-Lig-LCL", "ligament", "solid", g.LCL, 1),
    PartSpec(700041, "LX-Meniscus-Medial", "meniscus", "solid", g.MENISCUS_MED, 1),
    PartSpec(700042, "LX-Meniscus-Lateral", "meniscus", "solid", g.MENISCUS_LAT, 1),
    PartSpec(700051, "LX-Tendon-Patellar", "tendon", "tendon", -1, 4),
    PartSpec(700061, "LX-Capsule", "capsule", "capsule", -1, 4),
)
ROLE_ORDER = (
    "femur",
    "tibia",
    "fibula",
    "patella",
    "skin",
    "flesh",
    "ligament",
    "meniscus",
    "tendon",
    "capsule",
    "fixed",
)
#: Flesh regions by nominal height of the slab (straight pose, mm).
KNEE_FLESH_Z = (-60.0, 60.0)


@dataclass(frozen=True)
class DemoLeg:
    """The generated demo leg.

    Attributes
    ----------
    model : Model
        Nodes, solids (hexahedra, or tetrahedra for the tet variants) and shells (quads, or
        triangles on faces cut into tets), one ``*PART`` per tissue (ids 7xxxxx).
    setup : dict
        Roles and landmarks in the ``kneegui-setup`` format (version 1).
    design : DemoDesign
        The designed anatomy the tests measure against (radii, flexion, dimensions).
    layout : Layout
        Grid block counts (resolution).
    side : str
        ``"right"`` or ``"left"``.
    stats : dict
        Element counts and the resolution factor; for a variant also ``variant`` and
        ``element_types``, and with tetrahedra ``tet_cells``, ``inverted_tets`` and the worst
        tet measures (``tet_min_dihedral_deg``, ``tet_max_dihedral_deg``, ``tet_min_collapse``).
    """

    model: Model
    setup: dict[str, Any]
    design: DemoDesign
    layout: Layout
    side: str
    stats: dict[str, Any] = field(default_factory=dict)


def count_solids(layout: Layout) -> int:
    """Number of solid elements a layout produces (cheap: labels only)."""
    ix = g._Index(layout)
    labels, _ = g._labels(layout, ix, layout.nominal_z())
    return int(np.count_nonzero(labels != g.VOID))


def quality_problems(model: Model) -> list[str]:
    """Which default quality bounds (``resources/quality_thresholds.csv``, role ``*``: corner
    Jacobian, aspect ratio, warpage; and no inverted element) the model breaks; [] if none."""
    from kneegui.quality import compute_quality, load_thresholds

    limits = load_thresholds().for_role(None)
    q = compute_quality(model.coords, model.blocks)
    problems = []
    if q.n_inverted:
        problems.append(f"{q.n_inverted} inverted elements")
    for metric, name in (
        ("jacobian", "jacobian_corner"),
        ("aspect", "aspect"),
        ("warpage", "warpage"),
    ):
        t = limits[metric]
        values = np.concatenate([eq.metric(name) for eq in q.by_type.values()])
        bad = int(np.count_nonzero(t.worse_than(values, t.fail)))
        if bad:
            problems.append(f"{bad} elements with {metric} worse than {t.fail}")
    return problems


def candidate_layouts(
    elements: int, tries: int = 9, shaft_aspect: float = SHAFT_ASPECT
) -> list[Layout]:
    """Layouts near ``elements`` solids: the nearest first, then its neighbours in resolution
    (alternately finer and coarser), each with a different block structure."""
    first = layout_for(elements, shaft_aspect)
    out, seen = [first], {_signature(first)}
    for m in range(1, 40):
        for sign in (1, -1):
            lay = make_layout(first.factor * 1.03 ** (sign * m), shaft_aspect)
            sig = _signature(lay)
            if sig in seen:
                continue
            seen.add(sig)
            if abs(count_solids(lay) - elements) <= 0.3 * elements:
                out.append(lay)
            if len(out) >= tries:
                return out
    return out


def _signature(lay: Layout) -> tuple:
    return (lay.rows.counts, lay.cols.counts, lay.rings.counts, lay.slabs.counts)


def layout_for(elements: int, shaft_aspect: float = SHAFT_ASPECT) -> Layout:
    """The layout whose solid (grid cell) count is nearest ``elements`` (bisection on the
    resolution)."""
    lo, hi = 0.05, 20.0
    best: tuple[int, float, Layout] | None = None
    for _ in range(40):
        mid = np.sqrt(lo * hi)
        lay = make_layout(mid, shaft_aspect)
        n = count_solids(lay)
        cand = (abs(n - elements), mid, lay)
        if best is None or cand[:2] < best[:2]:
            best = cand
        if n < elements:
            lo = mid
        else:
            hi = mid
        if hi / lo < 1.0005:
            break
    assert best is not None
    return best[2]


def generate_demo_leg(
    elements: int = 20_000,
    side: str = "right",
    design: DemoDesign | None = None,
    *,
    element_type: str = "hex",
    joint: str = "sliding",
    initial_flexion: float | None = None,
    unit: str = "mm",
) -> DemoLeg:
    """Generate the built-in demo lower extremity (pelvis and foot excluded).

    Parameters
    ----------
    elements : int
        Wanted number of solid (hex) elements; the nearest the block structure allows is built.
        The coarsest model (any request up to about 7,300) has about 7,200 solids, the fewest with
        every structure and the quality bounds; 20,000 is the default (the paper's model had
        about 19,000); over 1,000,000 works for benchmarks. Every returned mesh meets the
        default quality bounds (no inverted element, corner Jacobian >= 0.3, aspect <= 10,
        warpage <= 30 degrees, ``resources/quality_thresholds.csv``): a resolution that misses
        them as built is repaired (:func:`build_demo_leg`), and if that fails too the next
        resolution within 30 % of the request is tried.
    side : {"right", "left"}
        The leg. A left leg is the right one mirrored in y, with element node orders flipped so
        that no element is inverted.
    design : DemoDesign, optional
        Anatomy; the default is the documented 50th-percentile male knee.
    element_type : {"hex", "tet", "mixed", "tet10"}
        See :class:`Variant`. With tetrahedra, ``elements`` counts the grid cells; each tet cell
        becomes 12 tetrahedra (docs/demo-leg.md).
    joint : {"sliding", "welded"}
        See :class:`Variant`.
    initial_flexion : float, optional
        Knee angle (degrees, 0 - 20) the leg is built at; the default is the design's (9).
    unit : {"mm", "m"}
        Length unit of the model and of the setup's coordinates.

    Returns
    -------
    DemoLeg

    Raises
    ------
    KneeguiError
        Unknown side or variant, an element count outside 1,000 - 5,000,000, a flexion outside
        0 - 20 degrees, or no resolution near the request meets the quality bounds (not seen with
        the default design at any size).
    """
    if side not in SIDES:
        raise KneeguiError(f"side must be 'right' or 'left', got {side!r}")
    if not (MIN_ELEMENTS <= int(elements) <= MAX_ELEMENTS):
        raise KneeguiError(
            f"elements must be between {MIN_ELEMENTS:,} and {MAX_ELEMENTS:,}, got {elements}"
        )
    variant = Variant(element_type, joint, unit)
    design = design or DemoDesign()
    if initial_flexion is not None:
        lo, hi = FLEXION_RANGE_DEG
        if not (lo <= float(initial_flexion) <= hi):
            raise KneeguiError(
                f"initial flexion must be between {lo:g} and {hi:g} degrees, got {initial_flexion}"
            )
        design = replace(design, initial_flexion_deg=float(initial_flexion))
    tried = []
    for layout in candidate_layouts(int(elements), shaft_aspect=variant.shaft_aspect):
        leg, problems = build_demo_leg(layout, design, side, variant)
        if not problems:
            return leg
        tried.append(f"{leg.stats['solids']:,} solids: {'; '.join(problems)}")
    raise KneeguiError(
        f"no demo leg near {int(elements):,} solids meets the quality bounds ("
        + " | ".join(tried)
        + ")"
    )


def build_demo_leg(
    layout: Layout, design: DemoDesign, side: str = "right", variant: Variant | None = None
) -> tuple[DemoLeg, list[str]]:
    """Build the demo leg of one layout, repairing it if it misses the quality bounds.

    The grid is built and measured (:func:`quality_problems`); if an element misses a bound,
    the free flesh nodes around it are moved (:func:`repair_grid`) and the mesh is measured
    again, up to :data:`REPAIR_ROUNDS` times. A mesh that met the bounds as built is returned
    untouched.

    Parameters
    ----------
    layout : Layout
        Block counts (:func:`kneegui.demo.layout.make_layout`).
    design : DemoDesign
        Anatomy.
    side : {"right", "left"}
    variant : Variant, optional
        Meshing variant (default: hexahedra, sliding joint, mm). The grid is measured and
        repaired as hexahedra; a variant with tetrahedra is then cut into tets
        (:mod:`kneegui.demo.tetmesh`) and must have no inverted tet.

    Returns
    -------
    leg : DemoLeg
        ``stats["repaired_nodes"]`` says how many nodes the repair moved (0 if none).
    problems : list of str
        The bounds the final mesh still misses ([] when it meets them all).
    """
    variant = variant or Variant()
    grid = g.build_grid(design, layout)
    if variant.joint == "welded":
        grid = weld_joint(grid)
    as_hex = replace(variant, element_type="hex", unit="mm")
    leg = _assemble(grid, design, side, as_hex)
    problems = quality_problems(leg.model)
    moved = 0
    for _ in range(REPAIR_ROUNDS):
        if not problems:
            break
        grid, moved_now = repair_grid(grid)
        if not moved_now:
            break
        moved += moved_now
        leg = _assemble(grid, design, side, as_hex)
        problems = quality_problems(leg.model)
    if variant != as_hex and not problems:
        leg = _assemble(grid, design, side, variant)
        inverted = leg.stats.get("inverted_tets", 0)
        if inverted:
            problems = [f"{inverted} inverted tetrahedra"]
    leg.stats["repaired_nodes"] = moved
    if problems:
        leg.stats["quality_problems"] = problems
    return leg, problems


def repair_grid(grid: g.Grid) -> tuple[g.Grid, int]:
    """Move free flesh nodes (:func:`kneegui.demo.grid.free_flesh_nodes`) around the elements
    that miss the quality bounds (:mod:`kneegui.demo.repair`); returns the new grid and how many
    nodes moved."""
    hexes = grid.cell_conn[grid.cell_label > g.VOID]
    quads = np.concatenate([conn for conn, _ in grid.shells.values()])
    coords = repair_quality(
        grid.coords,
        hexes,
        quads,
        g.free_flesh_nodes(grid),
        QualityTargets.from_thresholds(),
        guards=grid.cell_conn[grid.cell_label == g.VOID],
    )
    moved = int(np.count_nonzero(np.any(coords != grid.coords, axis=1)))
    return replace(grid, coords=coords), moved


def _assemble(
    grid: g.Grid, design: DemoDesign, side: str, variant: Variant | None = None
) -> DemoLeg:
    variant = variant or Variant()
    suffix = "R" if side == "right" else "L"
    labels = grid.cell_label
    solid_pid = np.zeros(len(labels), dtype=np.int64)
    shell_conn, shell_pid = [], []
    for spec in PARTS:
        if spec.kind == "solid":
            mask = labels == spec.label
            if spec.region:
                z = grid.cell_z
                lo, hi = KNEE_FLESH_Z
                region = np.where(z > hi, "thigh", np.where(z < lo, "calf", "knee"))
                mask &= region == spec.region
            solid_pid[mask] = spec.pid
        else:
            conn, owner = grid.shells[spec.kind]
            if spec.kind == "cortical":
                conn = conn[owner == spec.label]
            shell_conn.append(conn)
            shell_pid.append(np.full(len(conn), spec.pid, dtype=np.int64))
    keep = solid_pid > 0
    order = np.lexsort((np.flatnonzero(keep), solid_pid[keep]))
    solid_rows = np.flatnonzero(keep)[order]
    hex_conn = grid.cell_conn[solid_rows]
    hex_pid = solid_pid[solid_rows]
    quad_conn = np.concatenate(shell_conn)
    quad_pid = np.concatenate(shell_pid)
    order = np.argsort(quad_pid, kind="stable")
    quad_conn, quad_pid = quad_conn[order], quad_pid[order]
    grid_coords = grid.coords
    role_pids = {r: [s.pid for s in PARTS if s.role == r] for r in {s.role for s in PARTS}}
    tet_conn = np.zeros((0, 4), dtype=np.int64)
    tet_pid = np.zeros(0, dtype=np.int64)
    tri_conn = np.zeros((0, 3), dtype=np.int64)
    tri_pid = np.zeros(0, dtype=np.int64)
    tet_stats: dict[str, Any] = {}
    if variant.has_tets:
        (
            grid_coords,
            hex_conn,
            hex_pid,
            tet_conn,
            tet_pid,
            quad_conn,
            quad_pid,
            tri_conn,
            tri_pid,
            tet_stats,
        ) = _cut_tets(
            grid_coords,
            hex_conn,
            hex_pid,
            quad_conn,
            quad_pid,
            variant,
            role_pids["flesh"],
            _pinned_nodes(grid),
        )

    blocks_in = [
        (hex_conn, hex_pid),
        (tet_conn, tet_pid),
        (quad_conn, quad_pid),
        (tri_conn, tri_pid),
    ]
    if variant.joint == "sliding":
        # soft tissue slides on the bones around the joint (see kneegui.demo.sliding)
        sliding = (
            role_pids["flesh"] + role_pids["capsule"] + role_pids["skin"] + role_pids["tendon"]
        )
        for bones, soft, attached in (
            # the menisci slide under the femur but sit on the tibia; the flesh slides on both
            (role_pids["femur"], sliding + role_pids["meniscus"], []),
            (role_pids["tibia"] + role_pids["fibula"], sliding, []),
        ):
            grid_coords, conns = detach_soft_tissue(
                grid_coords, blocks_in, bones, soft, attached_pids=attached
            )
            blocks_in = [(c, pid) for c, (_, pid) in zip(conns, blocks_in, strict=True)]
    (hex_conn, _), (tet_conn, _), (quad_conn, _), (tri_conn, _) = blocks_in
    tet_type = "tet4"
    if variant.element_type == "tet10":
        grid_coords, tet_conn = tetmesh.add_mid_edge_nodes(grid_coords, tet_conn)
        tet_type = "tet10"

    used = np.unique(np.concatenate([c.ravel() for c in (hex_conn, tet_conn, quad_conn, tri_conn)]))
    remap = np.full(len(grid_coords), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    coords = grid_coords[used].copy()
    hex_conn, tet_conn = remap[hex_conn], remap[tet_conn]
    quad_conn, tri_conn = remap[quad_conn], remap[tri_conn]
    if side == "left":
        coords[:, 1] *= -1.0
        hex_conn = hex_conn[:, list(MIRRORED_NODE_ORDER["hex8"])]
        tet_conn = tet_conn[:, list(MIRRORED_NODE_ORDER[tet_type])]
        quad_conn = quad_conn[:, list(MIRRORED_NODE_ORDER["quad4"])]
        tri_conn = tri_conn[:, list(MIRRORED_NODE_ORDER["tri3"])]
    scale = UNITS[variant.unit]
    if scale != 1.0:
        coords *= scale
    node_ids = np.arange(1, len(used) + 1, dtype=np.int64)
    n_hex, n_tet = len(hex_conn), len(tet_conn)
    n_solid = n_hex + n_tet
    shell_start = 10 ** len(str(n_solid)) + 1
    blocks = {}
    if n_hex:
        blocks["hex8"] = ElementBlock("hex8", np.arange(1, n_hex + 1), hex_pid, hex_conn)
    if n_tet:
        blocks[tet_type] = ElementBlock(
            tet_type, np.arange(n_hex + 1, n_solid + 1), tet_pid, tet_conn
        )
    if len(quad_conn) or not len(tri_conn):
        blocks["quad4"] = ElementBlock(
            "quad4", np.arange(shell_start, shell_start + len(quad_conn)), quad_pid, quad_conn
        )
    if len(tri_conn):
        tri_start = shell_start + len(quad_conn)
        blocks["tri3"] = ElementBlock(
            "tri3", np.arange(tri_start, tri_start + len(tri_conn)), tri_pid, tri_conn
        )
    parts = {s.pid: Part(s.pid, f"{s.stem}-{suffix}", s.secid, s.pid - 700000) for s in PARTS}
    lat = remap[grid.landmarks["lateral_condyle"]]
    med = remap[grid.landmarks["medial_condyle"]]
    node_sets = {
        7001: NodeSet(7001, f"LX-Landmark-Condyle-Lateral-{suffix}", lat),
        7002: NodeSet(7002, f"LX-Landmark-Condyle-Medial-{suffix}", med),
    }
    model = Model(node_ids, coords, blocks, parts, node_sets)
    setup = _setup(
        design, side, node_ids, lat, med, remap[grid.landmarks["medial_plateau"]], variant.unit
    )
    counts = model.element_counts()
    stats = {
        "resolution_factor": grid.layout.factor,
        "solids": n_solid,
        "shells": len(quad_conn) + len(tri_conn),
        "nodes": len(used),
        "grid": {
            "rows": grid.layout.nu,
            "columns": grid.layout.nv,
            "rings": grid.layout.nr,
            "slabs": grid.layout.nk,
        },
        "elements_per_part": {parts[p].title: sum(c.values()) for p, c in sorted(counts.items())},
    }
    if variant != Variant():
        stats["variant"] = {
            "element_type": variant.element_type,
            "joint": variant.joint,
            "unit": variant.unit,
            "initial_flexion_deg": design.initial_flexion_deg,
        }
        stats["element_types"] = {t: len(b) for t, b in blocks.items()}
    stats.update(tet_stats)
    return DemoLeg(model, setup, design, grid.layout, side, stats)


def _pinned_nodes(grid: g.Grid) -> NDArray[np.bool_]:
    """Lattice nodes the tet improvement must not move: on the two cuts or on a cavity cell."""
    ix = g._Index(grid.layout)
    layer = np.arange(len(grid.coords)) // ix.per_layer
    pinned = (layer == 0) | (layer == grid.layout.nk)
    pinned[grid.cell_conn[grid.cell_label == g.VOID].ravel()] = True
    return pinned


def _cut_tets(coords, hex_conn, hex_pid, quad_conn, quad_pid, variant, flesh_pids, pinned):
    """Cut the tet cells of the variant into a BCC tet mesh (:mod:`kneegui.demo.tetmesh`), move
    the cell centres and the grid nodes inside one part (not on a shell, a part boundary, a cut or
    the cavity: the anatomy stays as it is) to the best worst tet quality, and split the shells on
    cut faces."""
    if variant.element_type == "mixed":
        is_tet = np.isin(hex_pid, flesh_pids)
    else:
        is_tet = np.ones(len(hex_conn), dtype=bool)
    # the part id is the label: BCC tets never cross a part boundary
    mesh = tetmesh.tetrahedralise(coords, hex_conn, hex_pid, is_tet, forced_split=quad_conn)
    centres = mesh.centre_of[mesh.centre_of >= 0]
    n = len(coords)
    lowest = np.full(n, np.iinfo(np.int64).max)
    highest = np.full(n, -1)
    np.minimum.at(lowest, hex_conn.ravel(), np.repeat(hex_pid, 8))
    np.maximum.at(highest, hex_conn.ravel(), np.repeat(hex_pid, 8))
    free = (lowest == highest) & ~pinned
    free[quad_conn.ravel()] = False  # shells keep their shape
    in_tets = np.zeros(len(mesh.coords), dtype=bool)
    in_tets[mesh.tets.ravel()] = True
    in_hexes = np.zeros(len(mesh.coords), dtype=bool)
    in_hexes[hex_conn[mesh.hex_rows].ravel()] = True
    corners = np.flatnonzero(free & in_tets[: len(free)] & ~in_hexes[: len(free)])
    movable = np.concatenate([centres, corners])
    new_coords = tetmesh.improve_centres(mesh.coords, mesh.tets, movable)
    q = tetmesh.tet_quality(new_coords, mesh.tets)
    tet_pid = hex_pid[mesh.tet_cell]
    # shells on cut faces become the same two triangles
    on_cut = tetmesh._rows_in(np.sort(quad_conn, axis=1), mesh.split_face_keys)
    tris = tetmesh.split_triangles(coords, quad_conn[on_cut])
    tri_pid = np.repeat(quad_pid[on_cut], 2)
    order = np.argsort(tri_pid, kind="stable")
    stats = {
        "inverted_tets": int(np.count_nonzero(q["volume"] <= 0.0)),
        "tet_min_dihedral_deg": round(float(q["min_dihedral"].min()), 2),
        "tet_max_dihedral_deg": round(float(q["max_dihedral"].max()), 2),
        "tet_min_collapse": round(float(q["collapse"].min()), 4),
        "tet_cells": int(is_tet.sum()),
    }
    return (
        new_coords,
        hex_conn[mesh.hex_rows],
        hex_pid[mesh.hex_rows],
        mesh.tets,
        tet_pid,
        quad_conn[~on_cut],
        quad_pid[~on_cut],
        tris[order],
        tri_pid[order],
        stats,
    )


def _setup(design, side, node_ids, lat, med, plateau_index, unit="mm") -> dict[str, Any]:
    sign = 1.0 if side == "right" else -1.0
    phi = design.flexion_rad
    scale = UNITS[unit]
    digits = 6 if scale == 1.0 else 9

    def tibia_point(x, y, z):
        p = g.rotate_about_y(np.array([x, y, z], dtype=float), phi) * scale
        return [
            round(float(p[0]), digits),
            round(sign * float(p[1]), digits),
            round(float(p[2]), digits),
        ]

    def femur_point(x, y, z):
        if scale == 1.0:
            return [x, sign * y, z]
        return [round(x * scale, digits), round(sign * y * scale, digits), round(z * scale, digits)]

    fx, fy = design.femur_shaft_centre
    tx, ty = design.tibia_shaft_centre
    roles: dict[str, list[int]] = {r: [] for r in ROLE_ORDER}
    for spec in PARTS:
        roles[spec.role].append(spec.pid)
    ankle_z = design.calf_bottom_z - design.ankle_joint_drop
    return {
        "format": "kneegui-setup",
        "version": 1,
        "description": "kneegui built-in demo leg (procedural 50th-percentile male lower "
        "extremity, pelvis and foot excluded)",
        "units": unit,
        "side": side,
        "moving_segment": "tibia",
        "roles": roles,
        "landmarks": {
            "lateral_condyle": node_ids[lat].tolist(),
            "medial_condyle": node_ids[med].tolist(),
            "lr_axis": [int(node_ids[plateau_index]), tibia_point(tx, ty, ankle_z)],
            "femur_axis": [femur_point(fx, fy, 330.0), femur_point(fx, fy, 120.0)],
            "tibia_axis": [tibia_point(tx, ty, -80.0), tibia_point(tx, ty, -350.0)],
        },
        "kinematics": {
            "tibial_rotation": "default",
            "patellar_flexion": "default",
            "patellar_tilt": "default",
        },
        "skin_contours": 86,
    }


def write_demo(
    outdir: str | Path,
    elements: int = 20_000,
    side: str = "right",
    *,
    element_type: str = "hex",
    joint: str = "sliding",
    initial_flexion: float | None = None,
    unit: str = "mm",
) -> tuple[Path, Path]:
    """Generate the demo leg and write ``demo_leg.k`` and ``demo_leg.setup.json`` in ``outdir``.

    Parameters
    ----------
    outdir : str or Path
        Output folder (created if missing).
    elements, side, element_type, joint, initial_flexion, unit
        As :func:`generate_demo_leg`. A variant's deck title names it (and its length unit; the
        setup file states it as ``"units"``).

    Returns
    -------
    (Path, Path)
        The deck and the setup file. The same arguments always give byte-identical files.
    """
    from kneegui.io.lsdyna import write_model
    from kneegui.setup.format import setup_to_json

    leg = generate_demo_leg(
        elements,
        side,
        element_type=element_type,
        joint=joint,
        initial_flexion=initial_flexion,
        unit=unit,
    )
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    title = f"kneegui demo leg ({side}, {leg.stats['solids']} solids"
    if "variant" in leg.stats:
        v = leg.stats["variant"]
        title += (
            f", {v['element_type']} {v['joint']}, {v['initial_flexion_deg']:g} deg, {v['unit']}"
        )
    deck = write_model(leg.model, out / DECK_NAME, title=title + ")")
    setup_path = out / SETUP_NAME
    setup = dict(leg.setup, model=DECK_NAME)
    atomic_write_text(setup_path, setup_to_json(setup))
    return deck, setup_path
