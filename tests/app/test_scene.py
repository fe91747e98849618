"""Part surfaces: which faces no one can see from outside (faces shared between shown parts)."""

import numpy as np

from app.scene import hidden_faces, part_surfaces
from kneegui.model import ElementBlock, Model

#: Cube 1's faces x = 0, y = 0, y = 1, z = 0, z = 1 (all but the one it shares with cube 2).
OUTER_FACES_OF_CUBE_1 = [[0, 3, 9, 6], [0, 1, 7, 6], [3, 4, 10, 9], [0, 1, 4, 3], [6, 7, 10, 9]]
#: The face x = 1 between the cubes, and cube 2's face x = 2.
INTERFACE = [1, 4, 10, 7]
FAR_FACE_OF_CUBE_2 = [2, 5, 11, 8]


def two_cubes(shells: dict[int, list[list[int]]]) -> Model:
    """Cube 1 (part 1) at x 0-1 beside cube 2 (part 2) at x 1-2, sharing the face x = 1, with
    quad shells of the parts in ``shells``."""
    coords = np.array([(i, j, k) for k in (0, 1) for j in (0, 1) for i in (0, 1, 2)], float)
    conn = [[0, 1, 4, 3, 6, 7, 10, 9], [1, 2, 5, 4, 7, 8, 11, 10]]
    blocks = {"hex8": ElementBlock("hex8", [1, 2], [1, 2], conn)}
    quads = [(pid, q) for pid, qs in shells.items() for q in qs]
    if quads:
        blocks["quad4"] = ElementBlock(
            "quad4", np.arange(len(quads)) + 10, [p for p, _ in quads], [q for _, q in quads]
        )
    return Model(node_ids=np.arange(len(coords)) + 1, coords=coords, blocks=blocks)


def drawn_keys(surfaces, pid, hidden) -> set[tuple[int, ...]]:
    """The faces of part ``pid`` left drawn, as sorted model-node tuples."""
    surf = surfaces[pid]
    faces = surf.mesh.irregular_faces
    return {
        tuple(sorted(int(n) for n in surf.model_index[list(f)]))
        for f, gone in zip(faces, hidden[pid], strict=True)
        if not gone
    }


def key(face: list[int]) -> tuple[int, ...]:
    return tuple(sorted(face))


def test_a_cube_under_shells_and_beside_a_cube_hides_every_face_while_both_are_shown():
    surfaces = part_surfaces(two_cubes({3: OUTER_FACES_OF_CUBE_1}))
    hidden = hidden_faces(surfaces, {1, 2, 3})
    assert hidden[1].all()  # under the shells or against cube 2
    assert drawn_keys(surfaces, 2, hidden) == {
        key(f) for f in ([2, 5, 11, 8], [1, 2, 8, 7], [4, 5, 11, 10], [1, 2, 5, 4], [7, 8, 11, 10])
    }
    assert not hidden[3].any()  # a shell with one solid under it is what is seen
    # cube 2 hidden: the face between the cubes is open to view
    assert drawn_keys(surfaces, 1, hidden_faces(surfaces, {1, 3})) == {key(INTERFACE)}
    # the shells hidden: cube 1's outer faces are seen, the face between the cubes is not
    assert drawn_keys(surfaces, 1, hidden_faces(surfaces, {1, 2})) == {
        key(f) for f in OUTER_FACES_OF_CUBE_1
    }


def test_a_shell_between_two_solids_and_a_shell_twice():
    surfaces = part_surfaces(
        two_cubes({4: [INTERFACE], 5: [FAR_FACE_OF_CUBE_2], 6: [FAR_FACE_OF_CUBE_2]})
    )
    hidden = hidden_faces(surfaces, {1, 2, 4, 5, 6})
    assert hidden[4].all()  # solid on both sides
    assert not hidden[5].any() and hidden[6].all()  # the same face once: the smaller part id
    assert drawn_keys(surfaces, 2, hidden) == {
        key(f) for f in ([1, 2, 8, 7], [4, 5, 11, 10], [1, 2, 5, 4], [7, 8, 11, 10])
    }
    assert not hidden_faces(surfaces, {1, 4, 5})[4].any()  # cube 2 hidden: one solid under it


def test_a_degenerate_quad_covers_a_triangle_face():
    # a shell triangle written as a quad with its fourth node repeated (LS-DYNA's way) is
    # the same face as the tetrahedron's
    coords = np.array([(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1)], float)
    tet = ElementBlock("tet4", [1], [1], [[0, 1, 2, 3]])
    faces = [[0, 2, 1, 1], [0, 1, 3, 3], [1, 2, 3, 3], [0, 3, 2, 2]]
    shells = ElementBlock("quad4", [10, 11, 12, 13], [3] * 4, faces)
    model = Model(node_ids=np.arange(4) + 1, coords=coords, blocks={"tet4": tet, "quad4": shells})
    surfaces = part_surfaces(model)
    hidden = hidden_faces(surfaces, {1, 3})
    assert hidden[1].all() and not hidden[3].any()
    assert not hidden_faces(surfaces, {1})[1].any()
