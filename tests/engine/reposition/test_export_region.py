"""The export at scale: the solvers see the knee's region only, whatever else the model holds;
the quality is measured again only where nodes moved; the weights' iterative solve agrees with
the direct one; the CLI's progress bar."""

from __future__ import annotations

import io

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from kneegui.commands.pose import ProgressBar
from kneegui.errors import Cancelled
from kneegui.model import ElementBlock, Model, Part
from kneegui.quality import compute_quality
from kneegui.reposition import Repositioner, RepositionOptions
from kneegui.reposition.pipeline import pose_model, requalify
from kneegui.reposition.rigid_blend import block_cg
from kneegui.setup import load_setup

FAR_PART = 799_999


def _with_far_tissue(model: Model, cells: int) -> tuple[Model, np.ndarray]:
    """The model and a ``cells``^3 block of hexes 2 m above it (a stand-in for the rest of a
    body: soft tissue the knee's relaxation must not read); returns the far nodes' indices."""
    g = np.arange(cells + 1, dtype=np.float64) * 10.0
    xyz = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    xyz += model.coords.mean(axis=0) + np.array([0.0, 0.0, 2000.0])
    n0 = model.n_nodes
    idx = np.arange((cells + 1) ** 3).reshape((cells + 1,) * 3)
    c = idx[:-1, :-1, :-1].ravel()
    di, dj, dk = (cells + 1) ** 2, cells + 1, 1
    conn = np.column_stack(
        [c, c + di, c + di + dj, c + dj, c + dk, c + di + dk, c + di + dj + dk, c + dj + dk]
    )
    hexes = model.blocks["hex8"]
    first_id = int(max(b.ids.max() for b in model.blocks.values())) + 1
    blocks = dict(model.blocks)
    blocks["hex8"] = ElementBlock(
        "hex8",
        np.concatenate([hexes.ids, first_id + np.arange(len(conn))]),
        np.concatenate([hexes.part_ids, np.full(len(conn), FAR_PART)]),
        np.concatenate([hexes.conn, conn + n0]),
    )
    parts = dict(model.parts)
    template = next(iter(model.parts.values()))
    parts[FAR_PART] = Part(FAR_PART, "far tissue", template.secid, template.mid, "")
    node_ids = np.concatenate([model.node_ids, model.node_ids.max() + 1 + np.arange(len(xyz))])
    big = Model(node_ids, np.vstack([model.coords, xyz]), blocks, parts)
    return big, n0 + np.arange(len(xyz))


@pytest.fixture(scope="module")
def far_repositioner(small_leg):
    big, far = _with_far_tissue(small_leg.model, 33)
    setup = dict(small_leg.setup)
    setup["roles"] = {**setup["roles"], "flesh": [*setup["roles"]["flesh"], FAR_PART]}
    return Repositioner(big, load_setup(setup, big), RepositionOptions()), far


def test_the_relaxation_sees_only_the_knee_region(small_repositioner, far_repositioner):
    far_rep, far = far_repositioner
    model = small_repositioner.model
    assert far_rep.model.n_elements > 3 * model.n_elements  # most of the model is far away
    small = pose_model(small_repositioner, 45.0).report
    big_posed = pose_model(far_rep, 45.0)
    big = big_posed.report
    # the solvers were handed the same elements: the far tissue adds none
    assert len(far_rep.relaxation.tets) == len(small_repositioner.relaxation.tets)
    assert not np.isin(far, far_rep.relaxation.tets).any()
    assert not np.isin(far, far_rep.relaxation.free).any()
    # and the regions they relaxed are the knee's (the harmonic weights normalise their edge
    # weights over all the soft tissue, so the far block shifts the mapping a little and the
    # degraded region by about 1 %; the solvers' work did not grow with the model)
    for key in ("free_nodes", "corners"):
        assert small["relaxation"][key] > 0
        assert big["relaxation"][key] == pytest.approx(small["relaxation"][key], rel=0.05)
    for key in ("free_nodes", "elements"):
        assert small["relaxation"]["quality"][key] > 0
        assert big["relaxation"]["quality"][key] == pytest.approx(
            small["relaxation"]["quality"][key], rel=0.05
        )
    # the far tissue is where the blend put it, untouched by relaxation and smoothing
    mapped = far_rep.pose(45.0)
    np.testing.assert_array_equal(big_posed.model.coords[far], mapped[far])
    assert big["quality"]["smoothed"]["inverted"] == small["quality"]["smoothed"]["inverted"] == 0


