"""Suggest the axis landmarks and a whole setup from the model's geometry.

* ``femur_axis``: centroids of two femoral shaft slabs (30-40 % and 55-65 % of the femur's
  length from its distal end), proximal first.
* ``tibia_axis``: centroids of two tibial shaft slabs (25-35 % and 65-75 % of the tibia's length
  from its proximal end), proximal first.
* ``lr_axis``: the centre of the medial plateau (centroid of the tibia's surface nodes in the top
  3 % of its length, medial half), then the tibial axis at the tibia's distal end (the
  tibio-talar joint centre, or the cut end of a model that stops above the ankle).

All are coordinates (``[x, y, z]``), which a setup attaches to their bone. They are suggestions
for the user to confirm; directions come from the bones, never from global axes.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray

from kneegui.errors import GeometryError, SetupError
from kneegui.geometry.transforms import unit
from kneegui.model import Model
from kneegui.setup.condyles import femur_frame, suggest_condyle_nodes, surface_node_indices
from kneegui.setup.format import FORMAT_NAME, FORMAT_VERSION, ROLES
from kneegui.setup.roles import suggest_roles


def _slab_centroid(pts: NDArray[np.float64], h: NDArray[np.float64], lo: float, hi: float):
    sel = (h >= lo) & (h <= hi)
    if sel.sum() < 3:
        raise GeometryError("too few bone nodes in a shaft slab to place the anatomical axis")
    return pts[sel].mean(axis=0)


def suggest_axis_landmarks(
    model: Model,
    femur_part_ids: Iterable[int],
    tibia_part_ids: Iterable[int],
    side: str,
    patella_part_ids: Iterable[int] | None = None,
) -> dict[str, list[list[float]]]:
    """Suggested ``femur_axis``, ``tibia_axis`` and ``lr_axis`` as ``[[x,y,z], [x,y,z]]``.

    Parameters
    ----------
    model : Model
        The model.
    femur_part_ids, tibia_part_ids : iterable of int
        Femur parts; tibia parts (without the fibula).
    side : {"right", "left"}
        Side of the knee.
    patella_part_ids : iterable of int, optional
        Helps find the anterior direction.

    Raises
    ------
    GeometryError
        If a bone is too small or not elongated.
    """
    femur_ids, tibia_ids = list(femur_part_ids), list(tibia_part_ids)
    frame = femur_frame(model, femur_ids, side, tibia_ids, patella_part_ids)
    sup, medial = np.asarray(frame["superior"]), np.asarray(frame["medial"])

    fem = model.coords[model.part_node_indices(femur_ids)]
    hf = fem @ sup
    f_len = float(np.ptp(hf))
    f_lo = hf.min()
    femur_prox = _slab_centroid(fem, hf, f_lo + 0.55 * f_len, f_lo + 0.65 * f_len)
    femur_dist = _slab_centroid(fem, hf, f_lo + 0.30 * f_len, f_lo + 0.40 * f_len)

    tib_nodes = model.part_node_indices(tibia_ids)
    if len(tib_nodes) < 20:
        raise GeometryError(f"the tibia parts {tibia_ids} have only {len(tib_nodes)} nodes")
    tib = model.coords[tib_nodes]
    _, sv, vt = np.linalg.svd(tib - tib.mean(axis=0), full_matrices=False)
    if sv[0] < 1.5 * sv[1]:
        raise GeometryError("the tibia is not elongated: cannot find its shaft axis")
    axis = vt[0] if vt[0] @ sup > 0 else -vt[0]
    ht = tib @ axis
    t_len = float(np.ptp(ht))
    t_hi = ht.max()
    tibia_prox = _slab_centroid(tib, ht, t_hi - 0.35 * t_len, t_hi - 0.25 * t_len)
    tibia_dist = _slab_centroid(tib, ht, t_hi - 0.75 * t_len, t_hi - 0.65 * t_len)
    tib_dir = unit(tibia_prox - tibia_dist, "tibial axis")

    surf = surface_node_indices(model, tibia_ids)
    spts = model.coords[surf] if len(surf) >= 10 else tib
    hs = spts @ tib_dir
    top = spts[hs >= hs.max() - 0.03 * t_len]
    ml_dir = unit(medial - (medial @ tib_dir) * tib_dir, "medial direction")
    ml = (top - top.mean(axis=0)) @ ml_dir
    medial_top = top[ml > 0.5 * (ml.min() + ml.max())]
    if len(medial_top) == 0:
        medial_top = top
    plateau = medial_top.mean(axis=0)
    plateau = plateau + (hs.max() - plateau @ tib_dir) * tib_dir
    h_end = (tib @ tib_dir).min()
    talar = tibia_dist + (h_end - tibia_dist @ tib_dir) * tib_dir

    def as_list(p: NDArray[np.float64]) -> list[float]:
        return [float(v) for v in p]

    return {
        "femur_axis": [as_list(femur_prox), as_list(femur_dist)],
        "tibia_axis": [as_list(tibia_prox), as_list(tibia_dist)],
        "lr_axis": [as_list(plateau), as_list(talar)],
    }


def suggest_setup(
    model: Model,
    side: str,
    moving_segment: str = "tibia",
    roles: Mapping[str, Iterable[int]] | None = None,
) -> dict[str, Any]:
    """A complete setup dict suggested from part titles and bone geometry.

    Parameters
    ----------
    model : Model
        The model.
    side : {"right", "left"}
        Side of the knee to reposition.
    moving_segment : {"tibia", "femur"}
        Which segment moves.
    roles : mapping, optional
        Roles to use instead of :func:`~kneegui.setup.roles.suggest_roles`.

    Returns
    -------
    dict
        In the file form of docs/setup-format.md; validate it with
        :func:`~kneegui.setup.format.load_setup`.

    Raises
    ------
    SetupError
        No femur or tibia part could be identified.
    GeometryError
        The bones' shape defeats the suggestion.
    """
    if roles is None:
        roles = suggest_roles(model, side=side)
    role_lists = {r: sorted(int(p) for p in roles.get(r, [])) for r in ROLES}
    for r in ("femur", "tibia"):
        if not role_lists[r]:
            raise SetupError(
                f"no part could be identified as {r}; assign it by hand", key=f"roles.{r}"
            )
    patella = role_lists["patella"] or None
    lateral, medial = suggest_condyle_nodes(
        model,
        role_lists["femur"],
        side,
        tibia_part_ids=role_lists["tibia"],
        patella_part_ids=patella,
    )
    axes = suggest_axis_landmarks(
        model, role_lists["femur"], role_lists["tibia"], side, patella_part_ids=patella
    )
    return {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "side": side,
        "moving_segment": moving_segment,
        "roles": role_lists,
        "landmarks": {
            "lateral_condyle": lateral.tolist(),
            "medial_condyle": medial.tolist(),
            **axes,
        },
        "kinematics": {
            "tibial_rotation": "default",
            "patellar_flexion": "default",
            "patellar_tilt": "default",
        },
        "skin_contours": 86,
    }
