"""The built-in demo leg: anatomy, conformity, quality, landmarks, determinism, files."""

from __future__ import annotations

import functools
import hashlib

import numpy as np
import pytest

from kneegui.demo import PARTS, DemoDesign, generate_demo_leg, write_demo
from kneegui.demo import generator as demo_generator
from kneegui.demo.generator import MIN_ELEMENTS, build_demo_leg, count_solids
from kneegui.demo.grid import rotate_about_y
from kneegui.demo.layout import make_layout
from kneegui.demo.sliding import SLIDING_RADIUS_MM
from kneegui.errors import KneeguiError
from kneegui.geometry.axes import compute_joint_axes, measure_flexion
from kneegui.geometry.circle_fit import fit_circle_2d
from kneegui.quality import compute_quality
from kneegui.setup.format import ROLES, load_setup
from kneegui.topology import SOLID_FACES

#: Requests whose meshes must meet the quality bounds: the smallest accepted request (the coarsest
#: mesh), requests between it and the default (repaired meshes), the default and finer ones (the
#: finer ones take seconds each: ``slow``).
SIZES_WITH_QUALITY = (
    MIN_ELEMENTS,
    2_000,
    8_000,
    10_000,
    12_000,
    20_000,
    pytest.param(50_000, marks=pytest.mark.slow),
    pytest.param(100_000, marks=pytest.mark.slow),
)


@functools.cache
def _leg(elements: int):
    """One generated leg per size for the whole module (generation is deterministic)."""
    return generate_demo_leg(elements)


@pytest.fixture(scope="module")
def leg():
    return _leg(20_000)


@pytest.fixture(scope="module")
def left_leg():
    return generate_demo_leg(20_000, side="left")


def _pids(leg, role):
    return [s.pid for s in PARTS if s.role == role]


def _role_nodes(leg, role, etypes=None):
    return leg.model.part_node_indices(_pids(leg, role), etypes)


# ------------------------------------------------------------------------- size, parts, roles
def test_default_size_is_near_the_papers_model(leg):
    n = len(leg.model.blocks["hex8"])
    assert 18_000 <= n <= 22_000
    assert leg.stats["solids"] == n


@pytest.mark.slow
def test_size_option_scales_the_same_anatomy():
    small = _leg(2_000)
    large = _leg(100_000)
    n_small = len(small.model.blocks["hex8"])
    n_large = len(large.model.blocks["hex8"])
    assert n_small < 7_500
    assert 85_000 <= n_large <= 115_000
    for leg in (small, large):
        counts = leg.model.element_counts()
        assert set(counts) == {s.pid for s in PARTS}


def test_smallest_request_gives_the_coarsest_layout():
    """Any request below the coarsest mesh returns the coarsest mesh (docs/demo-leg.md)."""
    coarsest = count_solids(make_layout(0.05))
    assert _leg(MIN_ELEMENTS).stats["solids"] == coarsest
    assert _leg(2_000).stats["solids"] == coarsest
    assert generate_demo_leg(5_000).stats["solids"] == coarsest


def test_every_part_is_present_titled_and_has_its_element_kind(leg):
    counts = leg.model.element_counts()
    for spec in PARTS:
        part = leg.model.parts[spec.pid]
        assert 700000 <= spec.pid < 800000
        assert part.title == f"{spec.stem}-R"
        kind = "hex8" if spec.kind == "solid" else "quad4"
        assert counts[spec.pid].get(kind, 0) > 0, part.title
        assert set(counts[spec.pid]) == {kind}


def test_setup_covers_every_part_and_loads_against_the_model(leg):
    roles = leg.setup["roles"]
    assert list(roles) == list(ROLES)
    assigned = sorted(p for pids in roles.values() for p in pids)
    assert assigned == sorted(leg.model.parts)
    setup = load_setup(leg.setup, leg.model)
    assert setup.side == "right"
    assert not setup.unassigned_parts
    assert len(setup.lateral_condyle_ids) >= 5 and len(setup.medial_condyle_ids) >= 5