def test_requalify_equals_measuring_every_element(small_leg, small_posed):
    model = small_leg.model
    before = small_posed(60.0).coords
    after = before.copy()
    rng = np.random.default_rng(3)
    moved = rng.choice(model.n_nodes, 40, replace=False)
    after[moved] += rng.normal(scale=0.2, size=(40, 3))
    previous = compute_quality(before, model.blocks)
    fast = requalify(previous, before, after, model.blocks)
    full = compute_quality(after, model.blocks)
    changed = 0
    for etype in full:
        for name in ("jacobian_corner", "jacobian_gauss", "aspect", "warpage", "skew", "volume"):
            np.testing.assert_allclose(
                fast[etype].metric(name), full[etype].metric(name), rtol=1e-12, atol=1e-12
            )
        np.testing.assert_array_equal(fast[etype].inverted, full[etype].inverted)
        changed += int(np.sum(fast[etype].volume != previous[etype].volume))
    assert changed > 0  # the moved nodes' elements were measured again


def test_block_cg_agrees_with_the_direct_solve():
    rng = np.random.default_rng(0)
    n = 400
    a = sp.random(n, n, density=0.02, random_state=1)
    a = a + a.T
    lap = sp.diags(np.asarray(abs(a).sum(axis=1)).ravel() + 0.1) - a
    rhs = rng.random((n, 4))
    exact = spla.splu(sp.csc_matrix(lap)).solve(rhs)
    got = block_cg(sp.csr_matrix(lap), rhs, np.zeros_like(rhs), 1.0 / lap.diagonal(), rtol=1e-12)
    np.testing.assert_allclose(got, exact, rtol=1e-8, atol=1e-10)


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_bar_draws_on_a_terminal_and_is_quiet_otherwise():
    piped = io.StringIO()
    bar = ProgressBar("90 deg", piped)
    bar(0.5, "relaxing")
    bar.close()
    assert piped.getvalue() == ""
    tty = _Terminal()
    bar = ProgressBar("90 deg", tty, interval=0.0)
    bar(0.5, "relaxing soft tissue")
    assert "90 deg [############            ]  50% relaxing soft tissue" in tty.getvalue()
    bar.close()
    assert tty.getvalue().endswith("\r")


def test_pose_model_reports_progress_and_cancels(small_repositioner):
    seen = []
    with pytest.raises(Cancelled):
        pose_model(
            small_repositioner,
            90.0,
            progress=lambda fraction, message: seen.append((fraction, message)),
            cancel=lambda: len(seen) > 3,
        )
    assert len(seen) > 3
    fractions = [f for f, _ in seen]
    assert fractions == sorted(fractions) and 0 <= fractions[0] and fractions[-1] < 1


def test_pose_model_asks_to_cancel_after_every_solver_iteration(small_repositioner):
    """A solver round on a whole-body model's region runs for tens of seconds: a cancel must not
    wait for its end (asked once per round before, the 1M demo went 90 s without asking)."""
    asked = []
    posed = pose_model(small_repositioner, 90.0, cancel=lambda: bool(asked.append(1)))
    relaxation = posed.report["relaxation"]
    iterations = relaxation["iterations"] + relaxation["quality"]["iterations"]
    assert relaxation["iterations"] > 10 * relaxation["rounds"]
    assert len(asked) >= iterations


def test_a_cancel_while_the_relaxation_is_set_up_stops_the_export(small_leg, small_setup):
    """The first export builds the relaxation and the bone contact (the 1M demo: 8.7 and 3.8 s);
    a cancel there stops it, and the next export builds them again and gets the same pose."""
    rep = Repositioner(small_leg.model, small_setup, RepositionOptions())
    messages, asked = [], []

    def cancel_once_setting_up() -> bool:
        asked.append(1)
        return messages[-1:] == ["preparing the relaxation"] and len(asked) > 2

    with pytest.raises(Cancelled, match="set-up"):
        pose_model(
            rep,
            60.0,
            progress=lambda fraction, message: messages.append(message),
            cancel=cancel_once_setting_up,
        )
    assert rep.relaxation is None  # nothing half-built is kept
    with pytest.raises(Cancelled, match="bone contact"):
        pose_model(rep, 60.0, cancel=lambda: rep.relaxation is not None)
    again = pose_model(rep, 60.0)
    fresh = pose_model(Repositioner(small_leg.model, small_setup, RepositionOptions()), 60.0)
    np.testing.assert_array_equal(again.model.coords, fresh.model.coords)


