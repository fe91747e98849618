"""Issue 23, item 4: the export holds on decks the project was not built around.

Every demo variant (element type, joint meshing, side, unit) is posed by the export
(:func:`kneegui.reposition.pipeline.pose_model`: mapping, relaxation, smoothing) at 0 to 120 deg,
and each cell asserts what a user needs of the written deck: no inverted element the
repositioner could have moved, no soft-tissue node deeper than 0.5 mm (in the model's unit)
inside a bone, at 90 deg no element measure worse than the initial model's worst, and soft
tissue that keeps its volume element by element (95th percentile of the soft solids' volume
change at most 25 % at 90 deg). The engine is told nothing of the variant.

The cheap cells (the coarse demo at 90 deg) run by default; the others are marked
``expensive`` and run with ``pytest -m expensive``.
docs/repositioning-comparison.md gives the same figures on the default-size variants.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest

from kneegui import demo
from kneegui.model import Model
from kneegui.quality import compute_quality
from kneegui.quality.summary import GATE_JACOBIAN_TOLERANCE, GATED_TET_METRICS, summarize_quality
from kneegui.reposition import Repositioner, RepositionOptions
from kneegui.reposition.checks import penetrating, surface_triangles
from kneegui.reposition.midside import TET10_MIDSIDE
from kneegui.reposition.pipeline import pose_model
from kneegui.reposition.preflight import preflight_of
from kneegui.setup import load_setup

ANGLES = (0.0, 30.0, 60.0, 90.0, 120.0)
#: Depth (mm of the model's own unit) beyond which a soft-tissue node counts as inside a bone:
#: nodes of a sliding interface lie on the bone surface itself.
IN_BONE_MM = 0.5
#: How far above the initial model's worst corner Jacobian the export's worst must stay at
#: 90 deg (the gate asks for no worse; this keeps its outcome off the last digits).
GATE_MARGIN = 0.005
#: Issue 23's bound on the 95th percentile of the soft solids' |volume change| at 90 deg.
P95_LIMIT_PCT = 25.0


#: The variants (``generate_demo_leg`` keywords): element type, joint meshing, side, initial
#: flexion and unit, each changed alone from the default hex, sliding, right, mm leg.
VARIANTS: dict[str, dict[str, Any]] = {
    "hex": {},
    "hex-left": {"side": "left"},
    "hex-m": {"unit": "m"},
    "hex-flexed0": {"initial_flexion": 0.0},
    "hex-flexed20": {"initial_flexion": 20.0},
    "welded": {"joint": "welded"},
    "tet": {"element_type": "tet"},
    "mixed": {"element_type": "mixed"},
    "tet10": {"element_type": "tet10"},
}


@dataclass(frozen=True)
class Variant:
    """A demo leg as a user might bring it, and its length unit (model units per millimetre),
    known only to the test."""

    model: Model
    setup: dict[str, Any]
    unit: float


#: Variants with no coarse grid that meets the demo's quality bounds (the leg built at 20 deg:
#: docs/demo-leg.md), built at this many solids instead.
SMALLEST_ELEMENTS = {"hex-flexed20": 20_000}


def build_variant(name: str, elements: int) -> Variant:
    """The named variant of the demo leg (:data:`VARIANTS`)."""
    keywords = VARIANTS[name]
    leg = demo.generate_demo_leg(max(elements, SMALLEST_ELEMENTS.get(name, 0)), **keywords)
    return Variant(leg.model, leg.setup, 1e-3 if keywords.get("unit") == "m" else 1.0)


@dataclass(frozen=True)
class Cell:
    """What the export wrote for one variant at one angle."""

    inverted_movable: int
    inverted_locked: int
    in_bone: int
    #: of them, nodes not as deep in a bone in the deck itself (a coarse tet's edge between
    #: two nodes on a curved bone, and its mid-side node, may cut into it at rest)
    in_bone_beyond_rest: int
    p95_pct: float
    worst_jacobian: float
    initial_worst_jacobian: float
    #: each gated tet measure: (worst, initial worst, True when low is bad)
    tet_measures: dict[str, tuple[float, float, bool]]


def export_cell(variant: Variant, rep: Repositioner, angle: float) -> Cell:
    """Pose with the export and measure the cell's figures."""
    model = variant.model
    setup = rep.setup
    posed = pose_model(rep, angle)
    coords = posed.model.coords
    q = compute_quality(coords, model.blocks)
    # locked as the pre-flight check finds them (tested in test_preflight.py): tied to bones that
    # move apart, with no free node that could save them at this flexion
    inverted = preflight_of(rep).split_inverted(posed.model, q)
    locked_n, movable = inverted["locked"], inverted["movable"] + inverted["other"]
    assert inverted["total"] == q.n_inverted
    interior = np.concatenate([rep.groups.flesh, rep.groups.band])
    ml = rep.axes.fe_axis.direction
    inside = np.zeros(len(interior), dtype=bool)
    inside_at_rest = np.zeros(len(interior), dtype=bool)
    for role in ("femur", "tibia", "fibula", "patella"):
        tris = surface_triangles(model, setup.parts_of(role), shells=False)
        if len(tris):
            depth = IN_BONE_MM * variant.unit
            inside |= penetrating(coords[interior], coords, tris, ml, depth)
            rest = model.coords
            inside_at_rest |= penetrating(rest[interior], rest, tris, ml, depth)
    report = posed.report
    initial_q = compute_quality(model.coords, model.blocks)
    summary = summarize_quality(posed.model, q, initial=initial_q)
    directions = summary["thresholds"]["*"]
    tet_measures = {
        m: (e["worst"], e["initial_worst"], directions[m]["direction"] == "min")
        for m in GATED_TET_METRICS
        if (e := summary["model"].get(m)) is not None
        and e.get("worst") is not None
        and e.get("initial_worst") is not None
        and m in directions
    }
    return Cell(
        inverted_movable=movable,
        inverted_locked=locked_n,
        in_bone=int(inside.sum()),
        in_bone_beyond_rest=int((inside & ~inside_at_rest).sum()),
        p95_pct=float(report["volume_change"]["soft_element_p95_abs_pct"]),
        worst_jacobian=float(q.worst_jacobian()),
        initial_worst_jacobian=float(initial_q.worst_jacobian()),
        tet_measures=tet_measures,
    )


