"""Suggest the posterior condyle node sets from the femur's surface.

The directions come from the bone itself, never from the model's global axes:

1. *long axis*: first principal direction of the femur nodes; the *distal* end is the one nearer
   the tibia (or patella) when their parts are given, else the wider end (the condyles);
2. *superior*: refined through the centroids of two shaft slabs;
3. *medial-lateral*: the direction of largest spread of the distal-end surface nodes across the
   shaft (epicondylar width > antero-posterior depth);
4. *anterior*: towards the patella when given, else away from the intercondylar notch (just
   above the distal end the middle of the bone is recessed far more behind than in front), else
   opposite the condyles' bulge behind the shaft line;
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
from kneegui.model import Model
from kneegui.topology import SHELL_TYPES, boundary_faces, sorted_unique


def surface_node_indices(model: Model, part_ids: Iterable[int]) -> NDArray[np.int64]:
    """Node indices on the surface of the given parts, taken together.

    Surface = nodes of solid faces used by exactly one solid element of those parts, plus every
    node of their shell elements (cortical shells sit on the bone surface).
    """
    wanted = np.array(sorted(set(int(p) for p in part_ids)), dtype=np.int64)
    quads, tris = boundary_faces(model.blocks, wanted)
    nodes = [quads.reshape(-1), tris.reshape(-1)]
    for etype in SHELL_TYPES:
        block = model.blocks.get(etype)
        if block is not None:
            nodes.append(block.conn[np.isin(block.part_ids, wanted)].reshape(-1))
    return sorted_unique(np.concatenate(nodes)).astype(np.int64)


def _slab(t: NDArray[np.float64], lo: float, hi: float) -> NDArray[np.bool_]:
    return (t >= lo) & (t <= hi)


def _perpendicular(v: NDArray[np.float64], axis: NDArray[np.float64]) -> NDArray[np.float64]:
    return v - np.outer(v @ axis, axis) if v.ndim == 2 else v - (v @ axis) * axis


def _notch_sign(
    pts: NDArray[np.float64],
    height: NDArray[np.float64],
    ml_dir: NDArray[np.float64],
    ap_dir: NDArray[np.float64],
    width: float,
) -> float:
    """+1 if ``ap_dir`` points anterior, -1 if posterior, 0 if undecided.

    Below the notch roof (5-18 % of the width above the distal end) the intercondylar notch opens
    posteriorly (deep, about
    a quarter of the width), while the trochlear groove in front is shallow: the middle strip of
    the bone is recessed from the condyles much more on the posterior side.
    """
    slab = (height > 0.05 * width) & (height < 0.18 * width)
    if slab.sum() < 10:
        return 0.0
    p = pts[slab]
    ml = p @ ml_dir
    a = p @ ap_dir
    mid = 0.5 * (ml.min() + ml.max())
    centre = np.abs(ml - mid) < 0.05 * width
    sides = np.abs(ml - mid) > 0.15 * width
    if centre.sum() < 2 or sides.sum() < 2:
        return 0.0
    recess_minus = a[centre].min() - a[sides].min()  # recess on the -ap side
    recess_plus = a[sides].max() - a[centre].max()  # recess on the +ap side
    if abs(recess_minus - recess_plus) < 0.05 * width:
        return 0.0
    return 1.0 if recess_minus > recess_plus else -1.0


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
        ``shaft_point`` (3,) (a point on the shaft axis) and ``surface_nodes`` (node indices of
        the femur's surface, or all its nodes if it has no surface).

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
    if len(surf) < 20:
        surf = nodes
    spts = model.coords[surf]
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
        sign = _notch_sign(pts, pts @ superior - h_min - (c_lo @ superior), ml, ap, width)
        if sign == 0.0:  # no notch to be seen: the condyles bulge behind the shaft line
            distal_region = spts[sh < h_min + 0.6 * width]
            a = (distal_region - c_lo) @ ap
            sign = 1.0 if -a.min() > a.max() else -1.0
        anterior = sign * ap
    left = np.cross(superior, anterior)
    medial = left if side == "right" else -left
    return {
        "superior": superior,
        "anterior": anterior,
        "medial": medial,
        "distal_point": distal_point,
        "width": width,
        "shaft_point": c_lo,
        "surface_nodes": surf,
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


def _circles_through(p1, p2, p3):
    """Centres (T, 2) and radii (T,) of the circles through point triples (NaN if collinear)."""
    ax, ay = p1[:, 0], p1[:, 1]
    bx, by = p2[:, 0], p2[:, 1]
    cx, cy = p3[:, 0], p3[:, 1]
    d = 2.0 * (ax * (by - cy) + bx * (cy - ay) + cx * (ay - by))
    with np.errstate(divide="ignore", invalid="ignore"):
        a2, b2, c2 = ax**2 + ay**2, bx**2 + by**2, cx**2 + cy**2
        ux = (a2 * (by - cy) + b2 * (cy - ay) + c2 * (ay - by)) / d
        uy = (a2 * (cx - bx) + b2 * (ax - cx) + c2 * (bx - ax)) / d
    centres = np.column_stack([ux, uy])
    return centres, np.hypot(ax - ux, ay - uy)


def _consensus_circle(
    points: NDArray[np.float64], radius_range: tuple[float, float], tol: float, seed: int = 0
) -> NDArray[np.bool_]:
    """Inliers (within ``tol``) of the best-supported circle with a radius in range.

    Every triple is tried for small sets, 4000 random triples (fixed seed) otherwise; the circle
    with the lowest truncated quadratic cost (MSAC) wins. Robust to a flat facet or a metaphysis
    curve beside the arc.
    """
    n = len(points)
    if n < 3:
        return np.zeros(n, dtype=bool)
    if n <= 30:
        tri = np.array(np.triu_indices(n, 1)).T
        triples = np.array([(i, j, k) for i, j in tri for k in range(j + 1, n)])
    else:
        rng = np.random.default_rng(seed)
        triples = np.sort(rng.integers(0, n, size=(4000, 3)), axis=1)
        triples = triples[(triples[:, 0] < triples[:, 1]) & (triples[:, 1] < triples[:, 2])]
    if len(triples) == 0:
        return np.zeros(n, dtype=bool)
    centres, radii = _circles_through(
        points[triples[:, 0]], points[triples[:, 1]], points[triples[:, 2]]
    )
    ok = np.isfinite(radii) & (radii >= radius_range[0]) & (radii <= radius_range[1])
    if not ok.any():
        return np.zeros(n, dtype=bool)
    centres, radii = centres[ok], radii[ok]
    best_inliers, best_cost = None, np.inf
    for start in range(0, len(radii), 2000):
        c, r = centres[start : start + 2000], radii[start : start + 2000]
        dist = np.hypot(points[None, :, 0] - c[:, None, 0], points[None, :, 1] - c[:, None, 1])
        res = np.abs(dist - r[:, None])
        # MSAC: truncated quadratic cost prefers the circle the points lie tightly on over a
        # compromise that merely keeps more of them within the tolerance
        cost = np.minimum(res, tol) ** 2
        total = cost.sum(axis=1)
        k = int(np.argmin(total))
        if total[k] < best_cost:
            best_cost, best_inliers = float(total[k]), res[k] <= tol
    return best_inliers


def _profile_selection(
    local: NDArray[np.float64], r0: float, max_arc_deg: float, tol: float
) -> NDArray[np.bool_]:
    """Nodes on the circular posterior profile of one condyle band.

    ``local`` columns: anterior, superior. The outline (outermost nodes per 5-degree sector about
    a provisional centre, from slightly below the distal point to ``max_arc_deg``) is searched
    for the circle of plausible radius (0.4-2 ``r0``) the outline nodes lie on most tightly
    (MSAC consensus of point triples, residuals truncated at ``tol``); a flatter distal facet or
    the metaphysis above the arc fall off it. The circle is refitted by least squares on its
    inliers, the tolerance is tightened to their robust scatter, and every node of the band
    within that tolerance of the circle, inside the inliers' angular range, is selected.
    """
    ap, h = local[:, 0], local[:, 1]
    centre = np.array([ap.min() + r0, h.min() + r0])
    ang, rad = _angles(local, centre)
    in_arc = (ang >= -10.0) & (ang <= max_arc_deg)
    outline = _outline(ang, rad, in_arc, 5.0, tol)
    cand = np.flatnonzero(outline)
    inliers = _consensus_circle(local[cand], (0.4 * r0, 2.0 * r0), tol)
    if inliers.sum() < 5:
        return np.zeros(len(local), dtype=bool)
    fit = fit_circle_2d(local[cand[inliers]])
    # tighten to the scatter of the inliers (robust sigma, re-estimated as the fit improves), so
    # the ends where a flatter facet or the metaphysis leave the arc tangentially are dropped
    tight = tol
    for _ in range(20):
        sigma = 1.4826 * float(np.median(np.abs(fit.residuals(local[cand[inliers]]))))
        tight = min(tol, max(0.005 * r0, 3.0 * sigma))
        ang, _ = _angles(local, fit.center)
        lo = max(ang[cand[inliers]].min(), -10.0)
        hi = min(ang[cand[inliers]].max(), max_arc_deg)
        new = (np.abs(fit.residuals(local[cand])) <= tight) & (ang[cand] >= lo) & (ang[cand] <= hi)
        if new.sum() < 5:
            return np.zeros(len(local), dtype=bool)
        if np.array_equal(new, inliers):
            break
        inliers = new
        fit = fit_circle_2d(local[cand[inliers]])
    ang, _ = _angles(local, fit.center)
    lo, hi = ang[cand[inliers]].min(), ang[cand[inliers]].max()
    return (np.abs(fit.residuals(local)) <= tight) & (ang >= lo - 1e-9) & (ang <= hi + 1e-9)


def suggest_condyle_nodes(
    model: Model,
    femur_part_ids: Iterable[int],
    side: str,
    tibia_part_ids: Iterable[int] | None = None,
    patella_part_ids: Iterable[int] | None = None,
    band_fraction: float = 0.2,
    max_arc_deg: float = 125.0,
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
    surf = np.asarray(frame["surface_nodes"])
    pts = model.coords[surf]
    origin = np.asarray(frame["distal_point"])
    r0 = 0.22 * width
    left = np.cross(sup, ant)
    side_sign = 1.0 if np.dot(med, left) > 0 else -1.0
    # The medial-lateral direction from the bone's spread is a few degrees off; nodes of one
    # condyle then do not line up in the sagittal projection. Refine it from the fitted centres
    # (as the F-E axis), tightening the tolerance as the rows line up.
    schedule = (4.0, 2.0, 1.0, 1.0, 1.0, 1.0, 1.0)
    chosen: list[NDArray[np.int64]] = []
    for step, factor in enumerate(schedule):
        tol = factor * tolerance_mm
        local = np.column_stack([(pts - origin) @ ant, (pts - origin) @ sup, (pts - origin) @ med])
        region = local[:, 1] < 0.6 * width
        ml = local[:, 2]
        ml_mid = 0.5 * (ml[region].min() + ml[region].max())
        chosen, centres = [], []
        for sign, name in ((-1.0, "lateral"), (1.0, "medial")):
            half = region & (sign * (ml - ml_mid) > 0.1 * width)
            if half.sum() < 5:
                raise GeometryError(f"no {name} condyle found on the femur surface")
            h_low = local[half, 1].min()
            bottom = half & (local[:, 1] <= h_low + 0.15 * width)
            band_centre = 0.5 * float(ml[bottom].min() + ml[bottom].max())
            band = half & (np.abs(ml - band_centre) <= band_fraction * width)
            idx = np.flatnonzero(band)
            keep = _profile_selection(local[idx][:, :2], r0, max_arc_deg, tol)
            if keep.sum() < 5:
                raise GeometryError(
                    f"only {int(keep.sum())} {name} condyle nodes found on the femur surface"
                )
            chosen.append(surf[idx[keep]])
            fit = fit_circle_2d(local[idx[keep]][:, :2])
            centres.append(
                origin
                + fit.center[0] * ant
                + fit.center[1] * sup
                + local[idx[keep], 2].mean() * med
            )
        if step == len(schedule) - 1:
            break
        gca = centres[1] - centres[0]
        gca = gca - (gca @ sup) * sup
        if np.linalg.norm(gca) < 0.2 * width:
            break
        new_med = unit(gca, "medial-lateral direction")
        settled = factor == 1.0 and float(new_med @ med) > np.cos(np.radians(0.01))
        med = new_med
        ant = unit(np.cross(side_sign * med, sup), "anterior direction")
        if settled:
            break
    return tuple(np.sort(model.node_ids[c]) for c in chosen)  # type: ignore[return-value]
