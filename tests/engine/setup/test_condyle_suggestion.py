"""Condyle node-set suggestion from the femur surface, in any orientation and for both sides."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from kneegui.errors import GeometryError
from kneegui.geometry import compute_joint_axes
from kneegui.model import ElementBlock, Model
from kneegui.setup import load_setup, suggest_condyle_nodes, surface_node_indices
from kneegui.setup.condyles import femur_frame
from kneegui.setup.synthetic import _hex_box, build_synthetic_knee, random_rotation


@pytest.mark.parametrize("side", ["right", "left"])
@pytest.mark.parametrize("seed", [None, 31, 32, 33])
@pytest.mark.parametrize("hints", [True, False])
def test_suggested_sets_fit_the_designed_circles(side, seed, hints):
    rot = None if seed is None else random_rotation(seed)
    knee = build_synthetic_knee(side=side, rotation=rot, translation=[-300.0, 40.0, 12.0])
    kwargs = {"tibia_part_ids": [201], "patella_part_ids": [401]} if hints else {}
    lateral, medial = suggest_condyle_nodes(knee.model, [101, 102], side, **kwargs)
    designed = compute_joint_axes(knee.model.coords, load_setup(knee.setup, knee.model))
    # every suggested node is on its own condyle's circle (not swapped, nothing off the arc)
    for ids, centre, radius in (
        (lateral, designed.lateral_center, 20.5),
        (medial, designed.medial_center, 23.3),
    ):
        assert len(ids) >= 20
        rel = knee.model.coords[knee.model.node_index(ids)] - centre
        in_plane = np.hypot(rel @ designed.anterior, rel @ designed.superior)
        np.testing.assert_allclose(in_plane, radius, atol=1e-6)
        assert np.all(np.abs(rel @ designed.sagittal_normal) <= 11.0 + 1e-6)
        # on the posterior-distal part of the circle (at most ~15 deg anterior of distal)
        assert np.all(rel @ designed.anterior < 0.25 * radius)
    data = copy.deepcopy(knee.setup)
    data["landmarks"]["lateral_condyle"] = lateral.tolist()
    data["landmarks"]["medial_condyle"] = medial.tolist()
    axes = compute_joint_axes(knee.model.coords, load_setup(data, knee.model))
    assert axes.lateral_fit.radius == pytest.approx(20.5, abs=0.3)
    assert axes.medial_fit.radius == pytest.approx(23.3, abs=0.3)
    assert axes.initial_flexion_deg == pytest.approx(9.0, abs=0.5)


@pytest.mark.parametrize("flat_deg", [20.0, 40.0])
@pytest.mark.parametrize("noise", [0.0, 0.05])
def test_flat_distal_facet_is_left_out(flat_deg, noise):
    """Like the demo leg and real knees: the distal facet is flatter than the posterior arc."""
    knee = build_synthetic_knee(
        rotation=random_rotation(4), distal_flat_deg=flat_deg, noise_mm=noise, seed=2
    )
    lateral, medial = suggest_condyle_nodes(knee.model, [101, 102], "right")
    data = copy.deepcopy(knee.setup)
    data["landmarks"]["lateral_condyle"] = lateral.tolist()
    data["landmarks"]["medial_condyle"] = medial.tolist()
    axes = compute_joint_axes(knee.model.coords, load_setup(data, knee.model))
    tol = 1e-6 if noise == 0 else 0.3
    assert axes.lateral_fit.radius == pytest.approx(20.5, abs=tol)
    assert axes.medial_fit.radius == pytest.approx(23.3, abs=tol)


def test_femur_frame_directions():
    rot = random_rotation(40)
    knee = build_synthetic_knee(side="left", rotation=rot)
    frame = femur_frame(knee.model, [101, 102], "left", tibia_part_ids=[201])
    world = knee.to_world[:3, :3]
    np.testing.assert_allclose(frame["superior"], world[:, 2], atol=1e-6)
    np.testing.assert_allclose(frame["anterior"], world[:, 0], atol=1e-6)
    # medial of the built knee is +y; mirrored into the left knee by 'world'
    np.testing.assert_allclose(frame["medial"], world @ [0.0, 1.0, 0.0], atol=1e-6)


def test_surface_of_a_hex_block():
    pts, conn = _hex_box([0, 0, 0], [3, 3, 3], (3, 3, 3))
    model = Model(
        np.arange(len(pts)) + 1,
        pts,
        {"hex8": ElementBlock("hex8", np.arange(27) + 1, np.ones(27), conn)},
    )
    surf = surface_node_indices(model, [1])
    assert len(surf) == 4**3 - 2**3
    inner = np.all((pts > 0.5) & (pts < 2.5), axis=1)
    assert not np.any(np.isin(np.flatnonzero(inner), surf))


def test_femur_without_shape_raises():
    pts, conn = _hex_box([0, 0, 0], [3, 3, 3], (3, 3, 3))
    model = Model(
        np.arange(len(pts)) + 1,
        pts,
        {"hex8": ElementBlock("hex8", np.arange(27) + 1, np.ones(27), conn)},
    )
    with pytest.raises(GeometryError, match="not elongated"):
        suggest_condyle_nodes(model, [1], "right")


def _reference_surface(model, part_ids):
    """Straightforward surface: faces counted with np.unique(axis=0)."""
    from kneegui.topology import SHELL_TYPES
    from kneegui.topology import SOLID_FACES as _SOLID_FACES

    faces, nodes = [], []
    for etype, block in model.blocks.items():
        conn = block.conn[np.isin(block.part_ids, list(part_ids))]
        if etype in SHELL_TYPES:
            nodes.append(conn.reshape(-1))
        elif etype in _SOLID_FACES:
            for face in _SOLID_FACES[etype]:
                f = conn[:, list(face)]
                faces.append(np.column_stack([f, np.full((len(f), 4 - f.shape[1]), -1)]))
    uniq, counts = np.unique(np.sort(np.concatenate(faces), axis=1), axis=0, return_counts=True)
    b = uniq[counts == 1].reshape(-1)
    return np.unique(np.concatenate([*nodes, b[b >= 0]]))


def test_surface_matches_reference_on_mixed_elements():
    """Hexes split into tets, wedges and pyramids, plus shells: same surface as np.unique."""
    pts, conn = _hex_box([0, 0, 0], [4, 3, 2], (4, 3, 2))
    n = len(conn)
    hexes, tets, wedges = conn[: n // 3], conn[n // 3 : 2 * n // 3], conn[2 * n // 3 :]
    # each hex -> 6 tets (around the 0-6 diagonal), or 2 wedges
    tet_rows = [(0, 1, 2, 6), (0, 2, 3, 6), (0, 3, 7, 6), (0, 7, 4, 6), (0, 4, 5, 6), (0, 5, 1, 6)]
    tet_conn = np.concatenate([tets[:, list(t)] for t in tet_rows])
    wedge_conn = np.concatenate([wedges[:, [0, 1, 2, 4, 5, 6]], wedges[:, [0, 2, 3, 4, 6, 7]]])
    shell = hexes[:, [4, 5, 6, 7]][:2]
    blocks = {
        "hex8": ElementBlock("hex8", np.arange(len(hexes)) + 1, np.full(len(hexes), 1), hexes),
        "tet4": ElementBlock(
            "tet4", np.arange(len(tet_conn)) + 100, np.full(len(tet_conn), 1), tet_conn
        ),
        "wedge6": ElementBlock(
            "wedge6", np.arange(len(wedge_conn)) + 500, np.full(len(wedge_conn), 2), wedge_conn
        ),
        "quad4": ElementBlock("quad4", [900, 901], [3, 3], shell),
    }
    model = Model(np.arange(len(pts)) + 1, pts, blocks)
    for parts in ([1], [2], [1, 2], [1, 2, 3], [3]):
        np.testing.assert_array_equal(
            surface_node_indices(model, parts), _reference_surface(model, parts)
        )


def test_demo_leg_suggested_nodes_fit_its_circular_arcs():
    """The demo's condyles are exact circular arcs (20.5 / 23.3 mm, docs/demo-leg.md): the plain
    fit of the suggested nodes gives those radii and an axis that does not depend on the nodes."""
    from kneegui.demo import generate_demo_leg
    from kneegui.setup.landmarks import suggest_setup

    leg = generate_demo_leg(2000)
    setup = load_setup(suggest_setup(leg.model, "right"), leg.model)
    axes = compute_joint_axes(leg.model.coords, setup)
    assert axes.lateral_fit.radius == pytest.approx(20.5, abs=0.01)
    assert axes.medial_fit.radius == pytest.approx(23.3, abs=0.01)
    assert axes.sensitivity is not None
    spread = axes.sensitivity
    assert spread.direction_spread_deg < 0.01
    assert max(spread.lateral_radius_spread_mm, spread.medial_radius_spread_mm) < 0.01
