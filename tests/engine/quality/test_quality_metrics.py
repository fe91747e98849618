"""Per-element metrics: QUALITY.md reference cases, invariances and independent re-derivations."""

from __future__ import annotations

import itertools
import warnings

import numpy as np
import pytest

from kneegui.errors import Cancelled
from kneegui.model import ElementBlock
from kneegui.quality import QualityEvaluator, compute_quality
from kneegui.quality.metrics import METRICS, ONLY_METRICS
from kneegui.topology import SOLID_FACES, split_degenerate_solids

UNIT_CUBE = np.array(
    [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)],
    dtype=float,
)


def _one(etype: str, pts) -> dict[str, float]:
    pts = np.asarray(pts, dtype=float)
    block = ElementBlock(etype, [1], [1], [list(range(len(pts)))])
    q = compute_quality(pts, {etype: block})[etype]
    names = ("jacobian_gauss", "jacobian_corner", "aspect", "warpage", "skew", "volume")
    out = {k: float(getattr(q, k)[0]) for k in names}
    out["inverted"] = bool(q.inverted[0])
    return out


def _cube_with(changes) -> np.ndarray:
    pts = UNIT_CUBE.copy()
    changes(pts)
    return pts


def _shear(p):
    p[4:, 0] += 0.5


def _raise7(p):
    p[7, 2] += 0.25


def _frustum(p):
    p[4:, :2] = 0.25 + 0.5 * p[4:, :2]


def _slab(p):
    p[:, 2] *= 0.05


def _push7(p):
    p[7] = (0.2, 0.8, -0.3)  # node 7 pushed down through the bottom face


# QUALITY.md "Reference cases (hex8)": J Gauss, J corner, aspect, warpage, skew (as printed)
REFERENCE_CASES = {
    "unit cube": (UNIT_CUBE, (1, 1, 1, 0, 0)),
    "shear": (_cube_with(_shear), (1, 1, 1.118, 0, 26.57)),
    "node 7 raised": (_cube_with(_raise7), (0.875, 0.800, 1.25, 19.75, 7.13)),
    "frustum": (_cube_with(_frustum), (0.459, 0.250, 2.12, 0, 0)),
    "slab": (_cube_with(_slab), (1, 1, 20, 0, 0)),
    "node 7 through bottom": (_cube_with(_push7), (-0.062, -0.700, 3.73, 150.5, 46.95)),
    "mirrored": (UNIT_CUBE[[4, 5, 6, 7, 0, 1, 2, 3]], (-1, -1, 1, 0, 0)),
}


@pytest.mark.parametrize("case", list(REFERENCE_CASES))
def test_hex_reference_cases(case):
    pts, (jg, jc, aspect, warp, skew) = REFERENCE_CASES[case]
    q = _one("hex8", pts)
    # tolerances: half a unit of the last printed digit
    assert q["jacobian_gauss"] == pytest.approx(jg, abs=5e-4)
    assert q["jacobian_corner"] == pytest.approx(jc, abs=5e-4)
    assert q["aspect"] == pytest.approx(aspect, abs=5e-3)
    assert q["warpage"] == pytest.approx(warp, abs=0.05)
    assert q["skew"] == pytest.approx(skew, abs=5e-3)
    assert q["inverted"] == (jc <= 0)


def test_affine_maps_keep_jacobian_one():
    rng = np.random.default_rng(1)
    for _ in range(20):
        a = rng.normal(size=(3, 3))
        if np.linalg.det(a) < 0:
            a[:, 0] *= -1
        q = _one("hex8", UNIT_CUBE @ a.T + rng.normal(size=3))
        assert q["jacobian_corner"] == pytest.approx(1.0, abs=1e-12)
        assert q["jacobian_gauss"] == pytest.approx(1.0, abs=1e-12)
        assert q["volume"] == pytest.approx(np.linalg.det(a), rel=1e-12)


def _random_hexes(n, amplitude, seed):
    rng = np.random.default_rng(seed)
    pts = np.tile(UNIT_CUBE, (n, 1)) + rng.uniform(-amplitude, amplitude, (8 * n, 3))
    conn = np.arange(8 * n).reshape(n, 8)
    return pts, {"hex8": ElementBlock("hex8", np.arange(n), np.zeros(n), conn)}


def test_corner_jacobian_never_exceeds_gauss_on_random_hexes():
    pts, blocks = _random_hexes(5000, 0.25, 2)
    q = compute_quality(pts, blocks)["hex8"]
    assert np.all(q.jacobian_corner <= q.jacobian_gauss + 1e-12)
    assert q.jacobian_corner.min() < 0.2  # the sample is not trivially good


