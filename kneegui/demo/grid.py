"""The structured grid of the demo leg: node positions, cell labels and shell faces.

Nodes live on a lattice of ``NK + 1`` layers; each layer holds the ``(NU + 1) x (NV + 1)`` core
nodes followed by ``NR`` rings of ``P`` nodes (ring 0 is the core boundary itself). Cells are
all the lattice hexahedra ("slots"); a label says what each one is (a bone, flesh, a ligament,
a meniscus, or void: not an element). Shells are the faces between labels where anatomy puts
them (cortical bone, skin, capsule, patellar tendon).

Positions: the core (bone column) is built in the straight pose, the femur side in the femur
frame and the tibia side in the tibia's own frame, then each rigid piece is rotated about the
flexion-extension axis (the y axis) by ``w * flexion`` with ``w`` = 0 above the joint gap and 1
below it. The meniscus top is placed under the (unrotated) femur. The skin is designed around the
straight limb and bent with a harmonic weight field (discrete Laplace on the lattice: 0 on the
femur and the thigh, 1 on the tibia, fibula and calf, the patellar share on the patella). The
rings are straight segments from the posed bone outline to the posed skin.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.sparse.linalg import cg

from kneegui.demo.design import DemoDesign, smoothstep
from kneegui.demo.layout import Layout
from kneegui.topology import ELEMENT_EDGES, SOLID_FACES

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]

# cell labels
VOID, FEMUR, TIBIA, FIBULA, PATELLA, FLESH = 0, 1, 2, 3, 4, 5
ACL, PCL, MCL, LCL, MENISCUS_LAT, MENISCUS_MED = 6, 7, 8, 9, 10, 11
BONES = (FEMUR, TIBIA, FIBULA, PATELLA)
SOFT_WITH_CAPSULE = (FLESH, MCL, LCL)


def rotate_about_y(points: FloatArray, angle: FloatArray | float) -> FloatArray:
    """Rotate points ``(..., 3)`` about the y axis by ``angle`` (rad, per point or scalar).

    Positive angles move a point below the origin towards -x (the foot goes posterior).
    """
    c, s = np.cos(angle), np.sin(angle)
    x, y, z = points[..., 0], points[..., 1], points[..., 2]
    return np.stack([c * x + s * z, y, -s * x + c * z], axis=-1)


@dataclass(frozen=True)
class Grid:
    """The generated lattice (before nodes are compacted into a Model).

    Attributes
    ----------
    layout : Layout
    coords : (n_nodes, 3) ndarray
        Final (flexed) positions of every lattice node (mm).
    weight : (n_nodes,) ndarray
        Share of the flexion each node received.
    cell_conn : (n_slots, 8) ndarray
        Lattice node indices of every cell slot (positive hex order).
    cell_label : (n_slots,) ndarray
        Label of every slot (``VOID`` = no element).
    cell_z : (n_slots,) ndarray
        Nominal mid-height of the slot's slab (straight pose), for naming flesh regions.
    shells : dict of str to (conn, owner)
        Quad shells per kind (``cortical``, ``skin``, ``capsule``, ``tendon``): node indices
        ``(m, 4)`` and the label of the cell they belong to.
    landmarks : dict
        Lattice node indices of the posterior condyle arcs and of the medial plateau centre.
    """

    layout: Layout
    coords: FloatArray
    weight: FloatArray
    cell_conn: IntArray
    cell_label: IntArray
    cell_z: FloatArray
    shells: dict
    landmarks: dict


class _Index:
    """Index arithmetic of the lattice."""

    def __init__(self, lay: Layout):
        self.lay = lay
        self.nu, self.nv, self.nr, self.nk = lay.nu, lay.nv, lay.nr, lay.nk
        self.P = lay.perimeter
        self.n_core = (self.nu + 1) * (self.nv + 1)
        self.per_layer = self.n_core + self.P * self.nr
        self.n_nodes = (self.nk + 1) * self.per_layer
        self.core_cells = self.nu * self.nv
        self.slot_per_slab = self.core_cells + self.P * self.nr
        self.n_slots = self.nk * self.slot_per_slab
        # perimeter node p -> core (i, j)
        nu, nv = self.nu, self.nv
        bi = np.concatenate(
            [np.arange(nu), np.full(nv, nu), np.arange(nu, 0, -1), np.zeros(nv, dtype=np.int64)]
        )
        bj = np.concatenate(
            [np.zeros(nu, dtype=np.int64), np.arange(nv), np.full(nu, nv), np.arange(nv, 0, -1)]
        )
        self.perim_i, self.perim_j = bi.astype(np.int64), bj.astype(np.int64)
        self.perim_core = self.perim_i * (nv + 1) + self.perim_j  # in-layer core node index

    def core_node(self, k, i, j):
        return np.asarray(k) * self.per_layer + np.asarray(i) * (self.nv + 1) + np.asarray(j)

    def ring_node(self, k, r, p):
        """Lattice node of ring ``r`` (0 = core boundary) at perimeter position ``p``."""
        k, r, p = np.broadcast_arrays(np.asarray(k), np.asarray(r), np.asarray(p) % self.P)
        inner = k * self.per_layer + self.perim_core[p]
        outer = k * self.per_layer + self.n_core + (np.maximum(r, 1) - 1) * self.P + p
        return np.where(r == 0, inner, outer)

    def ring_cell_side(self, p: IntArray) -> tuple[IntArray, IntArray]:
        """Side (0 lateral, 1 anterior, 2 medial, 3 posterior) and row/column of ring cell p."""
        nu, nv = self.nu, self.nv
        p = np.asarray(p)
        side = np.select([p < nu, p < nu + nv, p < 2 * nu + nv], [0, 1, 2], 3)
        idx = np.select(
            [side == 0, side == 1, side == 2],
            [p, p - nu, nu - 1 - (p - nu - nv)],
            nv - 1 - (p - 2 * nu - nv),
        )
        return side, idx


# ---------------------------------------------------------------------------------- shapes
def _bulged_square(centre, radius, s, t, bulge=0.6):
    """Sides of a square with outward-bulged edges around ``centre`` (a round bone section).

    Returns posterior (i=0) and anterior (i=NU) sides sampled at ``t``, lateral (j=0) and
    medial (j=NV) sides sampled at ``s``; the corners are real corners (about 140 degrees), as an
    O-grid core needs.
    """
    cx, cy = centre
    a = radius * np.sqrt(0.5)
    sag = bulge * radius * (1 - np.sqrt(0.5))
    c00, c10 = np.array([cx - a, cy - a]), np.array([cx + a, cy - a])
    c01, c11 = np.array([cx - a, cy + a]), np.array([cx + a, cy + a])
    bt = (4 * t * (1 - t))[:, None]
    bs = (4 * s * (1 - s))[:, None]
    post = c00 + t[:, None] * (c01 - c00) + sag * bt * np.array([-1.0, 0.0])
    ant = c10 + t[:, None] * (c11 - c10) + sag * bt * np.array([1.0, 0.0])
    lat = c00 + s[:, None] * (c10 - c00) + sag * bs * np.array([0.0, -1.0])
    med = c01 + s[:, None] * (c11 - c01) + sag * bs * np.array([0.0, 1.0])
    return post, ant, lat, med


def _pull_corners(sides, corners, depth, length, y_only=False):
    """Round corners: move every side point towards the middle by a Gaussian bump of ``depth``
    (mm) and width ``length`` (mm) around each corner (a smooth field, so sides stay consistent
    at shared corners and nothing folds)."""
    allpts = np.vstack(sides)
    centre = allpts.mean(axis=0)
    out = []
    for pts in sides:
        moved = pts.copy()
        for c in corners:
            u = (centre - c) / np.linalg.norm(centre - c)
            if y_only:
                u = np.array([0.0, np.sign(u[1])])
            bump = np.exp(-np.sum((pts - c) ** 2, axis=1) / length**2)
            moved += depth * bump[:, None] * u
        out.append(moved)
    return tuple(out)


def _tfi(post, ant, lat, med, s, t):
    """Transfinite interpolation of a quadrilateral patch from its four sides: (NU+1, NV+1, 2)."""
    S = s[:, None, None]
    T = t[None, :, None]
    c00, c01, c10, c11 = post[0], post[-1], ant[0], ant[-1]
    return (
        (1 - S) * post[None]
        + S * ant[None]
        + (1 - T) * lat[:, None]
        + T * med[:, None]
        - ((1 - S) * (1 - T) * c00 + (1 - S) * T * c01 + S * (1 - T) * c10 + S * T * c11)
    )


def _ray_to_ellipse(origin, points, ellipse):
    """Where rays from ``origin`` (2,) through ``points`` (n, 2) leave the ellipse
    ``(cx, cy, a, b)``."""
    cx, cy, a, b = ellipse
    d = points - origin
    o = origin - np.array([cx, cy])
    qa = (d[:, 0] / a) ** 2 + (d[:, 1] / b) ** 2
    qb = 2 * (o[0] * d[:, 0] / a**2 + o[1] * d[:, 1] / b**2)
    qc = (o[0] / a) ** 2 + (o[1] / b) ** 2 - 1.0
    tau = (-qb + np.sqrt(qb * qb - 4 * qa * qc)) / (2 * qa)
    return origin + tau[:, None] * d


def _smooth_along(values: FloatArray, z: FloatArray, sigma: float) -> FloatArray:
    """Gaussian smoothing of per-layer values ``(NK + 1, ...)`` along the nominal height."""
    w = np.exp(-0.5 * ((z[:, None] - z[None, :]) / sigma) ** 2)
    w /= w.sum(axis=1, keepdims=True)
    return np.tensordot(w, values, axes=(1, 0))


def _smooth_index(z: FloatArray, sigma: float) -> FloatArray:
    """Gaussian smoothing of a monotonic sequence over its index, ends kept in place."""
    n = len(z)
    i = np.arange(n)
    w = np.exp(-0.5 * ((i[:, None] - i[None, :]) / sigma) ** 2)
    # mirror-free: smooth the increments, then rescale them to keep both ends fixed
    dz = np.diff(z)
    dzs = (w[:-1, :-1] @ dz) / w[:-1, :-1].sum(axis=1)
    dzs *= (z[-1] - z[0]) / dzs.sum()
    return np.concatenate([[z[0]], z[0] + np.cumsum(dzs)])


def _soft_skin(origin, bone_xy, ellipse, t_min):
    """Skin points on the rays origin -> bone: the ellipse, kept at least about ``t_min`` away
    from the bone by a smooth maximum (the skin bulges over bones that come close to it)."""
    on_ellipse = _ray_to_ellipse(origin, bone_xy, ellipse)
    ray = bone_xy - origin
    length = np.linalg.norm(ray, axis=1)
    direction = ray / length[:, None]
    d = np.einsum("ij,ij->i", on_ellipse - bone_xy, direction)  # signed: < 0 if bone sticks out
    d_pos = 0.5 * (d + np.sqrt(d * d + 16.0))
    d_new = (d_pos**4 + t_min**4) ** 0.25
    return bone_xy + d_new[:, None] * direction


# ---------------------------------------------------------------------------------- builder
def build_grid(design: DemoDesign, lay: Layout) -> Grid:
    """Build the lattice of the demo leg for one layout.

    Parameters
    ----------
    design : DemoDesign
        Anatomy.
    lay : Layout
        Block counts.

    Returns
    -------
    Grid
    """
    ix = _Index(lay)
    zn = lay.nominal_z()
    k_slab = {name: lay.slabs.range(name) for name in lay.slabs.names}
    k_tc0 = k_slab["tibcond"][0]
    k_tp = k_slab["men"][0]  # tibia top layer
    k_mt = k_slab["void"][0]  # meniscus top layer
    k_fb = k_slab["void"][1]  # femur bottom layer
    k_n1 = k_slab["notch1"][1]  # top of the blended distal layers

    s_uniform = np.linspace(0.0, 1.0, ix.nu + 1)
    t_uniform = np.linspace(0.0, 1.0, ix.nv + 1)
    s_knee = lay.rows.params(lay.row_fractions())
    t_knee = lay.cols.params(lay.col_fractions())
    # medial weight of each core column: 0 up to the lateral notch wall, 1 from the medial one
    j_nl = lay.cols.start("vgap1")
    j_nm = lay.cols.stop("vgap2")
    jj = np.arange(ix.nv + 1)
    w_med = np.clip((t_knee - t_knee[j_nl]) / (t_knee[j_nm] - t_knee[j_nl]), 0.0, 1.0)
    w_med[jj <= j_nl] = 0.0
    w_med[jj >= j_nm] = 1.0

    core = np.zeros((lay.nk + 1, ix.nu + 1, ix.nv + 1, 3))
    for k in range(lay.nk + 1):
        if k >= k_fb:
            core[k] = _femur_layer(
                design, zn, k, k_fb, k_n1, s_uniform, t_uniform, s_knee, t_knee, w_med
            )
        elif k <= k_tp:
            core[k] = _tibia_layer(
                design, zn, k, k_tc0, k_tp, s_uniform, t_uniform, s_knee, t_knee, w_med
            )
    # meniscus top: just below the femur (after flexion), limited in height; tibia frame
    phi = design.flexion_rad
    tp_world = rotate_about_y(core[k_tp], phi)
    void_gap = _void_gap(design, core[k_fb], ix)
    target = core[k_fb].copy()
    target[..., 2] = np.minimum(
        core[k_fb][..., 2] - void_gap,
        tp_world[..., 2] + design.meniscus_height_limit(tp_world[..., 0]),
    )
    core[k_mt] = rotate_about_y(target, -phi)
    for k in range(k_tp + 1, k_mt):
        a = (k - k_tp) / (k_mt - k_tp)
        core[k] = (1 - a) * core[k_tp] + a * core[k_mt]

    labels, cell_z = _labels(lay, ix, zn)
    conn = _cell_connectivity(ix)
    weight = _flexion_weights(design, lay, ix, zn, labels, conn, k_mt, k_fb)
    w_grid = weight.reshape(lay.nk + 1, ix.per_layer)
    w_skin = w_grid[:, ix.n_core + (lay.nr - 1) * ix.P :]  # (NK+1, P)

    # core nodes: rigid pieces, femur frame above the joint gap, tibia frame below
    core_final = rotate_about_y(core, w_grid[:, : ix.n_core].reshape(core.shape[:3]) * phi)
    coords = np.zeros((ix.n_nodes, 3))
    layers = coords.reshape(lay.nk + 1, ix.per_layer, 3)
    layers[:, : ix.n_core] = core_final.reshape(lay.nk + 1, ix.n_core, 3)
    # skin: designed around the straight limb, bent with the harmonic flexion weights;
    # rays to the skin start from a smoothed bone outline so that the skin stays smooth where
    # the bone outline changes abruptly (joint gap, notch)
    bnd_straight = core.reshape(lay.nk + 1, -1, 3)[:, ix.perim_core]  # (NK+1, P, 3)
    smooth_xy = _smooth_along(bnd_straight[..., :2], zn, sigma=14.0)
    origins = smooth_xy.mean(axis=1)
    # the skin's layer heights: the nominal ones evened out over a few layers, so that thin
    # joint slabs open up towards the skin
    z_skin = _smooth_index(zn, 2.0)
    skin = np.zeros((lay.nk + 1, ix.P, 3))
    thickness = np.zeros((lay.nk + 1, ix.P))
    for k in range(lay.nk + 1):
        skin[k, :, :2] = _soft_skin(
            origins[k], smooth_xy[k], design.skin_ellipse(zn[k]), design.min_flesh_thickness
        )
        skin[k, :, 2] = z_skin[k]
        thickness[k] = np.linalg.norm(skin[k, :, :2] - bnd_straight[k, :, :2], axis=1)
    skin = rotate_about_y(skin, w_skin * phi)
    # rings: straight segments from the (posed) bone outline to the (posed) skin
    bnd = core_final.reshape(lay.nk + 1, -1, 3)[:, ix.perim_core]
    contexts = _ring_contexts(lay, ix, zn)
    for k in range(lay.nk + 1):
        g = _ring_fractions(lay, *(c[k] for c in contexts), thickness[k])  # (NR, P)
        ring = bnd[k][None] + g[..., None] * (skin[k] - bnd[k])[None]
        layers[k, ix.n_core :] = ring.reshape(-1, 3)

    shells = _shells(lay, ix, conn, labels)
    landmarks = _landmarks(design, lay, ix, coords, k_fb, k_tp, j_nl, j_nm)
    return Grid(lay, coords, weight, conn, labels, cell_z, shells, landmarks)


def free_flesh_nodes(grid: Grid) -> NDArray[np.bool_]:
    """Lattice nodes that may move without changing the anatomy, ``(n_nodes,)`` bool.

    A node is free when every element around it is flesh (no bone, ligament or meniscus; the
    joint cavity may border it) and it lies neither on the skin (outermost ring) nor on the two
    cuts (first and last layer). Such nodes are interior to the flesh or on the capsule: moving
    them a little changes only the shape of flesh elements (and of the capsule and patellar
    tendon shells that lie on the flesh).
    """
    lay = grid.layout
    ix = _Index(lay)
    n = len(grid.coords)
    in_flesh = np.zeros(n, dtype=bool)
    elsewhere = np.zeros(n, dtype=bool)
    flesh = grid.cell_label == FLESH
    other = ~flesh & (grid.cell_label != VOID)
    in_flesh[grid.cell_conn[flesh].ravel()] = True
    elsewhere[grid.cell_conn[other].ravel()] = True
    node = np.arange(n)
    layer, in_layer = node // ix.per_layer, node % ix.per_layer
    on_skin = in_layer >= ix.n_core + (lay.nr - 1) * ix.P
    on_cut = (layer == 0) | (layer == lay.nk)
    return in_flesh & ~elsewhere & ~on_skin & ~on_cut


def _void_gap(design: DemoDesign, femur_bottom: FloatArray, ix: _Index) -> float:
    """Gap between meniscus top and femur: about 1/6 of the knee's perimeter cell size, >= 1 mm."""
    bnd = femur_bottom.reshape(-1, 3)[ix.perim_core]
    perim = np.linalg.norm(np.diff(np.vstack([bnd, bnd[:1]]), axis=0), axis=1).sum()
    return max(2.0, perim / ix.P / 4.0)