@pytest.fixture(scope="module")
def repositioners():
    """``repositioners(name)``: the coarse variant and its repositioner, built once."""
    cache: dict[str, tuple[Variant, Repositioner]] = {}

    def get(name: str) -> tuple[Variant, Repositioner]:
        if name not in cache:
            variant = build_variant(name, 2000)
            setup = load_setup(variant.setup, variant.model)
            cache[name] = (variant, Repositioner(variant.model, setup, RepositionOptions()))
        return cache[name]

    return get


@pytest.fixture(scope="module")
def cells(repositioners):
    """``cells(name, angle)``: the export's figures, measured once per cell."""
    cache: dict[tuple[str, float], Cell] = {}

    def get(name: str, angle: float) -> Cell:
        if (name, angle) not in cache:
            variant, rep = repositioners(name)
            cache[name, angle] = export_cell(variant, rep, angle)
        return cache[name, angle]

    return get


#: (variant, angle) cells in the default run; every other cell is ``expensive`` (left out of the
#: default run to keep CI within its budget; ``pytest -m expensive`` runs them).
#: (the coarse hex demo at 0 deg: the pass beyond the relaxed region, 5 December; the mixed
#: demo at 90 deg: its settling pushed a tet's aspect past the initial worst, 13.54 against
#: 13.46, until gate rounds followed the settling, 5 December; the 10-node tet demo at 0 deg:
#: its mid-side nodes pushed along their edges failed the gate until they left the bones at
#: right angles to their edges and the edges got contact planes, 6 December)
DEFAULT_CELLS = {
    ("hex", 90.0),
    ("hex-m", 90.0),
    ("hex", 0.0),
    ("mixed", 90.0),
    ("tet10", 0.0),
    # the edges' planes crushed its corner tets until the quality stage held their middles
    # (7 December): collapse 0.061 against the initial 0.108, now 0.110
    ("tet10", 90.0),
    # the fast eps schedule left 5 movable knee-flesh elements inverted here until the slow
    # pass around them (RelaxOptions.slow_eps_decrease, 6 December, fourth session)
    ("hex-flexed20", 120.0),
}
#: Cells measured to miss a target, with what was measured (kept visible as expected failures
#: until the engine reaches them; docs/repositioning.md, known limits).
KNOWN_MISSES = {
    **{
        ("welded", angle, "export"): "the welded joint keeps movable elements inverted "
        f"(coarse demo, locked / movable: {counts}; docs/repositioning.md, known limits)"
        for angle, counts in ((60.0, "23 / 4"), (90.0, "62 / 22"), (120.0, "104 / 51"))
    },
    ("welded", 90.0, "quality"): "worst corner Jacobian below zero (inverted elements)",
    ("welded", 0.0, "quality"): "worst corner Jacobian 0.225 against the initial 0.330: the "
    "four elements below 0.330 are locked (every node tied to femur or tibia; coarse demo, "
    "5 December)",
}


