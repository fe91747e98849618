"""Skin contours (ALGORITHM.md §3, after Jani et al. 2012 and Jianhua et al. 1994).

The skin nodes are cut into cross-sections ("contours") along the limb: thigh contours along the
femoral axis, calf contours along the tibial axis, split by the bisector plane at the knee point
``P0``. Posing the skin takes four steps:

1. rigid step: every contour takes the rigid motion of its side's bones;
2. parallelizing: contour ``i`` rotates about the medial-lateral line through its centre ``Q_i``
   by ``w_i * theta`` (thigh +, calf -), ``theta`` = half the change of flexion and
   ``w_i = shape(1 - s_i / l)``, ``s_i = |Q_i - P0|``, ``l`` the zone length, so the contours at
   the joint meet on the bisector plane and none crosses another;
3. volume-preserving scaling: each point moves radially from ``Q_i`` by ``s = r0 / r1`` (distance
   to the segment's axis line before / after parallelizing, capped), which restores the flesh
   depth the tilt took away (anterior-posterior points stretch by up to ``1/cos``);
4. penetrations: a skin node that came closer to a bone than its clearance allows is pushed back
   out radially from its contour centre (local stretching).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from kneegui.geometry.transforms import RigidTransform
from kneegui.topology import sorted_unique

WEIGHT_SHAPES = ("linear", "cosine", "smoothstep")


def contour_weight(u: NDArray[np.float64], shape: str) -> NDArray[np.float64]:
    """Parallelizing weight for normalised distance ``u = s / l`` (1 at the joint, 0 at ``l``)."""
    x = np.clip(1.0 - u, 0.0, 1.0)
    if shape == "linear":
        return x
    if shape == "cosine":
        return 0.5 - 0.5 * np.cos(np.pi * x)
    if shape == "smoothstep":
        return x * x * (3.0 - 2.0 * x)
    raise ValueError(f"unknown weight shape {shape!r}; choose one of {WEIGHT_SHAPES}")


@dataclass(frozen=True)
class SkinContours:
    """Precomputed contour structure of the skin in the initial pose.

    Attributes
    ----------
    nodes : (K,) ndarray of int
        Skin node indices handled by the contours.
    side : (K,) ndarray of int8
        0 = thigh, 1 = calf.
    contour : (K,) ndarray of int
        Contour number of each node (thigh contours first, numbered from the joint outwards).
    n_contours : int
        Total number of contours (non-empty ones).
    contour_side : (C,) ndarray of int8
    contour_rank : (C,) ndarray of int
        Position of each contour from the joint on its side (0 = nearest).
    centers : (C, 3) ndarray
        Initial contour centres ``Q_i``.
    zone_length : (2,) ndarray
        Parallelizing zone length ``l`` of the thigh and the calf (model units).
    clearance : (K,) ndarray
        Initial distance of each skin node to the nearest bone-surface node.
    """

    nodes: NDArray[np.int64]
    side: NDArray[np.int8]
    contour: NDArray[np.int64]
    n_contours: int
    contour_side: NDArray[np.int8]
    contour_rank: NDArray[np.int64]
    centers: NDArray[np.float64]
    zone_length: NDArray[np.float64]
    clearance: NDArray[np.float64]


def build_skin_contours(
    coords: NDArray[np.float64],
    skin_nodes: NDArray[np.int64],
    knee_point: NDArray[np.float64],
    femur_dir: NDArray[np.float64],
    tibia_dir: NDArray[np.float64],
    n_contours: int,
    zone_factor: float,
    bone_surface: NDArray[np.int64],
) -> SkinContours:
    """Cut the skin into contours and measure what the pose step needs.

    Parameters
    ----------
    coords : (N, 3) ndarray
        Initial coordinates.
    skin_nodes : (K,) ndarray of int
        Skin node indices (bone-shared and fixed nodes already removed).
    knee_point : (3,) ndarray
        ``P0``, on the F-E axis mid-way between the condyles.
    femur_dir, tibia_dir : (3,) ndarray
        Unit directions of the femoral and tibial anatomical axes, distal -> proximal.
    n_contours : int
        Number of contours over the whole skin (the paper used 86).
    zone_factor : float
        Parallelizing zone length as a multiple of the mean skin radius at the joint.
    bone_surface : (B,) ndarray of int
        Bone outer-surface nodes (for the clearance of each skin node).
    """
    p = coords[skin_nodes] - knee_point
    bisector = femur_dir + tibia_dir
    bisector /= np.linalg.norm(bisector)
    side = (p @ bisector < 0).astype(np.int8)  # 1 = calf (below the bisector plane)
    s = np.where(side == 0, p @ femur_dir, -(p @ tibia_dir))
    s = np.maximum(s, 0.0)
    lengths = np.array([s[side == k].max() if np.any(side == k) else 0.0 for k in (0, 1)])
    total = max(float(lengths.sum()), 1e-9)
    n_side = np.maximum(1, np.round(n_contours * lengths / total)).astype(int)
    thickness = lengths / n_side
    rank = np.minimum((s / np.maximum(thickness[side], 1e-9)).astype(np.int64), n_side[side] - 1)
    raw = np.where(side == 0, rank, n_side[0] + rank)
    used, contour = np.unique(raw, return_inverse=True)
    contour_side = (used >= n_side[0]).astype(np.int8)
    contour_rank = np.where(contour_side == 0, used, used - n_side[0])
    counts = np.bincount(contour, minlength=len(used))
    centers = np.zeros((len(used), 3))
    for j in range(3):
        centers[:, j] = np.bincount(contour, weights=coords[skin_nodes, j], minlength=len(used))
    centers /= counts[:, None]
    # mean skin radius of the contours nearest the joint sets the zone length
    near = contour_rank <= 1
    radii = np.linalg.norm(coords[skin_nodes] - centers[contour], axis=1)
    r_joint = float(np.mean(radii[near[contour]])) if near.any() else float(radii.mean())
    zone = np.minimum(zone_factor * r_joint, np.maximum(lengths, 1e-9))
    if len(bone_surface):
        clearance, _ = cKDTree(coords[bone_surface]).query(coords[skin_nodes])
    else:
        clearance = np.full(len(skin_nodes), np.inf)
    return SkinContours(
        nodes=np.asarray(skin_nodes, dtype=np.int64),
        side=side,
        contour=contour,
        n_contours=len(used),
        contour_side=contour_side,
        contour_rank=contour_rank,
        centers=centers,
        zone_length=zone,
        clearance=clearance,
    )


def _rotate_about(points, centers, axis, angles):
    """Rotate each point about the line (center_i, axis) by angle_i (radians), vectorised."""
    v = points - centers
    c, s = np.cos(angles)[:, None], np.sin(angles)[:, None]
    k = axis[None, :]
    return centers + v * c + np.cross(k, v) * s + k * (v @ axis)[:, None] * (1.0 - c)


@dataclass(frozen=True)
class SkinPoseReport:
    """What the skin step did: parallelizing half-angle and fixes applied."""

    half_angle_deg: float
    scaled_capped: int
    penetrations_fixed: int


def pose_skin(
    contours: SkinContours,
    coords: NDArray[np.float64],
    knee_point: NDArray[np.float64],
    femur_dir: NDArray[np.float64],
    tibia_dir: NDArray[np.float64],
    fe_dir: NDArray[np.float64],
    thigh_motion: RigidTransform,
    calf_motion: RigidTransform,
    weight_shape: str = "linear",
    max_scale: float = 2.0,
    clearance_fraction: float = 0.5,
    bone_surface_posed: NDArray[np.float64] | None = None,
) -> tuple[NDArray[np.float64], SkinPoseReport]:
    """Posed coordinates of the contour skin nodes.

    Parameters
    ----------
    contours : SkinContours
        From :func:`build_skin_contours`.
    coords : (N, 3) ndarray
        Initial coordinates.
    knee_point, femur_dir, tibia_dir, fe_dir : (3,) ndarray
        ``P0``, femoral and tibial axis directions (distal -> proximal) and the F-E axis direction,
        all in the initial pose.
    thigh_motion, calf_motion : RigidTransform
        Rigid motion of the thigh's and the calf's bones from the initial pose.
    weight_shape : str
        Parallelizing weight shape, see :func:`contour_weight`.
    max_scale : float
        Cap of the volume-preserving scale factor.
    clearance_fraction : float
        A skin node closer to a bone than this fraction of its initial clearance is pushed out.
    bone_surface_posed : (B, 3) ndarray, optional
        Posed bone-surface points for the penetration check (skipped when None).

    Returns
    -------
    (K, 3) ndarray
        New positions of ``contours.nodes``.
    SkinPoseReport
    """
    nodes = contours.nodes
    x0 = coords[nodes]
    is_calf = contours.side == 1
    # 1. rigid step
    x1 = np.where(is_calf[:, None], calf_motion.apply(x0), thigh_motion.apply(x0))
    centers = np.where(
        (contours.contour_side == 1)[:, None],
        calf_motion.apply(contours.centers),
        thigh_motion.apply(contours.centers),
    )
    p0 = thigh_motion.apply(knee_point)
    l1 = thigh_motion.apply_vector(femur_dir)
    l2 = calf_motion.apply_vector(tibia_dir)
    m_thigh = thigh_motion.apply_vector(fe_dir)
    m_calf = calf_motion.apply_vector(fe_dir)

    def signed_angle(a, b, axis):
        return np.arctan2(np.cross(a, b) @ axis, a @ b)

    # theta: half the change of the signed angle from L1 to L2 about the M-L axis; rotating a
    # thigh contour by +theta about m brings its normal towards L2 (and a calf one by -theta)
    theta = 0.5 * (signed_angle(l1, l2, m_thigh) - signed_angle(femur_dir, tibia_dir, fe_dir))
    # 2. parallelizing rotation per contour
    s_i = np.linalg.norm(centers - p0, axis=1)
    zone = contours.zone_length[contours.contour_side]
    w = contour_weight(s_i / np.maximum(zone, 1e-9), weight_shape)
    ang_contour = np.where(contours.contour_side == 0, 1.0, -1.0) * w * theta
    ang = ang_contour[contours.contour]
    q = centers[contours.contour]
    x2 = np.empty_like(x1)
    for k, m in ((0, m_thigh), (1, m_calf)):
        sel = contours.side == k
        x2[sel] = _rotate_about(x1[sel], q[sel], m, ang[sel])
    # 3. volume-preserving radial scaling about Q_i
    axis_dir = np.where(is_calf[:, None], l2[None, :], l1[None, :])

    def dist_to_axis(x):
        d = x - p0
        return np.linalg.norm(d - (d * axis_dir).sum(axis=1)[:, None] * axis_dir, axis=1)

    r0, r1 = dist_to_axis(x1), dist_to_axis(x2)
    scale = np.where(r1 > 1e-9, r0 / np.maximum(r1, 1e-9), 1.0)
    scale = np.where(np.abs(ang) > 0, scale, 1.0)
    capped = int(np.count_nonzero(scale > max_scale))
    scale = np.clip(scale, 1.0 / max_scale, max_scale)
    x3 = q + scale[:, None] * (x2 - q)
    # 4. penetrations: push nodes that came too close to a bone back out from Q_i
    fixed = 0
    if bone_surface_posed is not None and len(bone_surface_posed):
        tree = cKDTree(bone_surface_posed)
        d, _ = tree.query(x3)
        limit = clearance_fraction * contours.clearance
        bad = d < limit
        fixed = int(np.count_nonzero(bad))
        for _ in range(8):
            if not bad.any():
                break
            radial = x3[bad] - q[bad]
            x3[bad] = q[bad] + radial * 1.05
            d[bad], _ = tree.query(x3[bad])
            bad = d < limit
    return x3, SkinPoseReport(float(np.degrees(theta)), capped, fixed)


def count_contour_crossings(
    contours: SkinContours,
    coords: NDArray[np.float64],
    tolerance: float = 0.0,
    reference: NDArray[np.float64] | None = None,
) -> int:
    """Number of skin nodes lying beyond the plane of the neighbouring contour nearer the joint.

    Each contour's plane is fitted to its nodes (centroid and least-squares normal, oriented away
    from the joint along the limb). A node of contour ``k + 1`` on the joint side of contour
    ``k``'s plane means the two contours cross. The first thigh and first calf contours are
    checked against each other the same way.

    Parameters
    ----------
    contours : SkinContours
        From :func:`build_skin_contours` (initial pose).
    coords : (N, 3) ndarray
        Coordinates to check (any pose).
    tolerance : float
        Distance (model units) a node may lie beyond the plane before it counts.
    reference : (N, 3) ndarray, optional
        The initial coordinates: a node counts only if it was on the right side there (a slab
        contour's fitted plane can have a node of a rough initial mesh slightly beyond it).
    """
    if reference is not None:
        before = _beyond_plane(contours, reference, tolerance)
        after = _beyond_plane(contours, coords, tolerance)
        return int(np.count_nonzero(after & ~before))
    return int(np.count_nonzero(_beyond_plane(contours, coords, tolerance)))


def _contour_pairs(contours: SkinContours) -> list[tuple[int, int]]:
    """(a, b) for each contour b and its neighbour a nearer the joint on the same side, and the
    first thigh contour with the first calf contour."""
    order = {k: np.flatnonzero(contours.contour_side == k) for k in (0, 1)}
    for k in (0, 1):
        order[k] = order[k][np.argsort(contours.contour_rank[order[k]])]
    pairs = [(a, b) for k in (0, 1) for a, b in zip(order[k][:-1], order[k][1:], strict=True)]
    if len(order[0]) and len(order[1]):
        pairs.append((order[0][0], order[1][0]))
    return pairs


def _fitted_planes(
    contours: SkinContours, coords: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Each contour's centroid (C, 3) and least-squares unit normal (C, 3) at ``coords``."""
    x = coords[contours.nodes]
    n_c = contours.n_contours
    centers = np.zeros((n_c, 3))
    counts = np.bincount(contours.contour, minlength=n_c)
    for j in range(3):
        centers[:, j] = np.bincount(contours.contour, weights=x[:, j], minlength=n_c)
    centers /= np.maximum(counts, 1)[:, None]
    normals = np.zeros((n_c, 3))
    for c in range(n_c):
        pts = x[contours.contour == c] - centers[c]
        if len(pts) >= 3:
            normals[c] = np.linalg.svd(pts, full_matrices=False)[2][-1]
    return centers, normals


def neighbour_planes(
    contours: SkinContours, coords: NDArray[np.float64], both_ways: bool = False
) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
    """For every contour node that has a neighbouring contour nearer the joint: that contour's
    plane at ``coords`` (centroid and least-squares normal of its nodes), oriented away from it
    towards the node's contour. With ``both_ways``, also every node against the plane of its
    neighbour farther from the joint, oriented back towards the joint.

    Returns
    -------
    rows : (M,) ndarray of int
        Rows of ``contours.nodes``.
    normals : (M, 3) ndarray
        Unit normals; the node is on the right side when ``normal . (x - point) >= 0``.
    offsets : (M,) ndarray
        ``normal . point`` for a point of the plane.
    """
    centers, normals = _fitted_planes(contours, coords)
    rows, out_n, out_o = [], [], []

    def add(plane: int, other: int, nodes_of: int) -> None:
        n = normals[plane] * np.sign(normals[plane] @ (centers[other] - centers[plane]) or 1.0)
        sel = np.flatnonzero(contours.contour == nodes_of)
        rows.append(sel)
        out_n.append(np.broadcast_to(n, (len(sel), 3)))
        out_o.append(np.full(len(sel), n @ centers[plane]))

    for a, b in _contour_pairs(contours):
        add(a, b, b)  # b's nodes beyond a's plane
        if both_ways:
            add(b, a, a)  # a's nodes short of b's plane
    if not rows:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 3)), np.zeros(0)
    return np.concatenate(rows), np.concatenate(out_n), np.concatenate(out_o)