def _femur_layer(design, zn, k, k_fb, k_n1, s_u, t_u, s_k, t_k, w_med):
    z = zn[k]
    beta = float(design.femur_knee_weight(z))
    s = (1 - beta) * s_u + beta * s_k
    t = (1 - beta) * t_u + beta * t_k
    in_blend = k_fb <= k <= k_n1
    tau = (k - k_fb) / (k_n1 - k_fb) if in_blend else 1.0
    # knee (condylar) shape
    y_lat, y_med = design.femur_side_y(z)
    y_side = y_lat + t * (y_med - y_lat)
    if in_blend:
        z_post = (1 - tau) * design.distal_flat_z(w_med) + tau * zn[k_n1]
    else:
        z_post = np.full_like(t, z)
    post = np.column_stack([design.posterior_femur_x(w_med, z_post), y_side])
    ant = np.column_stack([design.anterior_femur_x(y_side), y_side])
    bs = 4 * s * (1 - s)
    x_lat = post[0, 0] + s * (ant[0, 0] - post[0, 0])
    x_med = post[-1, 0] + s * (ant[-1, 0] - post[-1, 0])
    lat = np.column_stack([x_lat, y_lat - 1.5 * bs])
    med = np.column_stack([x_med, y_med + 1.5 * bs])
    # anterior corners rounded (the trochlear facets fall away at the sides)
    knee = _pull_corners((post, ant, lat, med), (ant[0].copy(), ant[-1].copy()), 5.0, 12.0)
    shaft = _bulged_square(design.femur_shaft_centre, design.femur_shaft_radius, s, t)
    sides = [beta * a + (1 - beta) * b for a, b in zip(knee, shaft, strict=True)]
    xy = _tfi(*sides, s, t)
    if in_blend:
        zz = (1 - tau) * design.distal_femur_z(xy[..., 0], w_med[None, :]) + tau * zn[k_n1]
        zz[0, :] = z_post  # exactly the arc height on the posterior side
    else:
        zz = np.full(xy.shape[:2], z)
    return np.concatenate([xy, zz[..., None]], axis=-1)


