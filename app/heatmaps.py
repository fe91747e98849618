"""The heat-map measures of the window and which of them a model offers (no Qt: the
command line's ``--metric`` choices come from here)."""

from __future__ import annotations

from kneegui.model import Model

#: Heat-map metrics: key -> (label, QualityResult metric name, "low is bad" flag). Which of
#: them a model offers, and in what order, is :func:`heatmap_metrics`.
HEATMAP_METRICS: dict[str, tuple[str, str, bool]] = {
    "jacobian": ("Jacobian", "jacobian_corner", True),
    "tet_collapse": ("Tet collapse", "tet_collapse", True),
    "dihedral_min": ("Tet min dihedral (°)", "dihedral_min", True),
    "dihedral_max": ("Tet max dihedral (°)", "dihedral_max", False),
    "vol_skew": ("Tet volumetric skew", "vol_skew", False),
    "midside_tangent": ("Tet10 mid-side offset", "midside_tangent", False),
    "aspect": ("Aspect ratio", "aspect", False),
    "warpage": ("Warpage (°)", "warpage", False),
    "skew": ("Skew (°)", "skew", False),
    "volume_change": ("Volume change, solids (%)", "volume_change", False),
    "area_change": ("Area change, shells (%)", "area_change", False),
}
#: Heat-map metrics of tetrahedra only.
TET_HEATMAPS = ("tet_collapse", "dihedral_min", "dihedral_max", "vol_skew")
#: Element types whose corner Jacobian varies with their shape (a tet's or a triangle's is 1).
JACOBIAN_TYPES = ("hex8", "wedge6", "pyramid5", "quad4")
TET_TYPES = ("tet4", "tet10")


def _types(model: Model | None) -> set[str]:
    return {t for t, b in model.blocks.items() if len(b)} if model is not None else set()


def jacobian_says_something(model: Model | None) -> bool:
    """Whether ``model`` has elements whose corner Jacobian is more than its sign (hexes,
    wedges, pyramids, quad shells); on tets and triangles alone it is 1 by definition."""
    return bool(_types(model) & set(JACOBIAN_TYPES))


def has_tets(model: Model | None) -> bool:
    """Whether ``model`` has tetrahedra (4- or 10-node)."""
    return bool(_types(model) & set(TET_TYPES))


def heatmap_metrics(model: Model | None) -> list[str]:
    """The heat-map metrics that say something on ``model``, most telling first.

    A tet's corner Jacobian is 1 by definition, so the Jacobian is offered only with hexes,
    wedges, pyramids or quad shells; the tet measures only with tets. On a model whose solids
    are all tets the tet measures come first, otherwise the Jacobian does. Warpage needs quad
    faces; volume change is offered with solids, area change with shells.
    """
    types = _types(model)
    tets = bool(types & set(TET_TYPES))
    other_solids = bool(types & {"hex8", "wedge6", "pyramid5"})
    quads = bool(types & set(JACOBIAN_TYPES))
    jacobian = ["jacobian"] if quads else []
    tet_keys = [*TET_HEATMAPS, *(["midside_tangent"] if "tet10" in types else [])] if tets else []
    keys = tet_keys + jacobian if tets and not other_solids else jacobian + tet_keys
    keys += ["aspect", *(["warpage"] if quads else []), "skew"]
    if tets or other_solids:
        keys.append("volume_change")
    if types & {"quad4", "tri3"}:
        keys.append("area_change")
    return keys
