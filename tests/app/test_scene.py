"""Part surfaces: which parts no one can see from outside (each face a face of another part)."""

import numpy as np

from app.scene import enclosed_parts, part_surfaces
from kneegui.model import ElementBlock, Model


def two_cubes(shells: list[list[int]]) -> Model:
    """Cube 1 (part 1) at x 0-1 beside cube 2 (part 2) at x 1-2, sharing the face x = 1;
    ``shells`` are quads of part 3."""
    coords = np.array([(i, j, k) for k in (0, 1) for j in (0, 1) for i in (0, 1, 2)], float)
    hexes = ElementBlock(
        "hex8", [1, 2], [1, 2], [[0, 1, 4, 3, 6, 7, 10, 9], [1, 2, 5, 4, 7, 8, 11, 10]]
    )
    blocks = {"hex8": hexes}
    if shells:
        blocks["quad4"] = ElementBlock(
            "quad4", np.arange(len(shells)) + 10, [3] * len(shells), shells
        )
    return Model(node_ids=np.arange(len(coords)) + 1, coords=coords, blocks=blocks)


#: Cube 1's faces but the one it shares with cube 2, as shells (x = 0, y = 0, y = 1, z = 0, z = 1).
OUTER_FACES_OF_CUBE_1 = [[0, 3, 9, 6], [0, 1, 7, 6], [3, 4, 10, 9], [0, 1, 4, 3], [6, 7, 10, 9]]


def test_a_cube_under_shells_and_beside_a_cube_is_enclosed_only_while_both_are_shown():
    surfaces = part_surfaces(two_cubes(OUTER_FACES_OF_CUBE_1))
    assert surfaces[1].enclosures == (frozenset({2}), frozenset({3}))
    assert surfaces[2].enclosures is None  # five faces of its own
    assert surfaces[3].enclosures is None  # shells are what is drawn over a solid
    assert enclosed_parts(surfaces, {1, 2, 3}) == {1}
    assert enclosed_parts(surfaces, {1, 3}) == set()  # the face x = 1 is open to view
    assert enclosed_parts(surfaces, {1, 2}) == set()
    assert enclosed_parts(surfaces, {2, 3}) == set()  # a hidden part is never "enclosed"


def test_a_face_left_open_keeps_the_cube_drawn():
    surfaces = part_surfaces(two_cubes(OUTER_FACES_OF_CUBE_1[:-1]))
    assert surfaces[1].enclosures is None
    assert enclosed_parts(surfaces, {1, 2, 3}) == set()


def test_a_degenerate_quad_covers_a_triangle_face():
    # a shell triangle written as a quad with its fourth node repeated (LS-DYNA's way) is
    # the same face as the tetrahedron's
    coords = np.array([(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1)], float)
    tet = ElementBlock("tet4", [1], [1], [[0, 1, 2, 3]])
    faces = [[0, 2, 1, 1], [0, 1, 3, 3], [1, 2, 3, 3], [0, 3, 2, 2]]
    shells = ElementBlock("quad4", [10, 11, 12, 13], [3] * 4, faces)
    model = Model(node_ids=np.arange(4) + 1, coords=coords, blocks={"tet4": tet, "quad4": shells})
    surfaces = part_surfaces(model)
    assert surfaces[1].enclosures == (frozenset({3}),)
    assert enclosed_parts(surfaces, {1, 3}) == {1}
