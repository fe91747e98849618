"""The demo leg's sliding interface around the knee joint.

In human-body models the tissue around the knee joint is not merged with the bones: cartilage,
menisci and the capsule slide on the condyles through contact definitions. A conforming grid
would instead weld every flesh node to the bone surface next to it, so the flesh in the joint
line would be torn between femur and tibia as the knee bends. Within ``radius`` of the
flexion-extension axis, the flesh, capsule and skin therefore get their own nodes where they touch
the femur, tibia or fibula (coincident with the bone's nodes, as at a contact interface), and the
menisci their own nodes where they touch the femur (they stay on the tibia). Ligaments and the
patellar tendon keep their bone attachments, and
so does the tissue right around their insertions.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from numpy.typing import NDArray

#: Radius (mm) about the F-E axis within which soft tissue slides on the bones.
SLIDING_RADIUS_MM = 80.0


def detach_soft_tissue(
    coords: NDArray[np.float64],
    element_sets: list[tuple[NDArray[np.int64], NDArray[np.int64]]],
    bone_pids: Iterable[int],
    soft_pids: Iterable[int],
    attached_pids: Iterable[int] = (),
    radius: float = SLIDING_RADIUS_MM,
) -> tuple[NDArray[np.float64], list[NDArray[np.int64]]]:
    """Give the soft elements their own copies of the bone nodes they touch near the joint.

    Parameters
    ----------
    coords : (N, 3) ndarray
        Node coordinates in the design frame (knee joint centre at the origin, F-E axis along y).
    element_sets : list of (conn, part_ids)
        Connectivity (node indices) and part id of each element, one entry per element block.
    bone_pids : iterable of int
        Parts whose nodes the soft tissue should slide on.
    soft_pids : iterable of int
        Parts that slide.
    attached_pids : iterable of int
        Parts attached to the bone (ligaments, tendon): a bone node they use is not split, so the
        tissue around an insertion stays attached with them.
    radius : float
        Only nodes within this distance of the F-E axis (in the sagittal x-z plane) are split.

    Returns
    -------
    coords : (N + D, 3) ndarray
        With the D duplicated nodes appended.
    conns : list of ndarray
        New connectivity of each block (soft elements refer to the copies).
    """
    bone_pids = np.array(sorted(set(bone_pids)), dtype=np.int64)
    soft_pids = np.array(sorted(set(soft_pids)), dtype=np.int64)
    n = len(coords)
    on_bone = np.zeros(n, dtype=bool)
    for conn, pids in element_sets:
        on_bone[conn[np.isin(pids, bone_pids)].reshape(-1)] = True
    near = np.hypot(coords[:, 0], coords[:, 2]) < radius
    split = on_bone & near
    touched = np.zeros(n, dtype=bool)
    for conn, pids in element_sets:
        touched[conn[np.isin(pids, soft_pids)].reshape(-1)] = True
    split &= touched
    attached_pids = np.array(sorted(set(attached_pids)), dtype=np.int64)
    for conn, pids in element_sets:
        split[conn[np.isin(pids, attached_pids)].reshape(-1)] = False
    copies = np.flatnonzero(split)
    new_index = np.full(n, -1, dtype=np.int64)
    new_index[copies] = n + np.arange(len(copies))
    out = []
    for conn, pids in element_sets:
        conn = conn.copy()
        soft = np.isin(pids, soft_pids)
        sub = conn[soft]
        hit = split[sub]
        sub[hit] = new_index[sub[hit]]
        conn[soft] = sub
        out.append(conn)
    return np.concatenate([coords, coords[copies]]), out
