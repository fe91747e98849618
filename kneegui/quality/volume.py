"""Element volume change against the initial pose: one rule, one set of key names.

The relative change is ``100 (v - v0) / |v0|`` percent, signed (growth positive).

- ``v0 < 0`` (an element already inverted in the initial model): the change is taken relative
  to ``|v0|``, so it stays signed like the change itself.
- ``v0 == 0`` (a degenerate initial element): no relative change exists. It is ``0`` where the
  element is still flat (nothing changed) and ``+inf`` / ``-inf`` (the sign of ``v``) where it
  gained volume, so that the largest change points at it instead of hiding it.

Reports name the values ``max_element_pct`` (signed change of the element whose change is
largest in magnitude), ``max_element_id`` and ``total_pct`` (change of the summed volume).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray


def volume_change_pct(volume: ArrayLike, initial_volume: ArrayLike) -> NDArray[np.float64]:
    """Signed relative volume change in percent, with the zero-volume rule of this module.

    Parameters
    ----------
    volume, initial_volume : array_like of float
        Signed volumes now and in the initial pose (broadcast together; scalars allowed).

    Returns
    -------
    ndarray of float
        ``100 (v - v0) / |v0|``; where ``v0 == 0``: 0 if ``v == 0`` else ``copysign(inf, v)``.
    """
    v = np.asarray(volume, dtype=np.float64)
    v0 = np.asarray(initial_volume, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        pct = 100.0 * (v - v0) / np.abs(v0)
    flat = np.where(v == 0.0, 0.0, np.copysign(np.inf, v))
    return np.where(v0 == 0.0, flat, pct)


def volume_change(
    volume: ArrayLike,
    initial_volume: ArrayLike,
    element_ids: ArrayLike | None = None,
) -> dict[str, float | int | None]:
    """Largest element volume change and the change of the total volume.

    Parameters
    ----------
    volume, initial_volume : (m,) array_like of float
        Signed element volumes now and in the initial pose (same elements, same order).
    element_ids : (m,) array_like of int, optional
        Ids, to name the element with the largest change.

    Returns
    -------
    dict
        ``max_element_pct``, ``max_element_id``, ``total_pct`` (module docstring); all ``None``
        when there are no elements.
    """
    volume = np.asarray(volume, dtype=np.float64)
    initial_volume = np.asarray(initial_volume, dtype=np.float64)
    if len(volume) == 0:
        return {"max_element_pct": None, "max_element_id": None, "total_pct": None}
    pct = volume_change_pct(volume, initial_volume)
    k = int(np.argmax(np.abs(pct)))
    total = volume_change_pct(volume.sum(), initial_volume.sum())
    return {
        "max_element_pct": float(pct[k]),
        "max_element_id": None if element_ids is None else int(np.asarray(element_ids)[k]),
        "total_pct": float(total),
    }