# ---------------------------------------------------------------------- independent re-derivations
_SIGNS = UNIT_CUBE * 2 - 1  # (xi, eta, zeta) of each hex node


def _reference_hex_dets(x: np.ndarray, points: np.ndarray) -> np.ndarray:
    """det(dx/dxi) at parametric points via shape-function derivatives (8, 3) per element."""
    out = []
    for xi, eta, zeta in points:
        s = _SIGNS
        dn = (
            np.stack(
                [
                    s[:, 0] * (1 + s[:, 1] * eta) * (1 + s[:, 2] * zeta),
                    s[:, 1] * (1 + s[:, 0] * xi) * (1 + s[:, 2] * zeta),
                    s[:, 2] * (1 + s[:, 0] * xi) * (1 + s[:, 1] * eta),
                ]
            )
            / 8.0
        )  # (3, 8)
        jac = np.einsum("dk,mkc->mcd", dn, x)
        out.append(np.linalg.det(jac))
    return np.stack(out, 1)


def test_hex_gauss_jacobian_and_volume_match_shape_function_derivation():
    pts, blocks = _random_hexes(500, 0.25, 3)
    q = compute_quality(pts, blocks)["hex8"]
    x = pts.reshape(-1, 8, 3)
    g = 1 / np.sqrt(3)
    dets = _reference_hex_dets(x, list(itertools.product((-g, g), repeat=3)))
    expected = np.where(dets.max(1) > 0, dets.min(1) / dets.max(1), -1.0)
    np.testing.assert_allclose(q.jacobian_gauss, expected, atol=1e-12)
    corner = _reference_hex_dets(x, _SIGNS)
    expected = np.where(corner.max(1) > 0, corner.min(1) / corner.max(1), -1.0)
    np.testing.assert_allclose(q.jacobian_corner, expected, atol=1e-12)
    # volume: 3-point Gauss integration of det (exact for the trilinear map) as a reference
    pts3, w3 = np.polynomial.legendre.leggauss(3)
    grid = list(itertools.product(pts3, repeat=3))
    weights = np.array([w3[i] * w3[j] * w3[k] for i, j, k in itertools.product(range(3), repeat=3)])
    np.testing.assert_allclose(q.volume, _reference_hex_dets(x, grid) @ weights, rtol=1e-12)


def _angle(a, b):
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, -1)))


def _reference_quad_face(p0, p1, p2, p3):
    """QUALITY.md literally: warpage by atan2 of triangle normals, skew from mid-side lines."""
    w1 = _angle(np.cross(p1 - p0, p2 - p0), np.cross(p2 - p0, p3 - p0))
    w2 = _angle(np.cross(p1 - p0, p3 - p0), np.cross(p2 - p1, p3 - p1))
    l1 = (p1 + p2) / 2 - (p3 + p0) / 2
    l2 = (p2 + p3) / 2 - (p0 + p1) / 2
    alpha = _angle(l1, l2)
    alpha = np.minimum(alpha, 180 - alpha)
    edges = np.stack(
        [np.linalg.norm(b - a, axis=-1) for a, b in ((p0, p1), (p1, p2), (p2, p3), (p3, p0))]
    )
    return np.maximum(w1, w2), 90 - alpha, edges.max(0) / edges.min(0)


def _reference_tri_face(p0, p1, p2):
    best = np.full(len(p0), 90.0)
    pts = (p0, p1, p2)
    for i in range(3):
        a, b, c = pts[i], pts[(i + 1) % 3], pts[(i + 2) % 3]
        median = (b + c) / 2 - a
        midline = (a + c) / 2 - (a + b) / 2
        alpha = _angle(median, midline)
        best = np.minimum(best, np.minimum(alpha, 180 - alpha))
    edges = np.stack([np.linalg.norm(b - a, axis=-1) for a, b in ((p0, p1), (p1, p2), (p2, p0))])
    return 90 - best, edges.max(0) / edges.min(0)