# ------------------------------------------------------------------------- conformity
def _hex_boundary_faces(model):
    block = model.blocks["hex8"]
    faces = block.conn[:, list(SOLID_FACES["hex8"])].reshape(-1, 4)
    owner = np.repeat(np.arange(len(block)), 6)
    key = np.sort(faces, axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    once = counts[inv.reshape(-1)] == 1
    return faces[once], block.part_ids[owner[once]], key[once]


def test_coincident_nodes_only_at_the_sliding_interface_and_every_node_is_used(leg):
    """Coincident nodes exist only where soft tissue slides on a bone near the joint (one bone
    node and one soft-tissue node each, within the sliding radius), as at a contact interface."""
    m = leg.model
    rounded = np.round(m.coords, 6)
    _, inverse, counts = np.unique(rounded, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    shared = np.flatnonzero(counts[inverse] > 1)
    assert counts.max() <= 2
    bone = set(np.concatenate([_role_nodes(leg, r) for r in ("femur", "tibia", "fibula")]).tolist())
    soft = set(
        np.concatenate(
            [_role_nodes(leg, r) for r in ("flesh", "capsule", "skin", "meniscus")]
        ).tolist()
    )
    assert len(shared) > 0
    for group in np.unique(inverse[shared]):
        pair = np.flatnonzero(inverse == group).tolist()
        assert sum(p in bone for p in pair) == 1 and sum(p in soft for p in pair) >= 1
    radius = np.hypot(m.coords[shared, 0], m.coords[shared, 2])
    assert radius.max() < SLIDING_RADIUS_MM
    used = np.unique(np.concatenate([b.conn.ravel() for b in m.blocks.values()]))
    assert len(used) == m.n_nodes


def test_shells_lie_on_hex_faces_and_share_their_nodes(leg):
    m = leg.model
    hex_faces = np.sort(m.blocks["hex8"].conn[:, list(SOLID_FACES["hex8"])].reshape(-1, 4), axis=1)
    quads = np.sort(m.blocks["quad4"].conn, axis=1)
    hex_set = {tuple(f) for f in hex_faces.tolist()}
    missing = [q for q in quads.tolist() if tuple(q) not in hex_set]

    # at the sliding interface around the joint a shell may lie on a hex face with coincident
    # nodes of its own (as at a contact interface)
    def place(nodes):
        return tuple(sorted(map(tuple, np.round(m.coords[list(nodes)], 6).tolist())))

    hex_places = {place(f) for f in hex_faces.tolist()}
    for q in missing:
        assert place(q) in hex_places, q
        assert np.hypot(m.coords[q, 0], m.coords[q, 2]).min() < SLIDING_RADIUS_MM, q


def test_flesh_shares_nodes_with_skin_and_bone_surfaces(leg):
    flesh = set(_role_nodes(leg, "flesh", ["hex8"]).tolist())
    skin = set(_role_nodes(leg, "skin").tolist())
    assert skin <= flesh  # the whole skin sits on flesh nodes
    for bone in ("femur", "tibia", "fibula", "patella"):
        cortical = set(
            leg.model.part_node_indices(
                [s.pid for s in PARTS if s.role == bone and s.kind == "cortical"]
            ).tolist()
        )
        assert len(cortical & flesh) > 20, bone


def test_no_free_hex_face_inside_the_flesh(leg):
    """Every boundary face of a flesh hex is covered by a shell, lies on a model cut, or lies on
    another part's face at the sliding interface around the joint."""
    m = leg.model
    faces, pids, key = _hex_boundary_faces(m)
    flesh = np.isin(pids, _pids(leg, "flesh"))
    shell_keys = {tuple(q) for q in np.sort(m.blocks["quad4"].conn, axis=1).tolist()}
    covered = np.array([tuple(k) in shell_keys for k in key[flesh].tolist()])

    # at the sliding interface a flesh face lies on a cortical shell with its own coincident
    # nodes: covered by the shell's position rather than its node ids
    def where(conn):
        return {tuple(sorted(map(tuple, np.round(m.coords[q], 6).tolist()))) for q in conn}

    # or on another solid's face (a meniscus or ligament it slides against), inside the
    # sliding radius
    places = where(m.blocks["quad4"].conn) | where(faces[~flesh])
    on_place = np.array(
        [
            tuple(sorted(map(tuple, np.round(m.coords[f], 6).tolist()))) in places
            for f in faces[flesh]
        ]
    )
    radius = np.hypot(m.coords[faces[flesh]][..., 0], m.coords[faces[flesh]][..., 2])
    covered |= on_place & (radius.min(axis=1) < SLIDING_RADIUS_MM)
    xyz = m.coords[faces[flesh]]  # (n, 4, 3)
    top = np.all(np.abs(xyz[..., 2] - leg.design.thigh_top_z) < 1e-6, axis=1)
    calf_frame = rotate_about_y(xyz, -leg.design.flexion_rad)
    bottom = np.all(np.abs(calf_frame[..., 2] - leg.design.calf_bottom_z) < 1e-6, axis=1)
    assert np.all(covered | top | bottom)
    assert top.any() and bottom.any()


def test_bones_are_closed_by_their_cortical_shells(leg):
    m = leg.model
    _faces, pids, key = _hex_boundary_faces(m)
    shell_keys = {tuple(q) for q in np.sort(m.blocks["quad4"].conn, axis=1).tolist()}
    for spec in PARTS:
        if spec.kind == "solid" and spec.role in ("femur", "tibia", "fibula", "patella"):
            sel = pids == spec.pid
            assert all(tuple(k) in shell_keys for k in key[sel].tolist()), spec.stem


def test_joint_gap_is_not_bridged_by_flesh_or_menisci(leg):
    """Menisci sit on the tibia only; femur and tibia are linked only by ligaments and the
    flesh around the joint, never by a hex touching both bones' articular surfaces."""
    femur = set(_role_nodes(leg, "femur").tolist())
    tibia = set(_role_nodes(leg, "tibia").tolist())
    men = set(_role_nodes(leg, "meniscus").tolist())
    assert men & tibia
    assert not men & femur
    block = leg.model.blocks["hex8"]
    touches_f = np.isin(block.conn, list(femur)).any(axis=1)
    touches_t = np.isin(block.conn, list(tibia)).any(axis=1)
    both = np.unique(block.part_ids[touches_f & touches_t])
    assert set(both.tolist()) <= set(_pids(leg, "ligament"))


# ------------------------------------------------------------------------- quality
def _assert_quality_bounds(model):
    q = compute_quality(model.coords, model.blocks)
    assert q.n_inverted == 0
    for etype, eq in q.by_type.items():
        assert eq.metric("jacobian_corner").min() >= 0.3, etype
        assert eq.metric("aspect").max() <= 10.0, etype
        assert eq.metric("warpage").max() <= 30.0, etype


@pytest.mark.parametrize("elements", SIZES_WITH_QUALITY)
def test_quality_bounds(elements):
    leg = _leg(elements)
    assert "quality_problems" not in leg.stats
    _assert_quality_bounds(leg.model)


@pytest.mark.slow
def test_quality_bounds_hold_for_every_layout_up_to_the_default_size():
    """Every distinct block structure from the coarsest to the default one meets the bounds
    (after the repair where needed), so no request in that range can miss them."""
    design = DemoDesign()
    seen = set()
    default = _leg(20_000).layout.factor
    factors = [0.05]
    while factors[-1] * 1.02 < default:
        factors.append(factors[-1] * 1.02)
    checked = 0
    for factor in [*factors, default]:
        layout = make_layout(factor)
        key = (layout.rows.counts, layout.cols.counts, layout.rings.counts, layout.slabs.counts)
        if key in seen:
            continue
        seen.add(key)
        leg, problems = build_demo_leg(layout, design)
        assert problems == [], (leg.stats["solids"], problems)
        _assert_quality_bounds(leg.model)
        checked += 1
    assert checked >= 15


def test_smallest_leg_keeps_the_anatomy():
    leg = _leg(2_000)
    setup = load_setup(leg.setup, leg.model)
    axes = compute_joint_axes(leg.model.coords, setup)
    assert abs(axes.lateral_fit.radius - leg.design.lateral_radius) <= 0.3
    assert abs(axes.medial_fit.radius - leg.design.medial_radius) <= 0.3
    assert abs(measure_flexion(leg.model.coords, setup) - 9.0) <= 1.0
    femur = leg.model.coords[_role_nodes(leg, "femur")]
    assert 95.0 <= np.ptp(femur[:, 1]) <= 105.0
    assert 370.0 <= _girth(leg, 0.0) <= 395.0


def test_default_mesh_needs_no_repair():
    assert _leg(20_000).stats["repaired_nodes"] == 0
    assert _leg(2_000).stats["repaired_nodes"] > 0


def test_a_mesh_that_misses_the_bounds_is_never_returned(monkeypatch):
    """If no resolution near the request meets the bounds, generation fails loudly."""
    monkeypatch.setattr(demo_generator, "quality_problems", lambda model: ["1 inverted elements"])
    with pytest.raises(KneeguiError, match="quality bounds"):
        generate_demo_leg(2_000)


def test_left_leg_is_the_mirror_and_not_inverted(leg, left_leg):
    assert np.allclose(left_leg.model.coords * [1, -1, 1], leg.model.coords)
    q = compute_quality(left_leg.model.coords, left_leg.model.blocks)
    assert q.n_inverted == 0
    assert min(eq.metric("jacobian_corner").min() for eq in q.by_type.values()) >= 0.3
    assert all(p.title.endswith("-L") for p in left_leg.model.parts.values())


# ------------------------------------------------------------------------- landmarks, pose
@pytest.mark.parametrize(
    "key,attr", [("lateral_condyle", "lateral_radius"), ("medial_condyle", "medial_radius")]
)
def test_posterior_condyle_arcs_fit_the_designed_radii(leg, key, attr):
    idx = leg.model.node_index(leg.setup["landmarks"][key])
    sagittal = leg.model.coords[idx][:, [0, 2]]
    fit = fit_circle_2d(sagittal)
    assert abs(fit.radius - getattr(leg.design, attr)) <= 0.3
    assert fit.arc_span_deg >= 60.0
    assert np.all(np.isin(idx, _role_nodes(leg, "femur")))


def test_setup_axes_measure_the_designed_radii_and_flexion(leg, left_leg):
    for one in (leg, left_leg):
        setup = load_setup(one.setup, one.model)
        axes = compute_joint_axes(one.model.coords, setup)
        assert abs(axes.lateral_fit.radius - one.design.lateral_radius) <= 0.3
        assert abs(axes.medial_fit.radius - one.design.medial_radius) <= 0.3
        assert not axes.warnings
        # the F-E axis is the designed y axis through the origin
        assert abs(abs(axes.fe_axis.direction[1]) - 1.0) < 1e-6
        assert np.linalg.norm(axes.fe_axis.point[[0, 2]]) < 1e-6
        assert abs(axes.initial_flexion_deg - one.design.initial_flexion_deg) <= 1.0
        assert abs(measure_flexion(one.model.coords, setup) - 9.0) <= 1.0


def _shaft_axis(leg, role, frame_angle, z_lo, z_hi):
    """Principal axis of the bone nodes between two heights of the bone's own frame."""
    pts = leg.model.coords[_role_nodes(leg, role)]
    local = rotate_about_y(pts, -frame_angle)
    sel = (local[:, 2] > z_lo) & (local[:, 2] < z_hi)
    p = pts[sel] - pts[sel].mean(axis=0)
    axis = np.linalg.svd(p, full_matrices=False)[2][0]
    return axis if axis[2] > 0 else -axis


def test_measured_flexion_from_the_bone_shafts(leg):
    f = _shaft_axis(leg, "femur", 0.0, 120.0, 390.0)
    t = _shaft_axis(leg, "tibia", leg.design.flexion_rad, -330.0, -110.0)
    angle = np.degrees(np.arctan2(f[0] * t[2] - f[2] * t[0], f[0] * t[0] + f[2] * t[2]))
    assert abs(abs(angle) - leg.design.initial_flexion_deg) <= 1.0
    assert t[0] > 0  # superior tibial direction points anterior: the foot is posterior


def _girth(leg, z, frame_angle=0.0):
    """Perimeter (mm) of the skin cut by the plane at height z of a frame (rotated about y)."""
    m = leg.model
    skin = m.blocks["quad4"].conn[np.isin(m.blocks["quad4"].part_ids, _pids(leg, "skin"))]
    pts = rotate_about_y(m.coords, -frame_angle)
    edges = np.concatenate([skin[:, [0, 1]], skin[:, [1, 2]], skin[:, [2, 3]], skin[:, [3, 0]]])
    edges = np.unique(np.sort(edges, axis=1), axis=0)
    za, zb = pts[edges[:, 0], 2] - z, pts[edges[:, 1], 2] - z
    cut = (za * zb < 0) | ((za == 0) & (zb != 0))
    t = za[cut] / (za[cut] - zb[cut])
    ring = (pts[edges[cut, 0]] + t[:, None] * (pts[edges[cut, 1]] - pts[edges[cut, 0]]))[:, :2]
    c = ring.mean(axis=0)
    ring = ring[np.argsort(np.arctan2(ring[:, 1] - c[1], ring[:, 0] - c[0]))]
    return float(np.linalg.norm(np.diff(np.vstack([ring, ring[:1]]), axis=0), axis=1).sum())


def test_proportions_of_a_50th_percentile_male(leg):
    femur = leg.model.coords[_role_nodes(leg, "femur")]
    knee_width = np.ptp(femur[:, 1])
    assert 95.0 <= knee_width <= 105.0
    assert 530.0 <= _girth(leg, 399.0) <= 560.0
    assert 370.0 <= _girth(leg, 0.0) <= 395.0
    phi = leg.design.flexion_rad
    calf = max(_girth(leg, z, phi) for z in (-200.0, -170.0, -140.0, -110.0))
    assert 355.0 <= calf <= 385.0
    assert 220.0 <= _girth(leg, -399.0, phi) <= 245.0
    bbox = leg.model.bounding_box()
    assert bbox[1, 2] == pytest.approx(400.0)


# ------------------------------------------------------------------------- determinism, files
def test_generation_is_deterministic(leg):
    again = generate_demo_leg(20_000)
    assert np.array_equal(again.model.coords, leg.model.coords)
    for etype, block in leg.model.blocks.items():
        assert np.array_equal(again.model.blocks[etype].conn, block.conn)
    assert again.setup == leg.setup


def test_write_demo_is_byte_identical_and_reads_back(tmp_path):
    from kneegui.io.lsdyna import read_deck

    a = write_demo(tmp_path / "a", elements=5_000)
    b = write_demo(tmp_path / "b", elements=5_000)
    for pa, pb in zip(a, b, strict=True):
        assert hashlib.sha256(pa.read_bytes()).digest() == hashlib.sha256(pb.read_bytes()).digest()
    model = read_deck(a[0])
    leg = generate_demo_leg(5_000)
    assert model.n_nodes == leg.model.n_nodes
    assert np.allclose(model.coords, leg.model.coords, atol=1e-6)
    assert {p.title for p in model.parts.values()} == {p.title for p in leg.model.parts.values()}
    setup = load_setup(a[1], model)
    assert abs(measure_flexion(model.coords, setup) - 9.0) <= 1.0


def test_bad_arguments_raise_typed_errors():
    with pytest.raises(KneeguiError):
        generate_demo_leg(20_000, side="up")
    with pytest.raises(KneeguiError):
        generate_demo_leg(10)


@pytest.mark.slow
def test_million_element_model_meets_the_bounds():
    """The generation time of this size is measured by the benchmark (``generate_s``)."""
    leg = generate_demo_leg(1_000_000)
    assert len(leg.model.blocks["hex8"]) >= 1_000_000 * 0.9
    assert "quality_problems" not in leg.stats
    q = compute_quality(leg.model.coords, leg.model.blocks)
    assert q.n_inverted == 0
    for eq in q.by_type.values():
        assert eq.metric("jacobian_corner").min() >= 0.3
        assert eq.metric("aspect").max() <= 10.0
        assert eq.metric("warpage").max() <= 30.0