def _beyond_plane(
    contours: SkinContours, coords: NDArray[np.float64], tolerance: float
) -> NDArray[np.bool_]:
    """Per contour node: lies beyond the plane of the neighbouring contour nearer the joint."""
    rows, normals, offsets = neighbour_planes(contours, coords)
    beyond = np.zeros(len(contours.nodes), dtype=bool)
    x = coords[contours.nodes[rows]]
    beyond[rows] = np.einsum("ij,ij->i", normals, x) - offsets < -tolerance
    return beyond


class ContourOrder:
    """Keeps every skin contour on its side of the neighbouring contour nearer the joint.

    As half-space constraints for :func:`kneegui.meshopt.quality_optimiser.optimise_quality`:
    each contour node must lie at least ``margin`` beyond the plane of its neighbour nearer the
    joint, and short of the plane of its neighbour farther from it (or as far as it lay in the
    initial pose, if that was less; a node already beyond it at rest is left alone), the planes
    refitted to the current coordinates whenever the constraints are asked for. Both ways,
    because a neighbour that may not move (beyond the relaxed region) must stop a contour that
    is pushed towards it.

    Parameters
    ----------
    contours : SkinContours
    rest_coords : (N, 3) ndarray
        The initial coordinates.
    margin : float
        Clearance asked beyond the neighbour's plane (model units).
    """

    def __init__(
        self, contours: SkinContours, rest_coords: NDArray[np.float64], margin: float
    ) -> None:
        self.contours = contours
        rows, normals, offsets = neighbour_planes(contours, rest_coords, both_ways=True)
        rest = np.einsum("ij,ij->i", normals, rest_coords[contours.nodes[rows]]) - offsets
        self._keep = rest >= 0.0
        self._nodes = contours.nodes[rows[self._keep]]
        self._clearance = np.minimum(rest[self._keep], margin)

    def constraints(
        self, coords: NDArray[np.float64]
    ) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
        """``(nodes, normals, offsets)``: node ``k`` should satisfy ``normal . x >= offset``."""
        _, normals, offsets = neighbour_planes(self.contours, coords, both_ways=True)
        return self._nodes, normals[self._keep], offsets[self._keep] + self._clearance

    def crossing(self, coords: NDArray[np.float64]) -> NDArray[np.int64]:
        """Contour nodes that do not keep their clearance (node indices, sorted)."""
        nodes, normals, offsets = self.constraints(coords)
        return sorted_unique(nodes[np.einsum("ij,ij->i", normals, coords[nodes]) < offsets])
