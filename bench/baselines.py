"""The methods an analyst would use instead of kneegui, on the same model and bone poses.

Both baselines are driven by the same rigid bone transforms kneegui uses
(:func:`kneegui.kinematics.posing.solve_bone_pose`), so they differ from kneegui only in how the
soft tissue follows the bones:

``rigid``
    Rigid segment rotation, what a user does with a transform tool. Every node of the moving
    segment's side is moved with that segment's rigid transform (the tibia's when the leg moves):
    the moving segment's bone nodes, plus every soft-tissue node on that side of the knee's
    bisector plane. The bisector plane contains the knee centre and the flexion-extension axis
    and halves the angle between the thigh (``axes.superior``) and the leg (``-tibia axis``) in
    the initial pose. Femur, patella and fixed nodes follow their own transforms (the patella is
    selected as a whole part, as a careful user would), every other node stays.

``rbf``
    Radial-basis (kriging) morph with bone nodes as control points, the approach of the PIPER
    framework's kriging module. Control points: a farthest-point subsample of the bone *surface*
    nodes of each rigid segment (femur, tibia + fibula, patella) and of any fixed part, at most
    :data:`RBF_CONTROL_POINTS` in total, shared among the segments in proportion to their
    surface-node counts (at least :data:`RBF_MIN_PER_SEGMENT` each). Their displacements (posed
    minus initial) are interpolated with
    ``scipy.interpolate.RBFInterpolator(kernel="thin_plate_spline")`` (degree-1 polynomial,
    no smoothing) and the interpolant is evaluated at every soft-tissue node; bone nodes take their
    bone's rigid transform.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import RBFInterpolator

from kneegui.geometry.axes import JointAxes
from kneegui.kinematics.posing import BonePose
from kneegui.model import Model
from kneegui.reposition import NodeGroups

#: Total number of RBF control points (bone-surface nodes) over all segments.
RBF_CONTROL_POINTS = 1000
#: Fewest control points any segment with surface nodes gets.
RBF_MIN_PER_SEGMENT = 50
#: Segments whose nodes are rigid (same order as the repositioner's).
RIGID_SEGMENTS = ("femur", "tibia", "patella", "fixed")
BASELINES = ("rigid", "rbf")


@dataclass(frozen=True)
class RbfControl:
    """The RBF control points: node indices and the segment each one belongs to."""

    nodes: NDArray[np.int64]
    segment: NDArray[np.str_]


def _bone_coords(
    coords0: NDArray[np.float64], groups: NodeGroups, bone: BonePose
) -> NDArray[np.float64]:
    """Initial coordinates with every rigid segment's nodes moved by its transform."""
    out = coords0.copy()
    for name in ("femur", "tibia", "patella"):
        idx = groups.segment[name]
        if len(idx):
            out[idx] = bone.transforms[name].apply(coords0[idx])
    return out


def moving_side_mask(
    coords0: NDArray[np.float64], axes: JointAxes, moving_segment: str
) -> NDArray[np.bool_]:
    """True for nodes on the moving segment's side of the knee's bisector plane.

    Parameters
    ----------
    coords0 : (N, 3) ndarray
        Initial coordinates (mm).
    axes : JointAxes
        Axes of the initial pose.
    moving_segment : {"tibia", "femur"}
        Which side moves.

    Returns
    -------
    (N,) ndarray of bool
    """
    thigh = axes.superior / np.linalg.norm(axes.superior)
    leg = -axes.tibia_axis.direction / np.linalg.norm(axes.tibia_axis.direction)
    normal = thigh - leg  # points to the thigh side; the plane halves the thigh-leg angle
    normal -= np.dot(normal, axes.fe_axis.direction) * axes.fe_axis.direction
    side = (coords0 - axes.knee_center) @ normal
    return side < 0 if moving_segment == "tibia" else side > 0


def rigid_segment_rotation(
    model: Model,
    groups: NodeGroups,
    axes: JointAxes,
    bone: BonePose,
    moving_segment: str = "tibia",
) -> NDArray[np.float64]:
    """Pose by rigidly rotating the moving segment's side of the knee (see module docstring).

    Parameters
    ----------
    model : Model
        Initial pose.
    groups : NodeGroups
        From :func:`kneegui.reposition.classify_nodes`.
    axes : JointAxes
        Axes of the initial pose.
    bone : BonePose
        Bone transforms of the target flexion.
    moving_segment : {"tibia", "femur"}
        The segment that moves (``JointSetup.moving_segment``).

    Returns
    -------
    (N, 3) ndarray of float64
        New coordinates (mm).
    """
    coords0 = model.coords
    out = _bone_coords(coords0, groups, bone)
    side = moving_side_mask(coords0, axes, moving_segment)
    soft = groups.soft[side[groups.soft]]
    out[soft] = bone.transforms[moving_segment].apply(coords0[soft])
    return out