def _tibia_layer(design, zn, k, k_tc0, k_tp, s_u, t_u, s_k, t_k, w_med):
    z = zn[k]
    beta = float(design.tibia_knee_weight(z))
    s = (1 - beta) * s_u + beta * s_k
    t = (1 - beta) * t_u + beta * t_k
    d = design
    y_side = d.plateau_lateral_y + t * (d.plateau_medial_y - d.plateau_lateral_y)
    bt = 4 * t * (1 - t)
    bs = 4 * s * (1 - s)
    # corners rounded: sides bulge out, ends pulled in (real corners remain for the O-grid)
    post = np.column_stack([d.plateau_posterior_x - 1.0 * bt, y_side])
    ant = np.column_stack([d.plateau_anterior_x + 1.0 * bt, y_side])
    xs = post[0, 0] + s * (ant[0, 0] - post[0, 0])
    lat = np.column_stack([xs, d.plateau_lateral_y - 1.0 * bs])
    med = np.column_stack([xs, d.plateau_medial_y + 1.0 * bs])
    knee = _pull_corners((post, ant, lat, med), (ant[0].copy(), ant[-1].copy()), 4.0, 12.0)
    shaft = _bulged_square(d.tibia_shaft_centre, float(d.tibia_shaft_radius_at(z)), s, t)
    sides = [beta * a + (1 - beta) * b for a, b in zip(knee, shaft, strict=True)]
    xy = _tfi(*sides, s, t)
    if k_tc0 <= k <= k_tp:
        tau = (k - k_tc0) / (k_tp - k_tc0)
        zz = (1 - tau) * zn[k_tc0] + tau * d.plateau_z(xy[..., 0], xy[..., 1], w_med[None, :])
    else:
        zz = np.full(xy.shape[:2], z)
    return np.concatenate([xy, zz[..., None]], axis=-1)