def test_hex_face_metrics_match_literal_definitions():
    pts, blocks = _random_hexes(2000, 0.3, 4)
    q = compute_quality(pts, blocks)["hex8"]
    x = pts.reshape(-1, 8, 3)
    faces = [_reference_quad_face(*(x[:, i] for i in f)) for f in SOLID_FACES["hex8"]]
    warp = np.max([f[0] for f in faces], axis=0)
    skew = np.max([f[1] for f in faces], axis=0)
    aspect = np.max([f[2] for f in faces], axis=0)
    assert warp.max() > 60
    np.testing.assert_allclose(q.warpage, warp, atol=1e-6)
    np.testing.assert_allclose(q.skew, skew, atol=1e-6)
    np.testing.assert_allclose(q.aspect, aspect, rtol=1e-12)


def test_tet_and_tri_face_metrics_match_literal_definitions():
    rng = np.random.default_rng(5)
    n = 2000
    tet = np.array([(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1)], dtype=float)
    pts = np.tile(tet, (n, 1)) + rng.uniform(-0.3, 0.3, (4 * n, 3))
    conn = np.arange(4 * n).reshape(n, 4)
    blocks = {
        "tet4": ElementBlock("tet4", np.arange(n), np.zeros(n), conn),
        "tri3": ElementBlock("tri3", np.arange(n), np.zeros(n), conn[:, :3]),
    }
    q = compute_quality(pts, blocks)
    x = pts.reshape(-1, 4, 3)
    faces = [
        _reference_tri_face(*(x[:, i] for i in f))
        for f in ((0, 1, 2), (0, 1, 3), (1, 2, 3), (0, 2, 3))
    ]
    np.testing.assert_allclose(q["tet4"].skew, np.max([f[0] for f in faces], 0), atol=1e-6)
    np.testing.assert_allclose(q["tet4"].aspect, np.max([f[1] for f in faces], 0), rtol=1e-12)
    np.testing.assert_allclose(q["tri3"].skew, faces[0][0], atol=1e-6)
    vol = (
        np.einsum("ij,ij->i", np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), x[:, 3] - x[:, 0]) / 6
    )
    np.testing.assert_allclose(q["tet4"].volume, vol, rtol=1e-12)
    assert np.array_equal(q["tet4"].inverted, vol <= 0) and q["tet4"].inverted.any()
    assert np.array_equal(q["tet4"].jacobian_corner, np.where(vol > 0, 1.0, -1.0))
    assert np.all(q["tet4"].warpage == 0) and np.all(q["tri3"].warpage == 0)


