"""Suggest the posterior condyle node sets from the femur's surface.

The directions come from the bone itself, never from the model's global axes:

1. *long axis*: first principal direction of the femur nodes; the *distal* end is the one nearer
   the tibia (or patella) when their parts are given, else the wider end (the condyles);
2. *superior*: refined through the centroids of two shaft slabs;
3. *medial-lateral*: the direction of largest spread of the distal-end surface nodes across the
   shaft (epicondylar width > antero-posterior depth);
4. *anterior*: towards the patella when given, else opposite the posterior bulge of the condyles
   relative to the shaft line (the condyles sit behind the shaft, the trochlea in line with it);
5. *medial*: the subject's left (= superior x anterior) for a right knee, its right for a left
   knee.

In each half of the distal end, the surface nodes of a band around the condyle's lowest point are
projected on the sagittal plane; the outer profile from the distal point round past posterior
(``0 .. max_arc_deg`` about a provisional centre) is fitted with a circle, trimming the nodes off
it (a flatter distal facet, the metaphysis above the arc), and re-centred until stable; the nodes
on that circle are the suggestion. The user confirms or edits the result.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from numpy.typing import NDArray

from kneegui.errors import GeometryError, SetupError
from kneegui.geometry.circle_fit import fit_circle_2d
from kneegui.geometry.transforms import unit
from kneegui.model import SHELL_TYPES, Model

#: Faces of each solid type as node positions (triangles padded with -1).
_SOLID_FACES: dict[str, list[tuple[int, ...]]] = {
    "hex8": [(0, 3, 2, 1), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)],
    "wedge6": [(0, 2, 1), (3, 4, 5), (0, 1, 4, 3), (1, 2, 5, 4), (2, 0, 3, 5)],
    "pyramid5": [(0, 3, 2, 1), (0, 1, 4), (1, 2, 4), (2, 3, 4), (3, 0, 4)],
    "tet4": [(0, 2, 1), (0, 1, 3), (1, 2, 3), (2, 0, 3)],
    "tet10": [(0, 2, 1), (0, 1, 3), (1, 2, 3), (2, 0, 3)],
}


def surface_node_indices(model: Model, part_ids: Iterable[int]) -> NDArray[np.int64]:
    """Node indices on the surface of the given parts, taken together.

    Surface = nodes of solid faces used by exactly one solid element of those parts, plus every
    node of their shell elements (cortical shells sit on the bone surface).
    """
    wanted = np.array(sorted(set(int(p) for p in part_ids)), dtype=np.int64)
    faces = []
    nodes = []
    for etype, block in model.blocks.items():
        mask = np.isin(block.part_ids, wanted)
        if not mask.any():
            continue
        conn = block.conn[mask]
        if etype in SHELL_TYPES:
            nodes.append(conn.reshape(-1))
        elif etype in _SOLID_FACES:
            for face in _SOLID_FACES[etype]:
                f = conn[:, list(face)]
                if f.shape[1] == 3:
                    f = np.column_stack([f, np.full(len(f), -1)])
                faces.append(f)
    if faces:
        allf = np.sort(np.concatenate(faces), axis=1)
        uniq, counts = np.unique(allf, axis=0, return_counts=True)
        boundary = uniq[counts == 1].reshape(-1)
        nodes.append(boundary[boundary >= 0])
    if not nodes:
        return np.zeros(0, dtype=np.int64)
    return np.unique(np.concatenate(nodes))


def _slab(t: NDArray[np.float64], lo: float, hi: float) -> NDArray[np.bool_]:
    return (t >= lo) & (t <= hi)


def _perpendicular(v: NDArray[np.float64], axis: NDArray[np.float64]) -> NDArray[np.float64]:
    return v - np.outer(v @ axis, axis) if v.ndim == 2 else v - (v @ axis) * axis


def femur_frame(
    model: Model,
    femur_part_ids: Iterable[int],
    side: str,
    tibia_part_ids: Iterable[int] | None = None,
    patella_part_ids: Iterable[int] | None = None,
) -> dict[str, NDArray[np.float64] | float]:
    """Anatomical directions of a femur from its geometry.

    Returns
    -------
    dict
        ``superior``, ``anterior``, ``medial`` (unit (3,) vectors), ``distal_point`` (3,) (the
        most distal node), ``width`` (mm, medial-lateral extent of the distal end) and
        ``shaft_point`` (3,) (a point on the shaft axis).

    Raises
    ------
    GeometryError
        If the femur has too few nodes or no elongated shape.
    """
    if side not in ("right", "left"):
        raise SetupError(f"expected 'right' or 'left', got {side!r}", key="side")
    femur_ids = list(femur_part_ids)
    nodes = model.part_node_indices(femur_ids)
    if len(nodes) < 20:
        raise GeometryError(f"the femur parts {femur_ids} have only {len(nodes)} nodes")
    pts = model.coords[nodes]
    mean = pts.mean(axis=0)
    _, sv, vt = np.linalg.svd(pts - mean, full_matrices=False)
    if sv[0] < 1.5 * sv[1]:
        raise GeometryError("the femur is not elongated: cannot find its shaft axis")
    axis = vt[0]
    t = (pts - mean) @ axis
    t_min, t_max = float(t.min()), float(t.max())
    length = t_max - t_min

    def centroid_of(pids: Iterable[int] | None) -> NDArray[np.float64] | None:
        if pids is None:
            return None
        idx = model.part_node_indices(list(pids))
        return model.coords[idx].mean(axis=0) if len(idx) else None

    tibia_c = centroid_of(tibia_part_ids)
    patella_c = centroid_of(patella_part_ids)
    hint = tibia_c if tibia_c is not None else patella_c
    if hint is not None:
        distal_sign = 1.0 if (hint - mean) @ axis > 0 else -1.0
    else:
        widths = []
        for lo, hi in ((t_min, t_min + 0.12 * length), (t_max - 0.12 * length, t_max)):
            q = _perpendicular(pts[_slab(t, lo, hi)] - mean, axis)
            _, s2, _ = np.linalg.svd(q - q.mean(axis=0), full_matrices=False)
            widths.append(s2[0] / np.sqrt(len(q)))
        distal_sign = -1.0 if widths[0] > widths[1] else 1.0
    superior = -distal_sign * axis
    h = (pts - mean) @ superior
    h_min = float(h.min())
    # shaft axis through two slab centroids away from both ends
    c_lo = pts[_slab(h, h_min + 0.30 * length, h_min + 0.40 * length)].mean(axis=0)
    c_hi = pts[_slab(h, h_min + 0.55 * length, h_min + 0.65 * length)].mean(axis=0)
    superior = unit(c_hi - c_lo, "femoral shaft axis")
    if superior @ (-distal_sign * axis) < 0.5:
        superior = -distal_sign * axis
    h = (pts - c_lo) @ superior
    h_min = float(h.min())
    distal_point = pts[int(np.argmin(h))]

    surf = surface_node_indices(model, femur_ids)
    spts = model.coords[surf] if len(surf) >= 20 else pts
    sh = (spts - c_lo) @ superior
    bottom = spts[sh < h_min + 0.15 * length]
    q = _perpendicular(bottom - c_lo, superior)
    _, _, vt2 = np.linalg.svd(q - q.mean(axis=0), full_matrices=False)
    ml = unit(_perpendicular(vt2[0], superior), "medial-lateral direction")
    ap = unit(np.cross(superior, ml), "antero-posterior direction")
    width = float(np.ptp(q @ ml))

    if patella_c is not None:
        anterior = ap if (patella_c - c_lo) @ ap > 0 else -ap
    else:
        distal_region = spts[sh < h_min + 0.6 * width]
        a = (distal_region - c_lo) @ ap
        anterior = ap if -a.min() > a.max() else -ap
    left = np.cross(superior, anterior)
    medial = left if side == "right" else -left
    return {
        "superior": superior,
        "anterior": anterior,
        "medial": medial,
        "distal_point": distal_point,
        "width": width,
        "shaft_point": c_lo,
    }


def _angles(local: NDArray[np.float64], centre: NDArray[np.float64]):
    """Angle about ``centre`` (0 = distal, 90 = posterior, degrees) and distance."""
    d = local - centre
    return np.degrees(np.arctan2(-d[:, 0], -d[:, 1])), np.hypot(d[:, 0], d[:, 1])


def _outline(ang, rad, in_arc, bin_deg: float, tol: float) -> NDArray[np.bool_]:
    """Points within ``tol`` of the outermost point of their angular bin."""
    bins = np.floor(ang / bin_deg).astype(np.int64)
    outer = np.zeros(len(ang), dtype=bool)
    for b in np.unique(bins[in_arc]):
        m = in_arc & (bins == b)
        outer |= m & (rad >= rad[m].max() - tol)
    return outer


def _trimmed_circle(points: NDArray[np.float64], sel: NDArray[np.bool_], tol: float):
    """Fit, then drop the worst-fitting points until every kept one is within ``tol``."""
    sel = sel.copy()
    while True:
        if sel.sum() < 5:
            return None, sel
        fit = fit_circle_2d(points[sel])
        res = np.abs(fit.residuals(points))
        worst = res[sel].max()
        if worst <= tol:
            return fit, sel
        cut = max(tol, min(0.8 * worst, 3.0 * float(np.median(res[sel]))))
        sel &= res <= cut


def _profile_selection(
    local: NDArray[np.float64], r0: float, max_arc_deg: float, tol: float
) -> NDArray[np.bool_]:
    """Nodes on the circular posterior profile of one condyle band.

    ``local`` columns: anterior, superior. The outline (outermost nodes per 5-degree sector about
    a provisional centre, from slightly below the distal point to ``max_arc_deg``) is seeded with
    its most posterior part - the flexion facet, circular on every knee - fitted with a circle
    (trimming nodes off it), then grown sector by sector along the outline while the nodes stay
    within ``tol`` of the refitted circle. A flatter distal facet or the metaphysis above the arc
    stop the growth. Finally every node within ``tol`` of the circle in the grown range is kept.
    """
    ap, h = local[:, 0], local[:, 1]
    centre = np.array([ap.min() + r0, h.min() + r0])
    ang, rad = _angles(local, centre)
    in_arc = (ang >= -10.0) & (ang <= max_arc_deg)
    outline = _outline(ang, rad, in_arc, 5.0, tol)
    seed = outline & (ap <= ap[outline].min() + 0.25 * r0)
    fit, sel = _trimmed_circle(local, seed, tol)
    if fit is None:
        # rough surfaces: accept the seed's own scatter
        fit, sel = _trimmed_circle(local, seed, 3.0 * fit_circle_2d(local[seed]).rms)
        if fit is None:
            return np.zeros(len(local), dtype=bool)
    tol = max(tol, 3.0 * fit.rms)
    for _ in range(100):
        ang, rad = _angles(local, fit.center)
        outline = _outline(ang, rad, (ang >= -10.0) & (ang <= max_arc_deg), 5.0, tol)
        lo, hi = ang[sel].min(), ang[sel].max()
        grown = (
            outline
            & (np.abs(fit.residuals(local)) <= tol)
            & (ang >= lo - 10.0)
            & (ang <= hi + 10.0)
        )
        if grown.sum() < 5 or np.array_equal(grown, sel):
            break
        sel = grown
        fit = fit_circle_2d(local[sel])
    ang, _ = _angles(local, fit.center)
    lo, hi = ang[sel].min(), ang[sel].max()
    return (np.abs(fit.residuals(local)) <= tol) & (ang >= lo) & (ang <= hi)


def suggest_condyle_nodes(
    model: Model,
    femur_part_ids: Iterable[int],
    side: str,
    tibia_part_ids: Iterable[int] | None = None,
    patella_part_ids: Iterable[int] | None = None,
    band_fraction: float = 0.08,
    max_arc_deg: float = 140.0,
    tolerance_mm: float = 0.3,
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Suggest the posterior lateral and medial condyle node sets.

    Parameters
    ----------
    model : Model
        The model.
    femur_part_ids : iterable of int
        Parts of the femur (cortical, trabecular, cartilage...).
    side : {"right", "left"}
        Side of the knee (tells medial from lateral once anterior is known).
    tibia_part_ids, patella_part_ids : iterable of int, optional
        Used to tell the distal end (tibia) and the anterior side (patella); strongly recommended.
    band_fraction : float
        Half-width of each condyle's medial-lateral band, as a fraction of the distal width.
    max_arc_deg : float
        Largest angle searched about the condyle centre, from the distal point (0) past
        posterior (90); nodes off the fitted circle are dropped anyway.
    tolerance_mm : float
        Distance below the outer profile (and off the fitted circle) still accepted (mm).

    Returns
    -------
    lateral_ids, medial_ids : ndarray of int64
        Node ids (sorted), for the setup's ``landmarks.lateral_condyle`` / ``medial_condyle``.

    Raises
    ------
    GeometryError
        If fewer than 5 nodes qualify on a side.
    """
    femur_ids = list(femur_part_ids)
    frame = femur_frame(model, femur_ids, side, tibia_part_ids, patella_part_ids)
    sup, ant, med = frame["superior"], frame["anterior"], frame["medial"]
    width = float(frame["width"])
    surf = surface_node_indices(model, femur_ids)
    if len(surf) < 10:
        surf = model.part_node_indices(femur_ids)
    pts = model.coords[surf]
    origin = np.asarray(frame["distal_point"])
    local = np.column_stack([(pts - origin) @ ant, (pts - origin) @ sup, (pts - origin) @ med])
    region = local[:, 1] < 0.6 * width
    ml = local[:, 2]
    ml_region = ml[region]
    ml_mid = 0.5 * (ml_region.min() + ml_region.max())
    r0 = 0.22 * width
    result = []
    for sign, name in ((-1.0, "lateral"), (1.0, "medial")):
        half = region & (sign * (ml - ml_mid) > 0.1 * width)
        if half.sum() < 5:
            raise GeometryError(f"no {name} condyle found on the femur surface")
        h_low = local[half, 1].min()
        bottom = half & (local[:, 1] <= h_low + 0.02 * width)
        band_centre = float(np.median(ml[bottom]))
        band = half & (np.abs(ml - band_centre) <= band_fraction * width)
        idx = np.flatnonzero(band)
        keep = _profile_selection(local[idx][:, :2], r0, max_arc_deg, tolerance_mm)
        chosen = surf[idx[keep]]
        if len(chosen) < 5:
            raise GeometryError(
                f"only {len(chosen)} {name} condyle nodes found on the femur surface"
            )
        result.append(np.sort(model.node_ids[chosen]))
    return result[0], result[1]