def _sector_nodes(ix: _Index, cell_mask: NDArray[np.bool_], spread: int) -> FloatArray:
    """0..1 weight on perimeter nodes: 1 on the nodes of the masked ring cells, falling linearly
    to 0 over ``spread`` cells on each side (periodic)."""
    cell = cell_mask.astype(bool)
    node = cell | np.roll(cell, 1)  # node p touches cells p-1 and p
    inside = np.flatnonzero(node)
    if len(inside) == 0:
        return np.zeros(ix.P)
    p = np.arange(ix.P)
    gap = np.abs(p[:, None] - inside[None, :])
    gap = np.minimum(gap, ix.P - gap).min(axis=1)
    return np.clip(1.0 - gap / (spread + 1.0), 0.0, 1.0)


def _ring_contexts(lay: Layout, ix: _Index, zn: FloatArray) -> tuple[FloatArray, ...]:
    """Weights ``(NK + 1, P)`` of the ring-distribution contexts.

    ``anterior``: front of the knee, where the mid ring block holds the patella and the patellar
    tendon runs along its outer face; ``gap``: the patella's levels, where the inner block is the
    thin patello-femoral gap; ``fibula``: the postero-lateral calf, where the mid block is the
    fibula.
    """
    side, idx = ix.ring_cell_side(np.arange(ix.P))
    spread = max(2, round(0.08 * ix.P))
    c0, c1 = lay.cols.range("lat_nw", "med_nw")
    ant = _sector_nodes(ix, (side == 1) & (idx >= c0) & (idx < c1), spread)
    r0, r1 = lay.rows.range("pcl", "acl")
    f0, f1 = lay.cols.range("lat_rim") if lay.cols.counts[0] else (0, 1)
    fib = _sector_nodes(
        ix,
        ((side == 0) & (idx >= r0) & (idx < r1)) | ((side == 3) & (idx >= f0) & (idx < f1)),
        spread,
    )
    z_ant = smoothstep((zn + 45.0) / 30.0) * (1.0 - smoothstep((zn - 50.0) / 35.0))
    z_gap = smoothstep((zn + 12.0) / 14.0) * (1.0 - smoothstep((zn - 45.0) / 20.0))
    z_fib = 1.0 - smoothstep((zn + 38.0) / 30.0)
    return (
        z_ant[:, None] * ant[None, :],
        z_gap[:, None] * np.ones(ix.P)[None, :],
        z_fib[:, None] * fib[None, :],
    )