def test_contact_extension_by_cg_matches_the_lu(small_repositioner, monkeypatch):
    import kneegui.reposition.contact as contact

    rep = small_repositioner
    bone = rep.bone_pose(90.0)
    coords = rep.pose(90.0)
    reach = rep.options.relax_contact_reach
    lu = rep._bone_contact(reach)
    monkeypatch.setattr(contact, "DIRECT_SOLVE_MAX", 0)  # as on a whole-body model
    cg = rep._bone_contact(reach)
    by_lu, by_cg = coords.copy(), coords.copy()
    pushed = lu.resolve(by_lu, bone.transforms)
    assert cg.resolve(by_cg, bone.transforms) == pushed > 0
    assert np.abs(by_lu - coords).max() > 0.1  # the pushes spread into the tissue
    np.testing.assert_allclose(by_cg, by_lu, rtol=0, atol=1e-5)


def test_local_laplace_solve_stays_near_the_pushes():
    from kneegui.reposition.contact import LocalLaplaceSolve

    # a strip of tissue 400 x 6 nodes held along one long side (a bone), pushed at one end
    nx, ny = 400, 6
    idx = np.arange(nx * ny).reshape(nx, ny)
    pairs = np.concatenate(
        [
            np.column_stack([idx[:-1].ravel(), idx[1:].ravel()]),
            np.column_stack([idx[:, :-1].ravel(), idx[:, 1:].ravel()]),
        ]
    )
    n = nx * ny
    adj = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    adj = (adj + adj.T).tocsr()
    held = np.zeros(n)
    held[idx[:, 0]] = 1.0  # edges to the bone's (held) nodes
    lap = sp.diags(np.asarray(adj.sum(axis=1)).ravel() + held) - adj
    rhs = np.zeros((n, 3))
    rhs[idx[:3].ravel()] = [1.0, -2.0, 0.5]
    solve = LocalLaplaceSolve(lap, hops=4)
    got = solve(rhs)
    exact = spla.splu(sp.csc_matrix(lap)).solve(rhs)
    assert 0 < solve.last_region < n // 4  # the far end of the strip was never touched
    np.testing.assert_allclose(got, exact, rtol=0, atol=1e-6 * np.abs(exact).max())
    # the bone contact's push-out on a whole-body model: its solve asks to cancel
    with pytest.raises(Cancelled):
        solve(rhs, cancel=lambda: True)
    np.testing.assert_array_equal(solve(rhs, cancel=lambda: False), got)


def test_bone_distance_query_does_not_depend_on_the_thread_count(small_repositioner):
    surface = small_repositioner._bone_surfaces()["femur"]
    rng = np.random.default_rng(5)
    centre = surface.node_xyz.mean(axis=0)
    points = centre + rng.normal(scale=40.0, size=(9000, 3))
    one = surface.query(points, threads=1)
    two = surface.query(points, threads=2)
    for a, b in zip(one, two, strict=True):
        np.testing.assert_array_equal(a, b)
    assert (one[0] < 0).any() and (one[0] > 0).any()  # points inside and outside the bone


def test_block_cg_can_be_cancelled():
    n = 2000
    lap = sp.diags([-np.ones(n - 1), 2.0 * np.ones(n) + 1e-6, -np.ones(n - 1)], [-1, 0, 1])
    rhs = np.ones((n, 2))
    calls = []

    def cancel() -> bool:
        calls.append(1)
        return len(calls) > 2

    with pytest.raises(Cancelled):
        block_cg(sp.csr_matrix(lap), rhs, np.zeros_like(rhs), 1.0 / lap.diagonal(), cancel=cancel)
    assert len(calls) == 3