# ---------------------------------------------------------------------- other element types
def test_perfect_wedge_and_its_degenerate_hex_storage():
    wedge = np.array([(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (0, 1, 1)], float)
    q = _one("wedge6", wedge)
    assert q["jacobian_corner"] == pytest.approx(1) and q["jacobian_gauss"] == pytest.approx(1)
    assert q["volume"] == pytest.approx(0.5)
    assert q["aspect"] == pytest.approx(np.sqrt(2))
    assert q["warpage"] == pytest.approx(0, abs=1e-12)
    assert q["skew"] == pytest.approx(np.degrees(np.arctan(0.5)))  # right isosceles triangle
    # stored as 8 nodes 1,2,3,3,4,5,6,6 the hex measure would be nonsense; the split is exact
    conn8 = np.array([[0, 1, 2, 2, 3, 4, 5, 5]])
    split = split_degenerate_solids(conn8)
    assert set(split) == {"wedge6"}
    rebuilt = wedge[split["wedge6"][1][0]]
    qr = _one("wedge6", rebuilt)
    assert qr["jacobian_corner"] == pytest.approx(1) and qr["volume"] == pytest.approx(0.5)
    collapsed = _one("hex8", wedge[conn8[0]])
    assert collapsed["jacobian_corner"] <= 0 and collapsed["aspect"] == np.inf


def test_wedge_gauss_volume_against_tet_split():
    rng = np.random.default_rng(6)
    wedge = np.array([(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (0, 1, 1)], float)
    for _ in range(10):
        a = rng.normal(size=(3, 3)) + 3 * np.eye(3)
        pts = wedge @ a.T  # affine: planar quads, exact volume det(a) / 2
        q = _one("wedge6", pts)
        assert q["volume"] == pytest.approx(np.linalg.det(a) / 2, rel=1e-12)
        assert q["jacobian_gauss"] == pytest.approx(1, abs=1e-12)
    pts = wedge.copy()
    pts[5] += (0.3, 0.2, -0.4)
    q = _one("wedge6", pts)
    assert 0 < q["jacobian_corner"] < q["jacobian_gauss"] < 1


def test_pyramid_metrics():
    h = 1 / np.sqrt(2)  # side edges of length 1: four equilateral triangles on a unit square
    pyramid = np.array([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0.5, 0.5, h)], float)
    q = _one("pyramid5", pyramid)
    assert q["jacobian_corner"] == pytest.approx(1) and q["jacobian_gauss"] == pytest.approx(1)
    assert q["volume"] == pytest.approx(h / 3)
    assert q["aspect"] == pytest.approx(1) and q["skew"] == pytest.approx(0, abs=1e-6)
    assert q["warpage"] == pytest.approx(0, abs=1e-12)
    kite = pyramid.copy()
    kite[2] = (1.5, 1.5, 0)  # unequal base corners
    assert 0 < _one("pyramid5", kite)["jacobian_corner"] < 1
    through = pyramid.copy()
    through[4, 2] = -0.3  # apex pushed through the base
    qt = _one("pyramid5", through)
    assert qt["jacobian_corner"] == -1 and qt["inverted"] and qt["volume"] < 0
    split = split_degenerate_solids(np.array([[0, 1, 2, 3, 4, 4, 4, 4]]))
    assert set(split) == {"pyramid5"}


def test_tet10_is_measured_on_its_corners():
    tet = np.array([(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1)], dtype=float)
    mids = np.array([(0, 1), (1, 2), (2, 0), (0, 3), (1, 3), (2, 3)])
    pts10 = np.vstack([tet, tet[mids].mean(1) + 0.05])  # curved edges do not matter
    q10 = _one("tet10", pts10)
    q4 = _one("tet4", tet)
    for k in ("jacobian_corner", "aspect", "skew", "volume"):
        assert q10[k] == pytest.approx(q4[k])
    assert q4["volume"] == pytest.approx(1 / 6)
    assert _one("tet4", tet[[1, 0, 2, 3]])["inverted"]


def test_quad_shell_metrics():
    square = np.array([(0, 0, 0), (2, 0, 0), (2, 1, 0), (0, 1, 0)], float)
    q = _one("quad4", square)
    assert (q["jacobian_corner"], q["jacobian_gauss"], q["aspect"], q["warpage"], q["skew"]) == (
        pytest.approx(1),
        pytest.approx(1),
        pytest.approx(2),
        pytest.approx(0),
        pytest.approx(0),
    )
    assert q["volume"] == pytest.approx(2)
    assert not _one("quad4", square[::-1])[
        "inverted"
    ]  # a shell has no inside: either order is fine
    bowtie = square[[0, 1, 3, 2]]
    assert _one("quad4", bowtie)["inverted"]
    folded = square.copy()
    folded[2, 2] = 1.0
    assert _one("quad4", folded)["warpage"] > 30


def test_triangle_shell_metrics():
    equilateral = np.array([(0, 0, 0), (1, 0, 0), (0.5, np.sqrt(3) / 2, 0)])
    q = _one("tri3", equilateral)
    assert q["aspect"] == pytest.approx(1) and q["skew"] == pytest.approx(0, abs=1e-6)
    assert q["volume"] == pytest.approx(np.sqrt(3) / 4) and q["jacobian_corner"] == 1
    collapsed = np.array([(0, 0, 0), (1, 0, 0), (2, 0, 0)], float)
    qc = _one("tri3", collapsed)
    assert qc["inverted"] and qc["skew"] == pytest.approx(90)


# ---------------------------------------------------------------------- evaluator behaviour
def test_row_subset_equals_full_evaluation_and_inputs_untouched():
    pts, blocks = _random_hexes(3000, 0.3, 7)
    before = pts.copy()
    ev = QualityEvaluator(blocks)
    full = ev.evaluate(pts)["hex8"]
    rows = np.array([5, 17, 2999, 0, 17])
    part = ev.evaluate(pts, rows={"hex8": rows})["hex8"]
    assert np.array_equal(part.rows, rows)
    for k in ("jacobian_corner", "jacobian_gauss", "aspect", "warpage", "skew", "volume"):
        np.testing.assert_array_equal(getattr(part, k), getattr(full, k)[rows])
    assert np.array_equal(pts, before)
    assert "hex8" not in ev.evaluate(pts, rows={"tet4": [0]})


def test_parallel_chunks_equal_serial():
    pts, blocks = _random_hexes(40000, 0.3, 8)
    serial = QualityEvaluator(blocks, threads=1).evaluate(pts)["hex8"]
    parallel = QualityEvaluator(blocks, threads=2).evaluate(pts)["hex8"]
    for k in ("jacobian_corner", "warpage", "volume"):
        np.testing.assert_array_equal(getattr(serial, k), getattr(parallel, k))


@pytest.mark.parametrize("threads", [1, 2])
def test_cancel_is_asked_between_waves_of_chunks(threads):
    """A whole-body model's quality takes over a second: ``cancel`` is asked before every wave
    of chunks, True stops it, and False changes nothing."""
    pts, blocks = _random_hexes(40000, 0.3, 8)  # 5 chunks: one wave
    asked = []
    ev = QualityEvaluator(blocks, threads=threads)
    result = ev.evaluate(pts, cancel=lambda: asked.append(1) or False)["hex8"]
    assert len(asked) == 1
    plain = ev.evaluate(pts)["hex8"]
    for k in ("jacobian_corner", "warpage", "volume"):
        np.testing.assert_array_equal(getattr(result, k), getattr(plain, k))
    with pytest.raises(Cancelled):
        compute_quality(pts, blocks, cancel=lambda: True)


def test_beams_and_springs_are_not_measured():
    pts = np.zeros((2, 3))
    blocks = {"beam2": ElementBlock("beam2", [1], [1], [[0, 1]])}
    assert compute_quality(pts, blocks).n_elements == 0


@pytest.mark.parametrize("only", ONLY_METRICS)
def test_single_metric_evaluation_is_bit_identical_to_the_full_one(only):
    # a heat-map redrawn with every slider pose measures its metric alone (and the Jacobian,
    # which says what is inverted); the values must be the full evaluation's exactly, on fair,
    # distorted and inverted elements of every type
    from kneegui.topology import NODES_PER_ELEMENT

    rng = np.random.default_rng(7)
    n = 400
    blocks, chunks, offset = {}, [], 0
    for etype in ("hex8", "wedge6", "pyramid5", "tet4", "tet10", "quad4", "tri3"):
        k = NODES_PER_ELEMENT[etype]
        ref = rng.normal(size=(1, k, 3))
        pts = ref + rng.normal(scale=0.6, size=(n, k, 3))  # some of them inverted
        conn = offset + np.arange(n * k).reshape(n, k)
        offset += n * k
        chunks.append(pts.reshape(-1, 3))
        blocks[etype] = ElementBlock(etype, np.arange(n), np.zeros(n), conn)
    coords = np.concatenate(chunks)
    evaluator = QualityEvaluator(blocks)
    rows = {etype: np.sort(rng.choice(n, 150, replace=False)) for etype in blocks}
    for subset in (None, rows):
        full = evaluator.evaluate(coords, subset)
        fast = evaluator.evaluate(coords, subset, only=only)
        assert list(fast) == list(full)
        for etype in full:
            np.testing.assert_array_equal(fast[etype].rows, full[etype].rows)
            np.testing.assert_array_equal(fast[etype].jacobian_corner, full[etype].jacobian_corner)
            np.testing.assert_array_equal(fast[etype].inverted, full[etype].inverted)
            np.testing.assert_array_equal(fast[etype].metric(only), full[etype].metric(only))
            for measured in fast[etype].measured:  # what comes with it (the other tet measures)
                np.testing.assert_array_equal(
                    fast[etype].metric(measured), full[etype].metric(measured)
                )
            # the rest of the kernel is not worked out, and says so
            skipped = [k for k in METRICS if k not in fast[etype].measured]
            assert fast[etype].has("jacobian") and skipped
            assert not fast[etype].has(skipped[0])
            assert fast[etype].has(only) == full[etype].has(only)
            with pytest.raises(ValueError, match="not measured"):
                fast[etype].metric(skipped[0])
        collapse = full["tet4"].tet_collapse
        assert collapse.min() < 0 < collapse.max()  # inverted and valid tets among the cases
    assert 0 < full.n_inverted < full.n_elements  # the cases include inverted elements
    with pytest.raises(ValueError, match="only= takes one of"):
        evaluator.evaluate(coords, only="jacobian_gauss")


def test_an_edge_of_1e_160_gives_an_infinite_aspect_without_a_warning():
    """A damaged deck's face with an edge of ~1e-160 overflows the edge ratio: its aspect is
    infinite, measured quietly (the pipeline fuzz test hit it as a RuntimeWarning)."""
    coords = np.array([[0.0, 0, 0], [1e-160, 0, 0], [1, 1, 0], [0, 1, 0]])
    blocks = {"quad4": ElementBlock("quad4", np.array([1]), np.array([1]), np.arange(4)[None, :])}
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        aspect = compute_quality(coords, blocks)["quad4"].aspect
    assert np.isinf(aspect[0])