#: Ring fractions (end of inner block, end of mid block) by context.
RING_SPLIT_DEFAULT = (0.14, 0.30)
RING_SPLIT_ANTERIOR = (0.30, 0.74)
RING_SPLIT_PF_GAP = 0.16
RING_SPLIT_FIBULA = (0.15, 0.45)


def _ring_fractions(
    lay: Layout, a_ant: FloatArray, a_gap: FloatArray, a_fib: FloatArray, thickness: FloatArray
) -> FloatArray:
    """Fraction of the way bone -> skin of the ring nodes of one layer, ``(NR, P)``.

    Three blocks (inner, mid, outer) whose split points blend between the default and the
    context splits; spacing is uniform inside the inner and mid blocks and, in the default
    context, grows geometrically through the outer block. Where the flesh is thin
    (``thickness``, mm) the default becomes uniform, so that thin flesh is not cut into slivers.
    """
    n_in, n_mid, n_out = lay.rings.counts
    r = np.arange(1, lay.nr + 1)[:, None]
    thick = smoothstep((thickness - 20.0) / 40.0)
    uniform = np.array([n_in / lay.nr, (n_in + n_mid) / lay.nr])[:, None]
    default = (1 - thick[None, :]) * uniform + thick[None, :] * np.array(RING_SPLIT_DEFAULT)[
        :, None
    ]
    fibula = (1 - thick[None, :]) * uniform + thick[None, :] * np.array(RING_SPLIT_FIBULA)[:, None]
    rest = 1 - a_ant - a_fib
    g_in = default[0] * rest + a_fib * fibula[0]
    g_in = g_in + a_ant * ((1 - a_gap) * RING_SPLIT_ANTERIOR[0] + a_gap * RING_SPLIT_PF_GAP)
    g_mid = default[1] * rest + a_fib * fibula[1] + a_ant * RING_SPLIT_ANTERIOR[1]
    g_in, g_mid = g_in[None, :], g_mid[None, :]
    q = (1.0 + 2.0 * thick * rest) ** (1.0 / n_out) + 1e-9  # outermost ring up to 3x the first
    m = np.clip(r - n_in - n_mid, 0, None)
    outer = (q**m - 1.0) / (q**n_out - 1.0)
    return np.where(
        r <= n_in,
        g_in * r / n_in,
        np.where(
            r <= n_in + n_mid,
            g_in + (g_mid - g_in) * (r - n_in) / n_mid,
            g_mid + (1 - g_mid) * outer,
        ),
    )


