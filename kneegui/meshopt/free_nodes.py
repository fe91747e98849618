"""Which nodes the smoother may move: interior soft-tissue nodes near degraded elements."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping

import numpy as np
from numpy.typing import NDArray

from kneegui.errors import raise_if_cancelled
from kneegui.meshopt.nodes import boundary_node_mask, node_part_count
from kneegui.model import ElementBlock, Model
from kneegui.quality.metrics import QualityResult
from kneegui.quality.thresholds import JACOBIAN_WARN

#: Solid types whose nodes the smoother can move (tet10 mid-side nodes would be left behind).
MOVABLE_SOLID_TYPES: tuple[str, ...] = ("hex8", "wedge6", "pyramid5", "tet4")


def degraded_elements(
    result: QualityResult,
    initial: QualityResult | None = None,
    threshold: float = JACOBIAN_WARN,
    tolerance: float = 0.02,
) -> dict[str, NDArray[np.bool_]]:
    """Elements the smoother should work on.

    An element is degraded when it is inverted (corner Jacobian <= 0), or when its corner
    Jacobian is below ``threshold`` *and* (given ``initial``) more than ``tolerance`` below its
    initial value.

    Parameters
    ----------
    result : QualityResult
        Full quality of the posed model.
    initial : QualityResult, optional
        Full quality of the initial model (same blocks).
    threshold : float
        Corner-Jacobian level below which an element counts as degraded (the warn level).
    tolerance : float
        Loss of corner Jacobian against the initial model that is ignored.

    Returns
    -------
    dict of str to (m,) ndarray of bool
        Per element type, aligned with the block rows.
    """
    out = {}
    for etype, q in result.by_type.items():
        bad = q.jacobian_corner < threshold
        if initial is not None and etype in initial:
            bad &= q.jacobian_corner < initial[etype].jacobian_corner - tolerance
        out[etype] = bad | q.inverted
    return out


def _grow(
    model: Model, selected: NDArray[np.bool_], part_ids: NDArray[np.int64], rings: int
) -> NDArray[np.bool_]:
    """Add ``rings`` layers of elements (of the given parts) around the selected nodes."""
    selected = selected.copy()
    for _ in range(rings):
        grown = selected.copy()
        for etype in MOVABLE_SOLID_TYPES:
            block = model.blocks.get(etype)
            if block is None:
                continue
            in_parts = np.isin(block.part_ids, part_ids)
            touching = in_parts & selected[block.conn].any(axis=1)
            grown[block.conn[touching].reshape(-1)] = True
        selected = grown
    return selected


def _base_candidates(
    model: Model,
    soft_tissue_part_ids: Iterable[int],
    degraded_element_mask: Mapping[str, NDArray[np.bool_]] | None,
    rings: int,
    cancel: Callable[[], bool] | None = None,
) -> tuple[NDArray[np.bool_], NDArray[np.int64]]:
    soft = np.array(sorted(set(int(p) for p in soft_tissue_part_ids)), dtype=np.int64)
    n = model.n_nodes
    soft_nodes = np.zeros(n, dtype=bool)
    soft_nodes[model.part_node_indices(soft, etypes=MOVABLE_SOLID_TYPES)] = True
    raise_if_cancelled(cancel, "smoothing cancelled")
    if degraded_element_mask is None:
        near = soft_nodes
    else:
        start = np.zeros(n, dtype=bool)
        for etype, mask in degraded_element_mask.items():
            block = model.blocks.get(etype)
            if block is not None and len(block):
                start[block.conn[np.asarray(mask, dtype=bool)].reshape(-1)] = True
        near = _grow(model, start, soft, rings)
    # nodes of element types the smoother cannot move, or of other parts, stay
    blocked = np.zeros(n, dtype=bool)
    for etype, block in model.blocks.items():
        if etype not in MOVABLE_SOLID_TYPES and etype not in ("quad4", "tri3") and len(block):
            blocked[block.conn.reshape(-1)] = True
    return near & soft_nodes & ~blocked, soft


def elements_touching(
    blocks: Mapping[str, ElementBlock], node_mask: NDArray[np.bool_]
) -> dict[str, ElementBlock]:
    """The elements of each block with a node in ``node_mask`` (every block kept, maybe empty).

    Every element using a node is among them, so whatever depends only on the elements around
    a node (the parts sharing it, whether a face through it is on the boundary) comes out the
    same for the masked nodes as from the whole model.
    """
    return {
        etype: block.select(node_mask[block.conn].any(axis=1)) for etype, block in blocks.items()
    }


def smoothing_free_nodes(
    model: Model,
    soft_tissue_part_ids: Iterable[int],
    fixed_part_ids: Iterable[int] = (),
    degraded_element_mask: Mapping[str, NDArray[np.bool_]] | None = None,
    rings: int = 2,
    soft_interfaces: bool = False,
    cancel: Callable[[], bool] | None = None,
) -> NDArray[np.bool_]:
    """Interior soft-tissue nodes near degraded elements: the nodes the smoother may move.

    Parameters
    ----------
    model : Model
        The (posed) model.
    soft_tissue_part_ids : iterable of int
        Parts whose solid elements may be smoothed (flesh, ligament, ...).
    fixed_part_ids : iterable of int
        Parts that must not change (bones, parts outside the joint); their nodes never move.
    degraded_element_mask : mapping of str to (m,) bool array, optional
        Degraded elements per type (e.g. from :func:`degraded_elements`). Default: every
        soft-tissue element counts, so every interior soft-tissue node is free.
    rings : int
        Layers of neighbouring soft-tissue elements added around the degraded ones.
    soft_interfaces : bool
        Also free the nodes shared only by soft-tissue solids of several parts (e.g. the
        interface between thigh and knee flesh). Default False: every part-boundary node stays.
    cancel : callable, optional
        Asked between the steps (a whole-body model: about a second in all); True raises
        :class:`~kneegui.errors.Cancelled`.

    Returns
    -------
    (N,) ndarray of bool
        Free nodes: used only by soft-tissue solids of a single part (hex8, wedge6, pyramid5,
        tet4) (or of several, with ``soft_interfaces``), not on the boundary surface of the
        solid mesh, not in a fixed part, and within ``rings`` elements of a degraded element.
    """
    free, soft = _base_candidates(model, soft_tissue_part_ids, degraded_element_mask, rings, cancel)
    raise_if_cancelled(cancel, "smoothing cancelled")
    # whether a node is shared by parts or lies on the boundary depends only on the elements
    # using it: look at those around the candidates alone, not at a whole-body model
    around = elements_touching(model.blocks, free)
    raise_if_cancelled(cancel, "smoothing cancelled")
    if soft_interfaces:
        # nodes touched by anything other than soft-tissue solids stay
        other = np.zeros(model.n_nodes, dtype=bool)
        for etype, block in around.items():
            if len(block) == 0:
                continue
            outside = ~np.isin(block.part_ids, soft) | (etype not in MOVABLE_SOLID_TYPES)
            other[block.conn[outside].reshape(-1)] = True
        free &= ~other
    else:
        free &= node_part_count(around, model.n_nodes) == 1
    raise_if_cancelled(cancel, "smoothing cancelled")
    free &= ~boundary_node_mask(model.n_nodes, around)
    raise_if_cancelled(cancel, "smoothing cancelled")
    fixed = list(fixed_part_ids)
    if fixed:
        free[model.part_node_indices(fixed)] = False
    return free


def smoothing_sliding_nodes(
    model: Model,
    soft_tissue_part_ids: Iterable[int],
    skin_part_ids: Iterable[int] = (),
    fixed_part_ids: Iterable[int] = (),
    degraded_element_mask: Mapping[str, NDArray[np.bool_]] | None = None,
    rings: int = 2,
) -> NDArray[np.bool_]:
    """Surface nodes that may slide tangentially on the skin (the smoother's option).

    The nodes on the outer boundary surface of the solid mesh that are used only by
    soft-tissue parts and skin parts, lie near degraded elements (as in
    :func:`smoothing_free_nodes`) and are not in a fixed part.

    Returns
    -------
    (N,) ndarray of bool
    """
    near, soft = _base_candidates(model, soft_tissue_part_ids, degraded_element_mask, rings)
    allowed_parts = set(soft.tolist()) | set(int(p) for p in skin_part_ids)
    around = elements_touching(model.blocks, near)  # all that decides for the near nodes
    other = np.zeros(model.n_nodes, dtype=bool)
    for block in around.values():
        if len(block):
            outside = ~np.isin(block.part_ids, list(allowed_parts))
            other[block.conn[outside].reshape(-1)] = True
    sliding = near & ~other & boundary_node_mask(model.n_nodes, around)
    fixed = list(fixed_part_ids)
    if fixed:
        sliding[model.part_node_indices(fixed)] = False
    return sliding