def test_a_cancel_during_the_write_leaves_no_deck(tmp_path, monkeypatch):
    """The write of a whole-body deck takes seconds: a cancel while it runs stops it, and
    neither the deck nor a temporary file is left (small write blocks here, so that the
    demo's write asks several times)."""
    from kneegui.demo import write_demo
    from kneegui.io import atomic, lsdyna_write
    from kneegui.io.lsdyna import read_deck
    from kneegui.reposition.pipeline import export_pose

    monkeypatch.setattr(lsdyna_write, "WRITE_BLOCK", 256)
    monkeypatch.setattr(atomic, "WRITE_CHUNK", 1 << 16)
    deck, setup_path = write_demo(tmp_path / "in", elements=2000)
    model = read_deck(deck)
    rep = Repositioner(model, load_setup(setup_path, model))
    messages: list[str] = []
    asked_while_writing = [0]

    def cancel() -> bool:
        if messages and messages[-1] == "writing the deck":
            asked_while_writing[0] += 1
            return asked_while_writing[0] >= 3  # well inside the write
        return False

    out = tmp_path / "out" / "posed.k"
    with pytest.raises(Cancelled, match="nothing written"):
        export_pose(
            rep,
            60.0,
            out,
            model_path=deck,
            force=True,
            progress=lambda fraction, message: messages.append(message),
            cancel=cancel,
        )
    assert asked_while_writing[0] == 3
    assert not out.parent.exists() or list(out.parent.iterdir()) == []


def test_the_single_steps_of_seconds_on_a_whole_body_model_ask_to_cancel(
    small_repositioner, monkeypatch
):
    """The steps that were one call each (the 1M demo: the region's energy 2.1 s, the mesh's
    edges 1.8 s, the region finding 1.4 s) ask between their parts; True stops each."""
    from kneegui.reposition import relax
    from kneegui.reposition.rigid_blend import mesh_edges
    from kneegui.topology import ELEMENT_EDGES

    rep = small_repositioner
    relaxation = rep._elastic_relaxation()
    pose = rep.pose(90.0)

    def counter():
        asked = []
        return asked, lambda: bool(asked.append(1))

    asked, count = counter()
    energy = relaxation.energy(relaxation.free, count)
    assert len(asked) >= 3
    reference = relaxation.energy(relaxation.free)
    np.testing.assert_array_equal(energy.diagonal, reference.diagonal)  # asking changes nothing
    with pytest.raises(Cancelled, match="energy"):
        relaxation.energy(relaxation.free, lambda: True)

    monkeypatch.setattr(relax, "CORNER_CHUNK", 1000)
    asked, count = counter()
    region = relaxation.degraded_region(pose, cancel=count)
    assert len(asked) == -(-len(relaxation.tets) // 1000)  # one question per chunk
    np.testing.assert_array_equal(region, relaxation.degraded_region(pose))
    with pytest.raises(Cancelled, match="region"):
        relaxation.degraded_region(pose, cancel=lambda: True)

    bone = rep.bone_pose(90.0)
    asked, count = counter()
    deep = relaxation._penetrating(pose, bone.transforms, count)
    assert len(asked) == len(relaxation.bones)  # one question per bone
    reference = relaxation._penetrating(pose, bone.transforms)
    np.testing.assert_array_equal(deep[0], reference[0])
    assert deep[1] == reference[1]
    with pytest.raises(Cancelled, match="contact"):
        relaxation._penetrating(pose, bone.transforms, lambda: True)

    model = rep.model
    masks = {etype: np.ones(len(block), dtype=bool) for etype, block in model.blocks.items()}
    asked, count = counter()
    edges = mesh_edges(model.blocks, masks, count)
    per_edge = sum(len(ELEMENT_EDGES[etype]) for etype, block in model.blocks.items() if len(block))
    assert len(asked) == len(model.blocks) + per_edge  # one sort: fewer keys than a piece
    np.testing.assert_array_equal(edges, mesh_edges(model.blocks, masks))
    with pytest.raises(Cancelled, match="edges"):
        mesh_edges(model.blocks, masks, lambda: True)


def test_the_push_out_asks_before_each_bone_and_moves_nothing_when_cancelled(
    small_repositioner,
):
    rep = small_repositioner
    contact = rep._bone_contact(rep.options.relax_contact_reach)
    pose, bone = rep.pose(90.0), rep.bone_pose(90.0)
    positions = pose.copy()
    with pytest.raises(Cancelled, match="out of the bones"):
        contact.resolve(positions, bone.transforms, lambda: True)
    np.testing.assert_array_equal(positions, pose)
    asked = []
    assert contact.resolve(positions, bone.transforms, lambda: bool(asked.append(1))) > 0
    assert len(asked) >= len(contact.surfaces)