def _cell_connectivity(ix: _Index) -> IntArray:
    """Lattice node indices ``(n_slots, 8)`` of every cell, positive hex order."""
    nu, nv, nr, nk, P = ix.nu, ix.nv, ix.nr, ix.nk, ix.P
    k, i, j = np.meshgrid(np.arange(nk), np.arange(nu), np.arange(nv), indexing="ij")
    k, i, j = k.reshape(nk, -1), i.reshape(nk, -1), j.reshape(nk, -1)
    bottom = [
        ix.core_node(k, i, j),
        ix.core_node(k, i + 1, j),
        ix.core_node(k, i + 1, j + 1),
        ix.core_node(k, i, j + 1),
    ]
    core = np.stack(bottom + [b + ix.per_layer for b in bottom], axis=-1)  # (nk, nu*nv, 8)
    k, r, p = np.meshgrid(np.arange(nk), np.arange(nr), np.arange(P), indexing="ij")
    k, r, p = k.reshape(nk, -1), r.reshape(nk, -1), p.reshape(nk, -1)
    bottom = [
        ix.ring_node(k, r, p),
        ix.ring_node(k, r + 1, p),
        ix.ring_node(k, r + 1, p + 1),
        ix.ring_node(k, r, p + 1),
    ]
    ring = np.stack(bottom + [b + ix.per_layer for b in bottom], axis=-1)
    return np.concatenate([core, ring], axis=1).reshape(-1, 8).astype(np.int64)