def _cells(check: str, angles=ANGLES):
    for name in VARIANTS:
        for angle in angles:
            marks = [] if (name, angle) in DEFAULT_CELLS else [pytest.mark.expensive]
            miss = KNOWN_MISSES.get((name, angle, check))
            if miss:
                marks.append(pytest.mark.xfail(reason=miss, strict=False))
            yield pytest.param(name, angle, marks=marks, id=f"{name}-{angle:g}")


@pytest.mark.parametrize(("name", "angle"), list(_cells("export")))
def test_export_holds_on_variant(cells, name, angle):
    """No inverted movable element, no tissue in a bone that the deck did not have there at
    rest (no variant has any: the 10-node tet demo's "9 mid-side nodes up to 6.8 mm inside the
    tibia in the deck" of 6 December were a mis-measure of the distance query, since
    exact near the surface); at 90 deg the soft tissue keeps its volume
    (measured on the coarse hex demo, 6 December, pinned kernels, volume aim 1/1.15 to 1.15:
    95th percentile 21.0 %, in metres 20.9 %, left 21.0 %, built at 0 deg 22.2 %; with the
    former aim of 1/1.2 to 1.2, 23.5-25.2 %, the leg built at 0 deg over the bound)."""
    cell = cells(name, angle)
    assert cell.inverted_movable == 0, cell
    assert cell.in_bone_beyond_rest == 0, cell
    if angle == 90.0:
        assert cell.p95_pct <= P95_LIMIT_PCT, cell


@pytest.mark.parametrize(("name", "angle"), list(_cells("quality", (0.0, 90.0))))
def test_quality_at_0_and_90_no_worse_than_initial(cells, name, angle):
    """At 0 deg (a far calf hex the mapping alone took to 0.327 against 0.330 until the
    quality stage mended beyond its region, 5 December) and 90 deg, the gate's measures, with
    a margin so that they cannot flip on rounding: the worst
    corner Jacobian at least :data:`GATE_MARGIN` better than the initial model's worst (where
    the deck has solids other than tetrahedra, whose single corner is 1.0 by definition), and
    each tet measure no worse than the initial worst (its gate; the worst tet of a deck is
    often one the export does not move, so no margin beyond equality is asked)."""
    cell = cells(name, angle)
    assert cell.tet_measures or cell.initial_worst_jacobian < 1.0 - GATE_MARGIN, cell
    if cell.initial_worst_jacobian < 1.0 - GATE_MARGIN:
        # or the initial worst element itself, carried rigidly (the mixed demo's calf hex,
        # equal to the initial value to rounding)
        carried = abs(cell.worst_jacobian - cell.initial_worst_jacobian) <= 1e-9
        assert carried or cell.worst_jacobian >= cell.initial_worst_jacobian + GATE_MARGIN, cell
    for measure, (worst, initial, low_bad) in cell.tet_measures.items():
        # a straight edge's mid-side offset is rounding (1e-11 edge lengths in the deck), and
        # a shorter edge scales it up: straight to within the gate's tolerance
        slack = GATE_JACOBIAN_TOLERANCE if measure.startswith("midside") else 0.0
        assert (worst >= initial - slack) if low_bad else (worst <= initial + slack), (
            measure,
            cell,
        )