def farthest_point_subsample(points: NDArray[np.float64], count: int) -> NDArray[np.int64]:
    """Indices of ``count`` points picked greedily, each farthest from those already picked.

    Deterministic: starts from the point farthest from the centroid.
    """
    n = len(points)
    if count >= n:
        return np.arange(n, dtype=np.int64)
    picked = np.empty(count, dtype=np.int64)
    picked[0] = int(np.argmax(np.linalg.norm(points - points.mean(axis=0), axis=1)))
    dist = np.linalg.norm(points - points[picked[0]], axis=1)
    for k in range(1, count):
        picked[k] = int(np.argmax(dist))
        np.minimum(dist, np.linalg.norm(points - points[picked[k]], axis=1), out=dist)
    return picked


def rbf_control_points(
    coords0: NDArray[np.float64], groups: NodeGroups, total: int = RBF_CONTROL_POINTS
) -> RbfControl:
    """The documented control-point subsample (see module docstring).

    Parameters
    ----------
    coords0 : (N, 3) ndarray
        Initial coordinates (mm).
    groups : NodeGroups
        Rigid segments and bone-surface nodes.
    total : int
        Control points over all segments.
    """
    candidates: dict[str, NDArray[np.int64]] = {}
    for name in RIGID_SEGMENTS:
        seg = groups.segment[name]
        surface = seg if name == "fixed" else np.intersect1d(seg, groups.bone_surface)
        if len(surface) == 0:
            surface = seg
        if len(surface):
            candidates[name] = surface
    n_all = sum(len(c) for c in candidates.values())
    nodes, labels = [], []
    for name, cand in candidates.items():
        share = max(RBF_MIN_PER_SEGMENT, round(total * len(cand) / n_all))
        pick = cand[farthest_point_subsample(coords0[cand], min(share, len(cand)))]
        nodes.append(pick)
        labels.append(np.full(len(pick), name))
    return RbfControl(np.concatenate(nodes), np.concatenate(labels))


def rbf_morph(
    model: Model, groups: NodeGroups, bone: BonePose, control: RbfControl
) -> NDArray[np.float64]:
    """Pose by a thin-plate-spline RBF morph of the soft tissue driven by bone control points.

    Parameters
    ----------
    model : Model
        Initial pose.
    groups : NodeGroups
        From :func:`kneegui.reposition.classify_nodes`.
    bone : BonePose
        Bone transforms of the target flexion.
    control : RbfControl
        From :func:`rbf_control_points` (computed once per model).

    Returns
    -------
    (N, 3) ndarray of float64
        New coordinates (mm).
    """
    coords0 = model.coords
    out = _bone_coords(coords0, groups, bone)
    src = coords0[control.nodes]
    displacement = out[control.nodes] - src
    interpolant = RBFInterpolator(src, displacement, kernel="thin_plate_spline")
    soft = groups.soft
    out[soft] = coords0[soft] + interpolant(coords0[soft])
    return out


def bone_rigidity_error(
    coords0: NDArray[np.float64],
    coords: NDArray[np.float64],
    bone_nodes: dict[str, NDArray[np.int64]],
    pairs: int = 5000,
    seed: int = 0,
) -> dict[str, float]:
    """Largest relative change of pairwise node distances inside each bone.

    Parameters
    ----------
    coords0, coords : (N, 3) ndarray
        Initial and posed coordinates (mm).
    bone_nodes : dict of str to (k,) ndarray of int
        Node indices of each bone (every node of its parts).
    pairs : int
        Random node pairs sampled per bone (fixed ``seed``; pairs closer than 1e-9 mm skipped).

    Returns
    -------
    dict
        Bone name -> ``max |d - d0| / d0`` over its sampled pairs (0 for a rigid motion), plus
        ``"max"`` over every bone.
    """
    rng = np.random.default_rng(seed)
    out: dict[str, float] = {}
    for name, idx in bone_nodes.items():
        if len(idx) < 2:
            continue
        a = idx[rng.integers(0, len(idx), pairs)]
        b = idx[rng.integers(0, len(idx), pairs)]
        d0 = np.linalg.norm(coords0[a] - coords0[b], axis=1)
        keep = d0 > 1e-9
        d = np.linalg.norm(coords[a[keep]] - coords[b[keep]], axis=1)
        out[name] = float(np.max(np.abs(d - d0[keep]) / d0[keep])) if keep.any() else 0.0
    out["max"] = max(out.values(), default=0.0)
    return out