def _labels(lay: Layout, ix: _Index, zn: FloatArray) -> tuple[IntArray, FloatArray]:
    """Label of every cell slot, and the nominal mid-z of its slab."""
    nk, nu, nv, nr, P = lay.nk, ix.nu, ix.nv, ix.nr, ix.P
    slab_name = np.empty(nk, dtype=object)
    for name in lay.slabs.names:
        a, b = lay.slabs.range(name)
        slab_name[a:b] = name
    zmid = 0.5 * (zn[:-1] + zn[1:])

    def in_slabs(*names):
        return np.isin(slab_name, names)

    R, C = lay.rows, lay.cols
    ii, jj = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")

    def rows_in(*names):
        out = np.zeros_like(ii, dtype=bool)
        for n in names:
            a, b = R.range(n)
            out |= (ii >= a) & (ii < b)
        return out

    def cols_in(*names):
        out = np.zeros_like(jj, dtype=bool)
        for n in names:
            a, b = C.range(n)
            out |= (jj >= a) & (jj < b)
        return out

    notch = rows_in("pcl", "ugap", "acl") & cols_in("vgap1", "lig", "vgap2")
    acl = rows_in("acl") & cols_in("lig")
    pcl = rows_in("pcl") & cols_in("lig")
    lat_comp = cols_in("lat_rim", "lat_out", "lat_nw")
    med_comp = cols_in("med_nw", "med_out", "med_rim")
    lat_rim = cols_in("lat_rim") if C.counts[0] else (jj == 0)
    med_rim = cols_in("med_rim") if C.counts[-1] else (jj == nv - 1)
    horns = rows_in("pcl", "ant")
    men_lat = lat_comp & (lat_rim | horns)
    men_med = med_comp & (med_rim | horns)

    core = np.zeros((nk, nu, nv), dtype=np.int64)
    core[in_slabs("calf", "tibmeta", "tub", "tibcond")] = TIBIA
    femur_slabs = in_slabs("notch1", "notch2", "cond", "pat", "femmeta", "thigh")
    core[femur_slabs] = FEMUR
    core[in_slabs("notch1", "notch2")] = np.where(notch, VOID, FEMUR)
    joint = in_slabs("men", "void", "notch1", "notch2")
    core[in_slabs("men")] = np.where(men_lat, MENISCUS_LAT, np.where(men_med, MENISCUS_MED, VOID))
    core[in_slabs("void")] = VOID
    for lab, mask in ((ACL, acl), (PCL, pcl)):
        sel = core[joint]
        sel[:, mask] = lab
        core[joint] = sel

    # rings
    ring = np.full((nk, nr, P), FLESH, dtype=np.int64)
    side, idx = ix.ring_cell_side(np.arange(P))
    rr = np.arange(nr)[:, None]
    n_in, n_mid, _ = lay.rings.counts
    inner = rr < n_in
    mid = (rr >= n_in) & (rr < n_in + n_mid)

    def on_side(s, block_range):
        a, b = block_range
        return (side == s) & (idx >= a) & (idx < b)

    patella_sector = on_side(1, C.range("lat_nw", "med_nw"))
    tendon_sector = on_side(1, C.range("vgap1", "vgap2"))
    fib_rows = R.range("pcl", "acl")
    fib_cols = C.range("lat_rim") if C.counts[0] else (0, 1)
    fibula_sector = on_side(0, fib_rows) | on_side(3, fib_cols)
    lcl_sector = on_side(0, R.range("acl"))
    mcl_sector = on_side(2, R.range("acl"))

    def put(slab_mask, ring_mask, sector, label):
        block = ring[slab_mask]
        block[:, ring_mask & sector[None, :]] = label
        ring[slab_mask] = block

    put(in_slabs("calf", "tibmeta", "tub"), mid, fibula_sector, FIBULA)
    put(in_slabs("tub"), inner | mid, tendon_sector, TIBIA)  # tibial tuberosity
    put(in_slabs("notch2", "cond", "pat"), mid, patella_sector, PATELLA)
    put(in_slabs("notch2", "cond", "pat"), inner, patella_sector, VOID)
    put(in_slabs("tibcond", "men", "void"), mid, lcl_sector, LCL)
    put(in_slabs("notch1", "notch2", "cond"), inner | mid, lcl_sector, LCL)
    put(
        in_slabs("tibmeta", "tub", "tibcond", "men", "void", "notch1", "notch2", "cond"),
        inner,
        mcl_sector,
        MCL,
    )

    labels = np.concatenate([core.reshape(nk, -1), ring.reshape(nk, -1)], axis=1).reshape(-1)
    cell_z = np.repeat(zmid, ix.slot_per_slab)
    return labels, cell_z