#: The least fraction of the initial worst tet collapse a tet may keep at 120 deg, where the
#: gate fails on every tet variant (the crease: docs/repositioning.md, known limits).
SLIVER_FRACTION_120 = 0.1


@pytest.mark.expensive
@pytest.mark.parametrize("name", ["tet", "mixed", "tet10"])
def test_no_tet_flattened_to_a_sliver_at_120(cells, name):
    """At 120 deg the tet variants miss the gate (worst collapse about 0.02 against the
    initial 0.108), but no tet is pressed flat: a gate round that flattened the worst tet
    from 0.042 to 0.014 (and the settling after it to 0.007, tet aspect 200) is now undone
    (7 December), leaving 0.020-0.021, twice this bound."""
    worst, initial, _ = cells(name, 120.0).tet_measures["tet_collapse"]
    assert worst >= SLIVER_FRACTION_120 * initial, (worst, initial)


def test_welded_joint_corners_proven_locked_leave_the_energy(cells, repositioners):
    """The welded joint at 90 deg: the untangling leaves out the corners of the elements the
    bones leave no valid shape (their free nodes cannot save them: the pre-flight's proof at
    this pose), and keeps fewer movable elements inverted than when their corners pulled the
    tissue around them (coarse demo, 6 December: 54 with them, 27 without, and 27 with the
    pinned corners' planes of 7 December (26 before their gradient's last bits changed); the
    cell's target of none is still a known miss)."""
    cell = cells("welded", 90.0)
    _, rep = repositioners("welded")
    relaxation = rep.relaxation
    locked = relaxation.locked_corners(rep.pose(90.0))
    assert len(locked) > 20
    assert cell.inverted_movable <= 40, cell


def test_the_relaxed_nodes_take_the_mid_side_nodes_of_their_edges(repositioners):
    """A 10-node tet's mid-side node between two skin contour nodes is no contour node; the
    relaxation moves it with its edge (left where the mapping put it, such nodes of the coarse
    10-node demo ended 1.4 edge lengths off their edges at 90 deg)."""
    variant, rep = repositioners("tet10")
    n = variant.model.n_nodes
    near = np.zeros(n, dtype=bool)
    near[rep._soft_near_joint()] = True
    soft = np.zeros(n, dtype=bool)
    soft[rep.groups.soft] = True
    block = variant.model.blocks["tet10"]
    mid = block.conn[:, list(TET10_MIDSIDE)]
    ends = block.conn[:, [list(e) for e in TET10_MIDSIDE.values()]]
    carried = near[ends].any(axis=2) & soft[mid]
    assert carried.sum() > 1000
    assert near[mid[carried]].all()


def test_length_options_scale_with_the_model(repositioners):
    """Every length the export uses is scaled by the knee's own size: the same demo in metres
    gets lengths a thousand times smaller and a contact penalty per squared unit a million
    times stiffer; nothing depends on the unit's name."""
    (_, mm), (_, m) = repositioners("hex"), repositioners("hex-m")
    assert m.length_scale == pytest.approx(1e-3 * mm.length_scale, rel=1e-9)
    a, b = (r.options.improvement.scaled(r.length_scale) for r in (mm, m))
    for name in ("contact_band", "contact_force_depth", "contact_clearance"):
        assert getattr(b.relax, name) == pytest.approx(1e-3 * getattr(a.relax, name), rel=1e-9)
    assert b.quality.constraint_tolerance == pytest.approx(
        1e-3 * a.quality.constraint_tolerance, rel=1e-9
    )
    assert b.quality.constraint_stiffness == pytest.approx(
        1e6 * a.quality.constraint_stiffness, rel=1e-9
    )
