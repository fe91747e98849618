"""A small synthetic knee (boxes and cylinders) with a known answer, for tests and examples.

Not anatomy: a femur shaft (hexes) with two condyle "wheels" (quad shells whose rims are exact
circles of the given radii about a common medial-lateral axis), a tibia shaft flexed by
``flexion_deg`` about that axis, a fibula, a patella, flesh and skin. Built in the subject frame
(x anterior, y subject's left, z superior, knee joint point at the origin), then mirrored for a
left knee and moved by an arbitrary rigid ``rotation`` / ``translation``, so code under test can
not rely on global axes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from kneegui.geometry.transforms import rotation_matrix
from kneegui.model import ElementBlock, Model, Part
from kneegui.topology import MIRRORED_NODE_ORDER

PART_TITLES = {
    101: "Femur_Cortical_R",
    102: "Femur_Condyle_Shell_R",
    201: "TIBIA_CORTICAL_R",
    301: "Fibula_R_cortical",
    401: "Patella_R",
    501: "Flesh_Thigh_R",
    601: "Skin_LowerExt_R",
    701: "Lig_ACL_R",
}


@dataclass(frozen=True, eq=False)
class SyntheticKnee:
    """The model, its setup dict, and the designed values."""

    model: Model
    setup: dict[str, Any]
    lateral_radius: float
    medial_radius: float
    flexion_deg: float
    to_world: NDArray[np.float64]  # (4, 4): subject frame -> model coordinates


def _hex_box(lo: ArrayLike, hi: ArrayLike, n: tuple[int, int, int]):
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    axes = [np.linspace(lo[i], hi[i], n[i] + 1) for i in range(3)]
    gx, gy, gz = np.meshgrid(*axes, indexing="ij")
    pts = np.column_stack([gx.ravel(), gy.ravel(), gz.ravel()])
    _nx, ny, nz = (k + 1 for k in n)

    def vid(i, j, k):
        return (i * ny + j) * nz + k

    i, j, k = np.meshgrid(*(np.arange(m) for m in n), indexing="ij")
    i, j, k = i.ravel(), j.ravel(), k.ravel()
    conn = np.column_stack(
        [
            vid(i, j, k),
            vid(i + 1, j, k),
            vid(i + 1, j + 1, k),
            vid(i, j + 1, k),
            vid(i, j, k + 1),
            vid(i + 1, j, k + 1),
            vid(i + 1, j + 1, k + 1),
            vid(i, j + 1, k + 1),
        ]
    )
    return pts, conn


def _wheel(centre: ArrayLike, radius: float, half_width: float, n_theta: int, n_w: int):
    """Quad shells on a cylinder about y; returns points, conn, rim angle of each point.

    Angle 0 = distal (-z), 90 = posterior (-x).
    """
    theta = np.radians(np.linspace(0.0, 360.0, n_theta, endpoint=False))
    ys = np.linspace(-half_width, half_width, n_w + 1)
    t, y = np.meshgrid(theta, ys, indexing="ij")
    c = np.asarray(centre, float)
    pts = np.column_stack(
        [c[0] - radius * np.sin(t.ravel()), c[1] + y.ravel(), c[2] - radius * np.cos(t.ravel())]
    )
    i, j = np.meshgrid(np.arange(n_theta), np.arange(n_w), indexing="ij")
    i, j = i.ravel(), j.ravel()
    i1 = (i + 1) % n_theta
    nw = n_w + 1
    conn = np.column_stack([i * nw + j, i1 * nw + j, i1 * nw + j + 1, i * nw + j + 1])
    return pts, conn, np.degrees(t.ravel())


def build_synthetic_knee(
    side: str = "right",
    flexion_deg: float = 9.0,
    rotation: ArrayLike | None = None,
    translation: ArrayLike | None = None,
    lateral_radius: float = 20.5,
    medial_radius: float = 23.3,
    noise_mm: float = 0.0,
    seed: int = 0,
    coordinate_landmarks: bool = False,
    distal_flat_deg: float = 0.0,
) -> SyntheticKnee:
    """Build the synthetic knee.

    Parameters
    ----------
    side : {"right", "left"}
        A left knee is the right one mirrored through the sagittal plane.
    flexion_deg : float
        Designed flexion: the tibia is rotated about the condyle axis by this angle.
    rotation : (3, 3) array_like, optional
        Orientation of the subject frame in model coordinates (default identity).
    translation : (3,) array_like, optional
        Position of the knee joint point in model coordinates.
    lateral_radius, medial_radius : float
        Condyle radii (mm).
    noise_mm : float
        Gaussian noise added to the condyle rim nodes (mm).
    coordinate_landmarks : bool
        Give the axis landmarks as coordinates instead of node ids.
    distal_flat_deg : float
        Make each condyle's rim flat (a plane, like the demo leg's distal femur) from the distal
        point up to this angle towards posterior; the circular arc then starts there.
    """
    rng = np.random.default_rng(seed)
    chunks: list[tuple[NDArray[np.float64], str, NDArray[np.int64], int]] = []
    offset = 0
    coords_list = []

    def add(pts, etype, conn, pid):
        nonlocal offset
        coords_list.append(pts)
        chunks.append((pts, etype, conn + offset, pid))
        offset += len(pts)
        return offset - len(pts)

    def add_hex(lo, hi, n, pid):
        pts, conn = _hex_box(lo, hi, n)
        return add(pts, "hex8", conn, pid)

    # femur: shaft (hexes), condyle wheels (shells). Condyle centres on the y axis at z = 0.
    zc = 0.0
    shaft_start = add_hex([-12, -12, 25], [12, 12, 320], (2, 2, 20), 101)
    lat_pts, lat_conn, lat_ang = _wheel([-8.0, -30.0, zc], lateral_radius, 11.0, 72, 4)
    med_pts, med_conn, med_ang = _wheel([-8.0, 30.0, zc], medial_radius, 11.0, 72, 4)
    for pts, ang, radius in ((lat_pts, lat_ang, lateral_radius), (med_pts, med_ang, medial_radius)):
        flat = (ang < distal_flat_deg) | (ang > 360.0 - distal_flat_deg)
        pts[flat, 2] = zc - radius * np.cos(np.radians(distal_flat_deg))
    lat_start = add(lat_pts, "quad4", lat_conn, 102)
    med_start = add(med_pts, "quad4", med_conn, 102)
    # tibia (flexed later), fibula, patella, flesh, skin, ligament
    tib_z0 = -max(lateral_radius, medial_radius) - 3.0
    tib_start = add_hex([-14, -14, tib_z0 - 330], [14, 14, tib_z0], (2, 2, 22), 201)
    n_tib = len(coords_list[-1])
    fib_start = add_hex([-20, -40, tib_z0 - 300], [-12, -32, tib_z0 - 20], (1, 1, 10), 301)
    n_fib = len(coords_list[-1])
    pat_start = add_hex([30, -15, 5], [40, 15, 45], (2, 3, 4), 401)
    n_pat = len(coords_list[-1])
    add_hex([-60, -60, 100], [60, 60, 300], (3, 3, 4), 501)
    sk, sk_conn, _ = _wheel([0.0, 0.0, 200.0], 70.0, 0.0, 24, 1)
    sk_conn = sk_conn[:, [0, 1, 1, 0]]  # degenerate ring: only used as 'skin' nodes
    add(np.column_stack([sk[:, 0], sk[:, 2] - 200.0, sk[:, 1] + 200.0]), "quad4", sk_conn, 601)
    add_hex([-5, -5, tib_z0 + 0.5], [5, 5, -5], (1, 1, 2), 701)

    coords = np.concatenate(coords_list)
    tib = coords[tib_start : tib_start + n_tib]
    centre_line = tib_start + np.flatnonzero(
        np.isclose(tib[:, 0], 0.0) & np.isclose(tib[:, 1], 0.0)
    )
    tibia_prox = centre_line[np.argmax(coords[centre_line, 2])]
    tibia_dist = centre_line[np.argmin(coords[centre_line, 2])]
    # flex the tibia + fibula about the condyle axis (y) through (-8, *, 0)
    pivot = np.array([-8.0, 0.0, zc])
    r_flex = rotation_matrix([0.0, 1.0, 0.0], flexion_deg)
    for start, n in ((tib_start, n_tib), (fib_start, n_fib)):
        coords[start : start + n] = (coords[start : start + n] - pivot) @ r_flex.T + pivot
    # noise on condyle rims
    if noise_mm:
        for start, n in ((lat_start, len(lat_pts)), (med_start, len(med_pts))):
            coords[start : start + n] += rng.normal(0.0, noise_mm, (n, 3)) * [1, 0, 1]
    del n_pat, pat_start

    # landmarks (subject frame), before mirroring and moving
    def arc_nodes(start, angles):
        sel = np.flatnonzero((angles >= distal_flat_deg) & (angles <= 120.0))
        return start + sel

    lat_nodes = arc_nodes(lat_start, lat_ang)
    med_nodes = arc_nodes(med_start, med_ang)
    shaft = coords[shaft_start : shaft_start + 3 * 3 * 21]
    shaft_axis_nodes = shaft_start + np.flatnonzero(
        (np.abs(shaft[:, 0]) < 1e-9) & (np.abs(shaft[:, 1]) < 1e-9)
    )
    femur_prox = shaft_axis_nodes[np.argmax(coords[shaft_axis_nodes, 2])]
    femur_dist = shaft_axis_nodes[np.argmin(coords[shaft_axis_nodes, 2])]
    medial_plateau = (np.array([0.0, 15.0, tib_z0]) - pivot) @ r_flex.T + pivot

    # mirror (left), then move
    mirror = np.diag([1.0, -1.0, 1.0]) if side == "left" else np.eye(3)
    rot = np.eye(3) if rotation is None else np.asarray(rotation, float)
    trans = np.zeros(3) if translation is None else np.asarray(translation, float)
    world = np.eye(4)
    world[:3, :3] = rot @ mirror
    world[:3, 3] = trans
    coords = coords @ world[:3, :3].T + trans
    medial_plateau = world[:3, :3] @ medial_plateau + trans

    node_ids = np.arange(1, len(coords) + 1, dtype=np.int64) * 3 + 1000
    blocks: dict[str, list] = {}
    eid = 1
    for _pts, etype, conn, pid in chunks:
        if side == "left" and etype in ("hex8", "quad4"):
            conn = conn[:, list(MIRRORED_NODE_ORDER[etype])]
        ids = np.arange(eid, eid + len(conn))
        eid += len(conn)
        blocks.setdefault(etype, []).append((ids, np.full(len(conn), pid), conn))
    model = Model(
        node_ids=node_ids,
        coords=coords,
        blocks={
            et: ElementBlock(et, *(np.concatenate(c) for c in zip(*rows, strict=True)))
            for et, rows in blocks.items()
        },
        parts={
            pid: Part(pid, title.replace("_R", "_L") if side == "left" else title)
            for pid, title in PART_TITLES.items()
        },
    )

    def nid(index: int) -> int | list[float]:
        if coordinate_landmarks:
            return [float(v) for v in coords[index]]
        return int(node_ids[index])

    setup = {
        "format": "kneegui-setup",
        "version": 1,
        "side": side,
        "moving_segment": "tibia",
        "roles": {
            "femur": [101, 102],
            "tibia": [201],
            "fibula": [301],
            "patella": [401],
            "skin": [601],
            "flesh": [501],
            "ligament": [701],
            "meniscus": [],
            "tendon": [],
            "capsule": [],
            "fixed": [],
        },
        "landmarks": {
            "lateral_condyle": node_ids[lat_nodes].tolist(),
            "medial_condyle": node_ids[med_nodes].tolist(),
            "lr_axis": [[float(v) for v in medial_plateau], nid(tibia_dist)],
            "femur_axis": [nid(femur_prox), nid(femur_dist)],
            "tibia_axis": [nid(tibia_prox), nid(tibia_dist)],
        },
        "kinematics": {
            "tibial_rotation": "default",
            "patellar_flexion": "default",
            "patellar_tilt": "default",
        },
        "skin_contours": 86,
    }
    return SyntheticKnee(model, setup, lateral_radius, medial_radius, flexion_deg, world)


def random_rotation(seed: int) -> NDArray[np.float64]:
    """A reproducible random proper rotation matrix (3, 3)."""
    q, r = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q