def _flexion_weights(design, lay, ix, zn, labels, conn, k_mt, k_fb) -> FloatArray:
    """Share of the flexion every lattice node gets (0 femur side, 1 tibia side)."""
    n = ix.n_nodes
    fixed = np.zeros(n, dtype=bool)
    value = np.zeros(n)
    layer = np.arange(n) // ix.per_layer
    in_core = (np.arange(n) % ix.per_layer) < ix.n_core
    # core nodes: rigid pieces by layer (femur frame above the joint gap, tibia frame below)
    fixed[in_core] = True
    value[in_core & (layer <= k_mt)] = 1.0
    # far from the knee: thigh 0, calf 1
    far_hi, far_lo = 150.0, -160.0
    fixed |= (zn[layer] >= far_hi) | (zn[layer] <= far_lo)
    value[zn[layer] <= far_lo] = 1.0
    # bones in the rings: fibula and tuberosity follow the tibia; the patella its own share
    for lab, w in ((FIBULA, 1.0), (TIBIA, 1.0), (PATELLA, design.patellar_flexion_ratio)):
        nodes = np.unique(conn[labels == lab])
        fixed[nodes] = True
        value[nodes] = w
    # harmonic interpolation on the lattice graph (ring nodes between the fixed ones)
    edges = np.sort(np.concatenate([conn[:, [a, b]] for a, b in ELEMENT_EDGES["hex8"]]), axis=1)
    code = np.unique(edges[:, 0] * np.int64(n) + edges[:, 1])
    edges = np.column_stack([code // n, code % n])
    free = np.flatnonzero(~fixed)
    if len(free) == 0:
        return value
    pos = np.full(n, -1)
    pos[free] = np.arange(len(free))
    deg = np.bincount(edges.ravel(), minlength=n).astype(float)
    a, b = edges[:, 0], edges[:, 1]
    rows, cols, vals = [], [], []
    rhs = np.zeros(len(free))
    for u, v in ((a, b), (b, a)):
        fu = pos[u] >= 0
        both = fu & (pos[v] >= 0)
        rows.append(pos[u[both]])
        cols.append(pos[v[both]])
        vals.append(-np.ones(both.sum()))
        bnd = fu & (pos[v] < 0)
        np.add.at(rhs, pos[u[bnd]], value[v[bnd]])
    rows.append(np.arange(len(free)))
    cols.append(np.arange(len(free)))
    vals.append(deg[free])
    lap = sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
        shape=(len(free), len(free)),
    )
    guess = smoothstep((60.0 - zn[layer[free]]) / 120.0)
    sol, _info = cg(lap, rhs, x0=guess, rtol=1e-9, maxiter=5000)
    value[free] = np.clip(sol, 0.0, 1.0)
    return value


def _shells(lay: Layout, ix: _Index, conn: IntArray, labels: IntArray) -> dict:
    """Quad shells on the faces between labels: cortical, skin, capsule, tendon."""
    n_slots = len(conn)
    faces = conn[:, np.array(SOLID_FACES["hex8"])].reshape(-1, 4)  # outward from their cell
    owner = np.repeat(np.arange(n_slots), 6)
    key = np.sort(faces, axis=1)[:, :3]  # three corners identify a face of a conforming grid
    n = np.int64(conn.max() + 1)
    if float(n) ** 3 < 2.0**62:
        code = (key[:, 0] * n + key[:, 1]) * n + key[:, 2]
        order = np.argsort(code, kind="stable")
        code_s = code[order]
        same_next = code_s[1:] == code_s[:-1]
    else:
        order = np.lexsort(key.T[::-1])
        key_s = key[order]
        same_next = np.all(key_s[1:] == key_s[:-1], axis=1)
    other = np.full(len(faces), -1)
    first = order[:-1][same_next]
    second = order[1:][same_next]
    other[first] = owner[second]
    other[second] = owner[first]
    lab_a = labels[owner]
    lab_b = np.where(other >= 0, labels[np.maximum(other, 0)], -1)
    out = {}
    is_bone = np.isin(lab_a, BONES)
    cortical = is_bone & (lab_b != lab_a)
    out["cortical"] = (faces[cortical], lab_a[cortical])
    # skin: outer faces of the outermost ring
    slot_in_slab = owner % ix.slot_per_slab
    ring_r = np.where(slot_in_slab >= ix.core_cells, (slot_in_slab - ix.core_cells) // ix.P, -1)
    face_no = np.tile(np.arange(6), n_slots)
    # ring cell face 3 is (1,2,6,5): nodes at ring r+1 -> the outer face
    skin = (ring_r == ix.nr - 1) & (face_no == 3) & (lab_a != VOID)
    out["skin"] = (faces[skin], lab_a[skin])
    capsule = np.isin(lab_a, SOFT_WITH_CAPSULE) & (lab_b == VOID)
    out["capsule"] = (faces[capsule], lab_a[capsule])
    # tendon: outer faces of the mid ring block in the tendon sector, tuberosity -> patella
    n_in, n_mid, _ = lay.rings.counts
    p = (slot_in_slab - ix.core_cells) % ix.P
    side, idx = ix.ring_cell_side(p)
    c0, c1 = lay.cols.range("vgap1", "vgap2")
    slab = owner // ix.slot_per_slab
    k0 = lay.slabs.start("tibcond")
    k1 = lay.slabs.stop("notch1")
    tendon = (
        (ring_r == n_in + n_mid - 1)
        & (face_no == 3)
        & (side == 1)
        & (idx >= c0)
        & (idx < c1)
        & (slab >= k0)
        & (slab < k1)
        & (lab_a != VOID)
    )
    out["tendon"] = (faces[tendon], lab_a[tendon])
    return out


def _landmarks(design, lay, ix, coords, k_fb, k_tp, j_nl, j_nm) -> dict:
    """Posterior condyle arc nodes and the medial plateau centre node (lattice indices)."""
    out = {}
    for name, js, radius in (
        ("lateral_condyle", np.arange(0, j_nl + 1), design.lateral_radius),
        ("medial_condyle", np.arange(j_nm, ix.nv + 1), design.medial_radius),
    ):
        z_top = radius * np.sin(np.radians(design.posterior_arc_top_deg))
        nodes = []
        for k in range(k_fb, lay.nk + 1):
            idx = ix.core_node(k, 0, js)
            if np.all(coords[idx, 2] <= z_top + 1e-9):
                nodes.append(idx)
        out[name] = np.concatenate(nodes)
    # medial plateau: tibia-top node nearest the medial compartment's contact centre
    i_all = np.arange(ix.nu + 1)
    j_all = np.arange(j_nm, ix.nv + 1)
    cand = ix.core_node(k_tp, i_all[:, None], j_all[None, :]).ravel()
    target = rotate_about_y(np.array([8.0, 24.0, 0.0]), design.flexion_rad)[:2]
    best = cand[np.argmin(np.linalg.norm(coords[cand, :2] - target, axis=1))]
    out["medial_plateau"] = int(best)
    return out
