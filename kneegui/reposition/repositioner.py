"""The repositioner: precompute once per setup, then pose the whole model at any flexion, cheaply.

Methods (``RepositionOptions.method``), compared in docs/repositioning.md:

``"paper"``
    Jani et al. 2012 as reconstructed in ALGORITHM.md: bones rigid, skin by contours, flesh and
    capsule by barycentric coordinates in a Delaunay tetrahedralisation of bone-surface + skin
    nodes, ligament / meniscus / tendon nodes by a tetrahedralisation of the skin nodes only.
``"blend"``
    Every soft-tissue node follows a blend of the bones' rigid motions with harmonic weights
    (see :mod:`kneegui.reposition.rigid_blend`); no tetrahedron spans the joint, so nothing shears.

Whatever the method, the export then improves the tissue the mapping degraded
(:meth:`Repositioner.improve`: the mesh-improvement chain of :mod:`kneegui.meshopt.chain` in the
region :mod:`kneegui.reposition.relax` sets up, untangling inverted elements and keeping tissue
out of the bones); :meth:`Repositioner.pose` (the live slider) skips that.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from kneegui.errors import Cancelled, SetupError, raise_if_cancelled
from kneegui.geometry.axes import JointAxes, compute_joint_axes, measure_flexion
from kneegui.kinematics.posing import BonePose, solve_bone_pose
from kneegui.meshopt.chain import (
    ImprovementOptions,
    ImprovementReport,
    StageCallback,
    improve_region,
)
from kneegui.meshopt.quality_optimiser import quality_aims
from kneegui.meshopt.smoothing_pipeline import smooth_posed_model
from kneegui.meshopt.volume_correction import VolumeCorrection, VolumeCorrectionOptions
from kneegui.model import Model
from kneegui.quality import compute_quality
from kneegui.quality.metrics import QualityResult
from kneegui.reposition.bone_overlap import BoneOverlap, BoneOverlapCheck
from kneegui.reposition.checks import surface_triangles
from kneegui.reposition.contact import BoneContact, BoneDepthGuard, BoneSurfaceDistance
from kneegui.reposition.embedding import Embedding, embed_nodes
from kneegui.reposition.midside import TET10_MIDSIDE, MidsideNodes
from kneegui.reposition.patella_tracking import PatellaSeating
from kneegui.reposition.relax import (
    ElasticRelaxation,
    RelaxedRegion,
    RelaxOptions,
    RelaxReport,
    shell_face_tetrahedra,
)
from kneegui.reposition.rigid_blend import (
    exp_twists_apply,
    harmonic_weights,
    log_rigid,
    mesh_edges,
    surface_distances,
)
from kneegui.reposition.skin_contours import (
    WEIGHT_SHAPES,
    SkinContours,
    SkinPoseReport,
    build_skin_contours,
    pose_skin,
)
from kneegui.setup.condyles import surface_node_indices
from kneegui.setup.format import JointSetup
from kneegui.setup.kinematic_tables import SUPPORTED_FLEXION_DEG
from kneegui.topology import corner_tetrahedra, sorted_unique

SOFT_ROLES = ("skin", "flesh", "ligament", "meniscus", "tendon", "capsule")
#: Tissues the paper maps to the skin contours only.
BAND_ROLES = ("ligament", "meniscus", "tendon")
METHODS = ("paper", "blend")
SEGMENTS = ("femur", "tibia", "patella", "fixed")


ProgressCallback = Callable[[float, str], None]


def smoothing_parts(setup: JointSetup) -> tuple[list[int], list[int]]:
    """The parts the export's smoothing may move (soft tissue less the skin, which keeps its
    mapped and relaxed surface) and the parts whose nodes stay (bones, ``fixed`` and unassigned
    parts, as :func:`classify_nodes` keeps them)."""
    fixed = set(setup.parts_of("femur", "tibia", "fibula", "patella", "fixed"))
    fixed |= set(setup.unassigned_parts)
    movable = set(setup.parts_of(*SOFT_ROLES)) - set(setup.parts_of("skin"))
    return sorted(movable), sorted(fixed)


def tissue_in_bones_warnings(found: Mapping[str, Any]) -> list[str]:
    """One warning line per bone with tissue inside it, from
    :meth:`Repositioner.tissue_in_bones` (the pose report's and the GUI's wording)."""
    return [
        f"{b['nodes']} soft-tissue node(s) deeper than {found['tolerance']:.3g} inside the "
        f"{name} (deepest {b['deepest']:.3g})"
        for name, b in found["bones"].items()
        if b["nodes"]
    ]


#: Patella and femur surface nodes closer than this to the other bone at rest (in mean condyle
#: radii, 11 mm on the demo) are watched by the patellar seating.
PATELLA_SEATING_BAND = 0.5
#: The patellar lift is worked out every this many degrees from the initial flexion and
#: interpolated.
PATELLA_LIFT_STEP = 1.0

#: The knee size the options' lengths are stated for (mm): the mean of the lateral and medial
#: posterior condyle radii Jani et al. (2012) measured, 20.5 and 23.3 mm. Every length option
#: (model units) is multiplied by the model's own mean condyle radius over this
#: (:attr:`Repositioner.length_scale`), so a model in metres, or a smaller knee, is posed with
#: the same relative clearances and tolerances.
REFERENCE_CONDYLE_RADIUS_MM = 21.9

#: Options read only by the export (:meth:`Repositioner.improve`), after the precompute and the
#: relaxation's set-up, which they do not change: :meth:`Repositioner.with_options` shares the
#: precompute when only these change.
EXPORT_ONLY_OPTIONS = frozenset({"volume_correction"})

#: Depth (in mean condyle radii, about 0.45 mm on the demo) beyond which a soft-tissue node counts
#: as inside a bone in the pose report: nodes of a sliding interface lie on the surface itself.
TISSUE_IN_BONE_TOLERANCE = 0.02


@dataclass(frozen=True)
class RepositionOptions:
    """Tunable choices of the repositioner (all have measured defaults).

    Lengths (``coupling_length``, ``contact_clearance``, ``contour_margin`` and those of
    ``improvement``'s stages) are millimetres of a knee of the reference size
    (:data:`REFERENCE_CONDYLE_RADIUS_MM`); the repositioner scales them to the model
    (:attr:`Repositioner.length_scale`). Reaches and regions are in mean condyle radii.

    Attributes
    ----------
    method : str
        ``"paper"`` or ``"blend"``.
    zone_factor : float
        Parallelizing zone length as a multiple of the skin radius at the joint.
    weight_shape : str
        Parallelizing weight: ``"linear"`` (the paper), ``"cosine"`` or ``"smoothstep"``.
    max_scale : float
        Cap of the volume-preserving scale factor of a skin point.
    clearance_fraction : float
        A skin node closer to a bone than this fraction of its initial clearance is pushed out.
    regularisation : float
        Pull of the harmonic weights towards the distance prior.
    coupling_strength, coupling_length, coupling_radii
        Pull of tissue lying on a bone towards that bone's motion: strength (relative to the
        mean node degree), decay length from the bone surface (model units), and the distances
        from the F-E axis (in mean condyle radii) over which it fades in from zero.
    relax : bool
        Relax the degraded tissue after the mapping in :meth:`Repositioner.pose_detailed` (the
        export); :meth:`Repositioner.pose` never does.
    relax_reach : float
        Only soft-tissue nodes within this many mean condyle radii of the F-E axis may be
        relaxed (bounds the precompute on large models; 7 was measured and not kept,
        docs/repositioning.md).
    relax_region : float
        The relaxed region reaches this many mean condyle radii around the degraded tissue.
    improvement : ImprovementOptions
        The mesh-improvement chain's stages after the mapping (:mod:`kneegui.meshopt.chain`):
        the untangling energy, the quality optimisation and the smoothing.
    volume_change : float or None
        In the quality optimisation, every soft solid element aims to keep its volume within
        ``1 + volume_change`` times its initial volume, either way (None: no limit, and the
        optimiser may shrink an element whose proportions stay good). The penalty is soft, so
        the aim sits a margin under what the export is held to (issue 23: the 95th percentile of
        the soft solids' volume change at most 25 % at 90 deg): with 0.2 that percentile settled
        at 23.5-25.2 % on the coarse hex variants, on the bound; with 0.15 at 20.9-22.2 %
        (docs/repositioning.md, *Volume kept element by element*). Tighter aims trade volume
        against the bone contact (docs/repositioning.md, known limits).
    contour_margin : float or None
        In the quality optimisation, every skin contour keeps at least this far (model units)
        beyond the plane of its neighbour nearer the joint, so that no contour crosses another;
        None lets them cross, which gives the crease behind a deeply flexed knee more room.
    contact_reach, contact_clearance
        Soft-tissue nodes within ``contact_reach`` mean condyle radii of a bone slide on it but
        are kept out of it, at their rest clearance up to ``contact_clearance``;
        ``contact_reach = 0`` (the default) turns contact off; 0.25 is a good value when
        penetrations matter more than element quality (see :mod:`kneegui.reposition.contact`
        and docs/repositioning.md for the measured trade-off).
    relax_contact_reach : float
        Before the relaxation (the export, never the slider), the same push out of the bones
        with this reach, so that the relaxation starts with the tissue outside the bones and the
        push spread smoothly through the tissue behind it (0 turns it off; ignored when
        ``contact_reach`` already applies it to every pose).
    patella_tracking : bool
        Lift the patella off the femur after its tables, radially from the F-E axis, by the
        smallest distance that gives back its rest clearance
        (:mod:`kneegui.reposition.patella_tracking`); off: the tables alone.
    push_ray_depth : (float, float) or None
        How the push chooses where a node leaves the bone, by its depth in mean condyle radii:
        shallower than the first value, at the nearest surface point (it slides on the bone);
        deeper than the second, where the straight way back to its rest place relative to that
        bone leaves it (the mapping carried it in along a smooth field, so neighbours leave at
        neighbouring places instead of at opposite faces of the bone); blended in between.
        ``None``: always the nearest point.
    volume_correction : VolumeCorrectionOptions or None
        Before the relaxation (the export, never the slider), one smoothed, linearised step that
        gives the soft solids back their rest volumes over the relaxable region
        (:mod:`kneegui.meshopt.volume_correction`): the mapping's long-wavelength volume change,
        which the quality stage's local moves remove on a coarse mesh but not on a fine one.
        ``None`` (the default) leaves it out: on the coarse demo built at 0° it left the export
        at 120° worse (docs/repositioning.md, "The mapping's volume change restored before the
        relaxation"). ``kneegui pose --restore-volume`` turns it on.
    """

    method: str = "blend"
    zone_factor: float = 2.0
    weight_shape: str = "cosine"
    max_scale: float = 2.0
    clearance_fraction: float = 0.5
    regularisation: float = 1e-4
    coupling_strength: float = 1.0
    coupling_length: float = 3.0
    coupling_radii: tuple[float, float] = (2.5, 4.5)
    contact_reach: float = 0.0
    contact_clearance: float = 0.5
    relax_contact_reach: float = 0.75
    push_ray_depth: tuple[float, float] | None = (0.05, 0.3)
    patella_tracking: bool = True
    relax: bool = True
    relax_reach: float = 5.0
    relax_region: float = 1.0
    improvement: ImprovementOptions = field(default_factory=ImprovementOptions)
    volume_change: float | None = 0.15
    contour_margin: float | None = 0.5
    volume_correction: VolumeCorrectionOptions | None = None

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise SetupError(
                f"unknown method {self.method!r}; choose one of {METHODS}", key="method"
            )
        if self.weight_shape not in WEIGHT_SHAPES:
            raise SetupError(
                f"unknown weight shape {self.weight_shape!r}; choose one of {WEIGHT_SHAPES}",
                key="weight_shape",
            )
        if not (self.zone_factor > 0 and self.max_scale >= 1 and 0 <= self.clearance_fraction < 1):
            raise SetupError(
                "zone_factor > 0, max_scale >= 1 and 0 <= clearance_fraction < 1 are required",
                key="options",
            )
        if self.push_ray_depth is not None:
            lo, hi = self.push_ray_depth
            if not 0 <= lo <= hi:
                raise SetupError(
                    f"push_ray_depth must be (shallow, deep) with 0 <= shallow <= deep, got "
                    f"{self.push_ray_depth!r}",
                    key="push_ray_depth",
                )


@dataclass(frozen=True)
class PoseResult:
    """One pose: all node coordinates and what was done to get them."""

    coords: NDArray[np.float64]
    target_flexion_deg: float
    achieved_flexion_deg: float
    bone_pose: BonePose
    skin: SkinPoseReport | None
    timings_s: dict[str, float] = field(default_factory=dict)
    relaxation: RelaxReport | None = None


@dataclass(frozen=True)
class NodeGroups:
    """How every node of the model is moved."""

    segment: dict[str, NDArray[np.int64]]  # rigid: femur, tibia, patella, fixed
    skin: NDArray[np.int64]
    band: NDArray[np.int64]  # ligament, meniscus, tendon
    flesh: NDArray[np.int64]  # flesh, capsule and any other soft node
    bone_surface: NDArray[np.int64]

    @property
    def soft(self) -> NDArray[np.int64]:
        """All soft-tissue nodes that move by mapping."""
        return np.concatenate([self.skin, self.band, self.flesh])


def classify_nodes(model: Model, setup: JointSetup) -> NodeGroups:
    """Split the model's nodes into rigid groups and soft-tissue groups.

    Bone nodes move with their bone (a soft-tissue node shared with a bone, e.g. a ligament's
    attachment, is a bone node). Nodes of ``fixed`` or unassigned parts stay where they are.
    """
    n = model.n_nodes
    taken = np.zeros(n, dtype=bool)
    segment: dict[str, NDArray[np.int64]] = {}
    for name in ("femur", "tibia", "patella"):
        idx = np.asarray(setup.segment_nodes[name], dtype=np.int64)
        idx = idx[~taken[idx]]
        taken[idx] = True
        segment[name] = idx
    fixed_parts = list(setup.roles["fixed"]) + list(setup.unassigned_parts)
    fixed = model.part_node_indices(fixed_parts)
    fixed = fixed[~taken[fixed]]
    taken[fixed] = True
    segment["fixed"] = fixed

    def soft_of(*roles: str) -> NDArray[np.int64]:
        idx = model.part_node_indices(setup.parts_of(*roles))
        return idx[~taken[idx]]

    skin = soft_of("skin")
    taken[skin] = True
    band = soft_of(*BAND_ROLES)
    taken[band] = True
    flesh = soft_of("flesh", "capsule")
    taken[flesh] = True
    bone_parts = setup.parts_of("femur", "tibia", "fibula", "patella")
    surface = surface_node_indices(model, bone_parts)
    return NodeGroups(segment, skin, band, flesh, surface)


class Repositioner:
    """Re-pose a model's knee: precompute in the constructor, then :meth:`pose` per angle.

    Parameters
    ----------
    model : Model
        The model in its initial pose.
    setup : JointSetup
        Validated setup of that model (:func:`kneegui.setup.load_setup`).
    options : RepositionOptions, optional
        Method and parameters (default: the measured best, see docs/repositioning.md).
    progress : callable, optional
        ``progress(fraction, message)`` during the precompute.
    cancel : callable, optional
        Returns True to abandon the precompute (raises :class:`kneegui.errors.Cancelled`).

    Attributes
    ----------
    axes : JointAxes
        Axes of the initial pose.
    initial_flexion : float
        Measured flexion of the initial pose (degrees).
    groups : NodeGroups
        How every node moves.
    length_scale : float
        Model units per millimetre of a knee of the reference size: the model's mean condyle
        radius over :data:`REFERENCE_CONDYLE_RADIUS_MM` (1 for a knee of that size in mm,
        0.001 for the same knee in metres). Every length option is multiplied by it.
    timings_s : dict
        Seconds spent in each precompute stage.
    """

    def __init__(
        self,
        model: Model,
        setup: JointSetup,
        options: RepositionOptions | None = None,
        progress: ProgressCallback | None = None,
        cancel: Callable[[], bool] | None = None,
    ) -> None:
        if setup.n_nodes != model.n_nodes:
            raise SetupError(
                f"the setup was validated on a model with {setup.n_nodes} nodes, this one has "
                f"{model.n_nodes}",
                key="model",
            )
        self.model = model
        self.setup = setup
        self.options = options or RepositionOptions()
        self.timings_s: dict[str, float] = {}
        self._progress = progress or (lambda fraction, message: None)
        self._cancel = cancel or (lambda: False)
        coords = model.coords
        t = self._stage("axes", 0.0)
        self.axes: JointAxes = compute_joint_axes(coords, setup)
        self.initial_flexion = float(self.axes.initial_flexion_deg)
        self.length_scale = self._condyle_size() / REFERENCE_CONDYLE_RADIUS_MM
        self._end("axes", t)
        t = self._stage("node groups", 0.1)
        self.groups = classify_nodes(model, setup)
        self._end("node groups", t)
        method = self.options.method
        self.contours: SkinContours | None = None
        self._flesh_embedding: Embedding | None = None
        self._band_embedding: Embedding | None = None
        self._weights: NDArray[np.float64] | None = None
        if method == "paper":
            if len(self.groups.skin) < 4:
                raise SetupError(
                    "the paper method needs skin nodes: give the skin parts the "
                    "'skin' role, or use method 'blend'",
                    key="roles.skin",
                )
            t = self._stage("skin contours", 0.2)
            self.contours = self._build_contours()
            self._end("skin contours", t)
        if method == "blend":
            t = self._stage("harmonic weights", 0.4)
            self._weights = self._harmonic_weights()
            self._end("harmonic weights", t)
        if method == "paper":
            t = self._stage("delaunay embedding", 0.7)
            control = np.concatenate(
                [self.groups.bone_surface, self.groups.skin, self._fixed_surface()]
            )
            self._flesh_embedding = embed_nodes(coords, control, self.groups.flesh)
            if len(self.groups.band):
                self._band_embedding = embed_nodes(coords, self.groups.skin, self.groups.band)
            self._end("delaunay embedding", t)
        self._surfaces: dict[str, BoneSurfaceDistance] | None = None  # built on first use
        self._seating: PatellaSeating | None = None
        self._lifts: dict[int, float] = {}  # patellar lift at grid step k (bone_pose)
        if self.options.patella_tracking and len(self.groups.segment["patella"]):
            t = self._stage("patella seating", 0.8)
            self._seating = self._patella_seating()
            self._end("patella seating", t)
        self._contact: BoneContact | None = None
        if self.options.contact_reach > 0:
            t = self._stage("bone contact", 0.85)
            self._contact = self._bone_contact(self.options.contact_reach)
            self._end("bone contact", t)
        self._relax_contact: BoneContact | None = None  # built on first use, like the relaxation
        # the relaxation's precompute is left to its first use: the slider never needs it, and
        # on a 1M-element model it costs more than everything above
        self._volume_correction: VolumeCorrection | None = None  # built on first use
        self.relaxation: ElasticRelaxation | None = None
        self._overlap_check: BoneOverlapCheck | None = None
        self._near_soft: NDArray[np.int64] | None = None  # soft nodes the in-bone check measures
        soft = np.zeros(model.n_nodes, dtype=bool)
        soft[self.groups.soft] = True
        # 10-node tets: every stage places mid-side nodes one by one; they end on their edges
        self._midside = MidsideNodes.of_block(model.blocks.get("tet10"), soft, model.coords)
        self._order_contours: SkinContours | None = None  # for blend: the relaxation's order
        self._initial_quality: QualityResult | None = None  # the smoothing's reference
        self._quality_memo: tuple[NDArray[np.float64], QualityResult] | None = None
        self._progress(1.0, "ready")

    # ---------------------------------------------------------------------- precompute
    def _stage(self, name: str, fraction: float) -> float:
        if self._cancel():
            raise Cancelled(f"precompute cancelled before {name}")
        self._progress(fraction, name)
        return time.perf_counter()

    def _end(self, name: str, t0: float) -> None:
        self.timings_s[name] = time.perf_counter() - t0

    def _condyle_size(self) -> float:
        """The mean condyle radius (model units): the knee's own length scale."""
        return 0.5 * (self.axes.lateral_fit.radius + self.axes.medial_fit.radius)

    def _fixed_surface(self) -> NDArray[np.int64]:
        return self.groups.segment["fixed"]

    def _harmonic_weights(self) -> NDArray[np.float64]:
        model, groups = self.model, self.groups
        soft_parts = np.array(self.setup.parts_of(*SOFT_ROLES), dtype=np.int64)
        masks = {etype: np.isin(b.part_ids, soft_parts) for etype, b in model.blocks.items()}
        edges = mesh_edges(model.blocks, masks)
        anchors = [groups.segment[s] for s in SEGMENTS]
        surfaces = [
            np.intersect1d(groups.segment[s], groups.bone_surface)
            if s != "fixed"
            else groups.segment[s]
            for s in SEGMENTS
        ]
        surfaces = [srf if len(srf) else anc for srf, anc in zip(surfaces, anchors, strict=True)]
        # the prior and the bone coupling both need these: one search per surface
        distance = surface_distances(model.coords, groups.soft, surfaces)
        return harmonic_weights(
            model.n_nodes,
            edges,
            groups.soft,
            anchors,
            model.coords,
            surfaces,
            self.options.regularisation,
            prior_strength=self._bone_coupling(distance[:, :3]),
            cancel=self._cancel,
            surface_distance=distance,
        )

    def _bone_coupling(self, bone_distance: NDArray[np.float64]) -> NDArray[np.float64]:
        """How strongly each soft node is pulled to the bone it lies on.

        Tissue lying on a bone (within ``coupling_length`` of its surface) follows that bone
        away from the joint, where it is attached in a real limb, but is free to slide in the
        joint region, so that nothing is torn between femur and tibia. The pull fades in
        smoothly with the distance from the F-E axis, from ``coupling_radii[0]`` to
        ``coupling_radii[1]`` times the mean condyle radius. ``bone_distance``: each soft
        node's distance to each moving bone's surface (:func:`surface_distances`).
        """
        opt = self.options
        coords = self.model.coords
        soft = self.groups.soft
        if opt.coupling_strength <= 0 or not np.isfinite(bone_distance).any():
            return np.zeros(len(soft))
        d = bone_distance.min(axis=1)
        rel = coords[soft] - self.axes.fe_axis.point
        axial = rel @ self.axes.fe_axis.direction
        r = np.linalg.norm(rel - axial[:, None] * self.axes.fe_axis.direction, axis=1)
        size = 0.5 * (self.axes.lateral_fit.radius + self.axes.medial_fit.radius)
        lo, hi = (k * size for k in opt.coupling_radii)
        t = np.clip((r - lo) / max(hi - lo, 1e-9), 0.0, 1.0)
        fade = t * t * (3.0 - 2.0 * t)
        return opt.coupling_strength * np.exp(-d / (opt.coupling_length * self.length_scale)) * fade

    def _bone_triangles(self) -> dict[str, NDArray[np.int64]]:
        """Outer surface triangles of each moving segment (solids' faces, else its shells)."""
        model, setup = self.model, self.setup
        triangles = {}
        for segment, roles in (
            ("femur", ("femur",)),
            ("tibia", ("tibia", "fibula")),
            ("patella", ("patella",)),
        ):
            parts = setup.parts_of(*roles)
            tris = surface_triangles(model, parts, shells=False)
            triangles[segment] = tris if len(tris) else surface_triangles(model, parts)
        return triangles

    def _bone_surfaces(self) -> dict[str, BoneSurfaceDistance]:
        """Each moving segment's rest surface for distance queries, built once (the bone contact,
        the relaxation's contact and the bone-overlap check share it)."""
        if self._surfaces is None:
            # exact as far out as the relaxation's contact looks (its planes' band)
            relax = self.options.improvement.relax or RelaxOptions()
            band = relax.contact_band * self.length_scale
            self._surfaces = {
                name: BoneSurfaceDistance(self.model.coords[tris], exact_within=band)
                for name, tris in self._bone_triangles().items()
                if len(tris)
            }
        return self._surfaces

    def _build_contours(self) -> SkinContours:
        """The skin's contours in the initial pose (ALGORITHM.md §3)."""
        return build_skin_contours(
            self.model.coords,
            self.groups.skin,
            self.axes.knee_center,
            self.axes.superior,
            self.axes.tibia_axis.direction,
            self.setup.skin_contours,
            self.options.zone_factor,
            self.groups.bone_surface,
        )

    def _patella_seating(self) -> PatellaSeating | None:
        """The patella's seating on the femur (None without both surfaces)."""
        surfaces = self._bone_surfaces()
        if "patella" not in surfaces or "femur" not in surfaces:
            return None
        size = 0.5 * (self.axes.lateral_fit.radius + self.axes.medial_fit.radius)
        axis = self.axes.fe_axis
        return PatellaSeating(
            surfaces["patella"],
            surfaces["femur"],
            axis.point,
            axis.direction,
            band=PATELLA_SEATING_BAND * size,
            length_scale=self.length_scale,
        )

    def initial_quality(self, cancel: Callable[[], bool] | None = None) -> QualityResult:
        """Quality of the initial model (every element), computed once and shared by the
        relaxation's aims, the smoothing's goals and the export's report (``cancel`` as for
        :func:`~kneegui.quality.compute_quality`)."""
        if self._initial_quality is None:
            self._initial_quality = compute_quality(
                self.model.coords, self.model.blocks, cancel=cancel
            )
        return self._initial_quality

    def quality_of(
        self, coords: NDArray[np.float64], cancel: Callable[[], bool] | None = None
    ) -> QualityResult:
        """Quality of every element at ``coords``, remembered for the last coordinates asked
        about: the smoothing and the export's report measure the same relaxed pose (``cancel``
        as for :func:`~kneegui.quality.compute_quality`)."""
        memo = self._quality_memo
        if memo is not None and memo[0].shape == coords.shape and np.array_equal(memo[0], coords):
            return memo[1]
        result = compute_quality(coords, self.model.blocks, cancel=cancel)
        self._quality_memo = (np.array(coords, copy=True), result)
        return result

    def _elastic_relaxation(self, cancel: Callable[[], bool] | None = None) -> ElasticRelaxation:
        model, g = self.model, self.groups
        soft_parts = np.array(self.setup.parts_of(*SOFT_ROLES), dtype=np.int64)
        free = self._soft_near_joint()
        raise_if_cancelled(cancel, "relaxation set-up cancelled")
        near = np.zeros(model.n_nodes, dtype=bool)
        near[free] = True
        # only the soft elements with a node the relaxation may move: the relaxation keeps no
        # other (their corners would have no free node), and building the geometry of every
        # soft element of a whole-body model cost more than the knee's relaxation itself
        solids = {
            e: np.isin(b.part_ids, soft_parts) & near[b.conn].any(axis=1)
            for e, b in model.blocks.items()
        }
        shells = {e: solids.pop(e) for e in ("quad4", "tri3") if e in solids}
        face_tets, virtual = shell_face_tetrahedra(model.blocks, shells, solids, model.n_nodes)
        raise_if_cancelled(cancel, "relaxation set-up cancelled")
        # one array of corners, not the two it is made of as well (a whole-body model's region
        # has millions)
        tets = np.concatenate([corner_tetrahedra(model.blocks, solids, cancel), face_tets])
        del face_tets
        size = 0.5 * (self.axes.lateral_fit.radius + self.axes.medial_fit.radius)
        raise_if_cancelled(cancel, "relaxation set-up cancelled")
        initial = self.initial_quality(cancel)
        raise_if_cancelled(cancel, "relaxation set-up cancelled")
        options = (self.options.improvement.relax or RelaxOptions()).scaled(self.length_scale)
        if options.slide_skin is None:
            options = replace(options, slide_skin=self.options.method == "blend")
        margin = self.options.contour_margin
        contours = self._relaxed_contours() if margin is not None else None
        if margin is not None:
            margin *= self.length_scale
        return ElasticRelaxation(
            model.coords,
            tets,
            free,
            self._bone_surfaces(),
            options=options,
            virtual=virtual,
            attached=np.concatenate([g.segment[s] for s in ("femur", "tibia", "patella")]),
            quads=model.blocks["quad4"].conn[shells["quad4"]] if "quad4" in shells else None,
            region_radius=self.options.relax_region * size,
            sliding=g.skin,
            blocks=model.blocks,
            aims=quality_aims(
                initial,
                model.blocks,
                rest_coords=model.coords,
                volume_change=self.options.volume_change,
            ),
            skin_contours=contours,
            contour_margin=margin,
            segment_of=self._segment_of(),
            beyond=g.soft,
            initial_quality=initial,
            cancel=cancel,
        )

    def _segment_of(self) -> NDArray[np.int64]:
        """(N,) index of the rigid segment (femur, tibia, patella, fixed) each node moves with,
        -1 for the soft tissue."""
        out = np.full(self.model.n_nodes, -1, dtype=np.int64)
        for k, name in enumerate(SEGMENTS):
            out[self.groups.segment[name]] = k
        return out

    def _relaxed_contours(self) -> SkinContours | None:
        """The skin contours the relaxation keeps in order (the method's own, else built once;
        None without skin)."""
        if self.contours is None and self._order_contours is None and len(self.groups.skin) >= 4:
            self._order_contours = self._build_contours()
        return self.contours if self.contours is not None else self._order_contours

    def _soft_near_joint(self) -> NDArray[np.int64]:
        """Soft-tissue nodes within ``relax_reach`` mean condyle radii of the F-E axis (at rest),
        and every node of a skin contour one of them belongs to, and the soft mid-side node of
        every 10-node tet edge with an end among them: those the relaxation may move and the
        in-bone check measures. Computed once.

        Whole contours, because a contour that is free only on the side nearer the axis (its
        anterior and posterior nodes lie farther from it than its medial and lateral ones) can
        be held in order neither by nor against its free neighbour: the default demo at 120 deg
        kept 8 nodes of such a contour behind the tilted plane of the next one."""
        if self._near_soft is None:
            axis = self.axes.fe_axis
            rel = self.model.coords[self.groups.soft] - axis.point
            radial = rel - np.outer(rel @ axis.direction, axis.direction)
            size = 0.5 * (self.axes.lateral_fit.radius + self.axes.medial_fit.radius)
            reach = self.options.relax_reach * size
            near = self.groups.soft[np.linalg.norm(radial, axis=1) < reach]
            contours = self._relaxed_contours()
            if contours is not None:
                in_near = np.zeros(self.model.n_nodes, dtype=bool)
                in_near[near] = True
                touched = sorted_unique(contours.contour[in_near[contours.nodes]])
                near = np.union1d(near, contours.nodes[np.isin(contours.contour, touched)])
            block = self.model.blocks.get("tet10")
            if block is not None and len(block):
                # a skin edge's mid-side node is no skin contour node: left behind where the
                # contour's corners moved 11-14 mm, it sat 1.4 edge lengths off its edge (the
                # coarse 10-node demo at 90 deg)
                in_near = np.zeros(self.model.n_nodes, dtype=bool)
                in_near[near] = True
                mid = block.conn[:, list(TET10_MIDSIDE)]
                ends = block.conn[:, [list(e) for e in TET10_MIDSIDE.values()]]
                extra = mid[in_near[ends].any(axis=2)]
                near = np.union1d(near, np.intersect1d(extra, self.groups.soft))
            self._near_soft = near
        return self._near_soft

    def _bone_contact(self, reach: float, cancel: Callable[[], bool] | None = None) -> BoneContact:
        model, setup, g = self.model, self.setup, self.groups
        soft_parts = np.array(setup.parts_of(*SOFT_ROLES), dtype=np.int64)
        masks = {etype: np.isin(b.part_ids, soft_parts) for etype, b in model.blocks.items()}
        size = 0.5 * (self.axes.lateral_fit.radius + self.axes.medial_fit.radius)
        edges = mesh_edges(model.blocks, masks, cancel)
        raise_if_cancelled(cancel, "bone contact set-up cancelled")
        return BoneContact(
            model.coords,
            self._bone_surfaces(),
            g.soft,
            edges,
            reach=reach * size,
            clearance=self.options.contact_clearance * self.length_scale,
            ray_depth=None
            if self.options.push_ray_depth is None
            else tuple(k * size for k in self.options.push_ray_depth),
            cancel=cancel,
        )

    # ---------------------------------------------------------------------- posing
    def bone_pose(self, flexion_deg: float) -> BonePose:
        """Rigid bone transforms for ``flexion_deg`` (see :func:`solve_bone_pose`), the patella
        seated on the femur (``options.patella_tracking``)."""
        lo, hi = SUPPORTED_FLEXION_DEG
        if not np.isfinite(flexion_deg) or not lo <= flexion_deg <= hi:
            raise SetupError(
                f"target flexion {flexion_deg!r} deg is outside the supported "
                f"range {lo:g} to {hi:g} deg",
                key="flexion",
            )
        bone = solve_bone_pose(self.axes, self.setup, float(flexion_deg))
        if self._seating is not None:
            lift = self._patellar_lift(float(flexion_deg))
            if lift > 0:
                tr = bone.transforms
                patella = self._seating.lifted(tr["patella"], tr["femur"], lift)
                bone = replace(bone, transforms={**tr, "patella": patella}, patellar_lift=lift)
        return bone

    def _patellar_lift(self, flexion_deg: float) -> float:
        """The patellar seating's lift at ``flexion_deg``: worked out exactly every
        :data:`PATELLA_LIFT_STEP` from the initial flexion (once each, cached) and interpolated
        linearly in between. It varies smoothly with flexion, and a slider step then seldom
        pays for the distance queries (3-20 ms each)."""
        # the grid is anchored at the initial flexion, where the lift is exactly zero
        steps = (flexion_deg - self.initial_flexion) / PATELLA_LIFT_STEP
        low = int(np.floor(steps))
        t = steps - low
        lifts = []
        for k in (low, low + 1) if t > 0 else (low,):
            if k not in self._lifts:
                angle = self.initial_flexion + k * PATELLA_LIFT_STEP
                tr = solve_bone_pose(self.axes, self.setup, angle).transforms
                self._lifts[k] = self._seating.lift(tr["patella"], tr["femur"])
            lifts.append(self._lifts[k])
        return lifts[0] if t == 0 else (1.0 - t) * lifts[0] + t * lifts[1]

    def pose(self, flexion_deg: float) -> NDArray[np.float64]:
        """All node coordinates (N, 3) at ``flexion_deg`` (a new array); the cheap slider step
        (no relaxation)."""
        return self.pose_detailed(flexion_deg, remeasure=False, relax=False).coords

    def pose_detailed(
        self,
        flexion_deg: float,
        remeasure: bool = True,
        relax: bool | None = None,
        progress: ProgressCallback | None = None,
        cancel: Callable[[], bool] | None = None,
    ) -> PoseResult:
        """All node coordinates at ``flexion_deg``, with the bone pose, skin report and timings.

        With ``remeasure`` the achieved flexion is measured again from the posed coordinates (the
        anatomical axes through the landmarks, as for the initial model); otherwise it is the
        bone solver's own measure of the transforms, which is much cheaper. ``relax`` (default:
        ``options.relax``) runs the elastic relaxation of the degraded tissue; ``progress`` and
        ``cancel`` are passed to it.
        """
        timings: dict[str, float] = {}
        t0 = time.perf_counter()
        bone = self.bone_pose(flexion_deg)
        tr = bone.transforms
        coords0 = self.model.coords
        out = coords0.copy()
        for name in ("femur", "tibia", "patella"):
            idx = self.groups.segment[name]
            if len(idx):
                out[idx] = tr[name].apply(coords0[idx])
        t1 = time.perf_counter()
        timings["bones"] = t1 - t0
        skin_report = None
        method = self.options.method
        g = self.groups
        if method == "blend":
            twists = np.stack([log_rigid(tr[s]) if s != "fixed" else np.zeros(6) for s in SEGMENTS])
            soft = g.soft
            out[soft] = exp_twists_apply(self._weights @ twists, coords0[soft])
        t2 = time.perf_counter()
        timings["blend"] = t2 - t1
        if method == "paper":
            skin_xyz, skin_report = pose_skin(
                self.contours,
                coords0,
                self.axes.knee_center,
                self.axes.superior,
                self.axes.tibia_axis.direction,
                self.axes.fe_axis.direction,
                tr["femur"],
                tr["tibia"],
                self.options.weight_shape,
                self.options.max_scale,
                self.options.clearance_fraction,
                out[g.bone_surface],
            )
            t3 = time.perf_counter()
            timings["skin"] = t3 - t2
            emb = self._flesh_embedding
            out[g.skin] = skin_xyz
            out[emb.nodes] = emb.apply(out[emb.control])
            if self._band_embedding is not None:
                be = self._band_embedding
                out[be.nodes] = be.apply(out[be.control])
            timings["soft tissue"] = time.perf_counter() - t3
        if self._contact is not None:
            t4 = time.perf_counter()
            self._contact.resolve(out, tr)
            timings["contact"] = time.perf_counter() - t4
        out = self._midside.straighten(out)
        relax_report = None
        if self.options.relax if relax is None else relax:
            t5 = time.perf_counter()
            out, relax_report = self.relax(out, bone, progress, cancel)
            timings["relax"] = time.perf_counter() - t5
        achieved = measure_flexion(out, self.setup) if remeasure else bone.measured_flexion_deg
        timings["total"] = time.perf_counter() - t0
        return PoseResult(
            out, float(flexion_deg), float(achieved), bone, skin_report, timings, relax_report
        )

    def relax(
        self,
        coords: NDArray[np.float64],
        bone: BonePose,
        progress: ProgressCallback | None = None,
        cancel: Callable[[], bool] | None = None,
    ) -> tuple[NDArray[np.float64], RelaxReport | None]:
        """Relax the soft tissue of a pose: :meth:`improve` without the smoothing.

        Returns
        -------
        coords : (N, 3) ndarray
            Relaxed coordinates (bones and fixed nodes unchanged).
        report : RelaxReport or None
            None when ``options.improvement.relax`` is None.
        """
        coords, report = self.improve(coords, bone, smooth=False, progress=progress, cancel=cancel)
        return coords, report.relaxation

    def improve(
        self,
        coords: NDArray[np.float64],
        bone: BonePose,
        *,
        relax: bool = True,
        smooth: bool = True,
        progress: ProgressCallback | None = None,
        cancel: Callable[[], bool] | None = None,
        stage_done: StageCallback | None = None,
    ) -> tuple[NDArray[np.float64], ImprovementReport]:
        """Run the mesh-improvement chain (:func:`kneegui.meshopt.chain.improve_region`,
        ``options.improvement``) on the soft tissue of a pose, in the region
        :mod:`kneegui.reposition.relax` sets up: untangle, meet the quality aims, then (with
        ``smooth``) smooth the soft tissue but the skin, with :meth:`bone_depth_guard`.

        Parameters
        ----------
        coords : (N, 3) ndarray
            All node coordinates of a pose (e.g. :meth:`pose`); not modified.
        bone : BonePose
            The bones' pose (:meth:`bone_pose`), solved once per angle.
        relax, smooth : bool
            Run the untangling and quality stages, and the smoothing stage (each when
            ``options.improvement`` has it).
        progress, cancel : callable, optional
        stage_done : callable, optional
            ``stage_done(stage, coords)`` when a stage of the chain ends and another follows
            (:data:`kneegui.meshopt.chain.StageCallback`; the 10-node tets' mid-side nodes
            put back on their edges).

        Returns
        -------
        coords : (N, 3) ndarray
            Improved coordinates (bones and fixed nodes unchanged).
        report : ImprovementReport
        """
        options = self.options.improvement.scaled(self.length_scale)
        if not smooth:
            options = replace(options, smooth=None)
        if not relax:
            options = replace(options, relax=None)
        relaxation = None
        corrected = None
        report_progress = progress or (lambda fraction, message: None)

        def check(step: str) -> None:
            # each step below takes seconds on a whole-body model (the 1M demo: 8.7 s to build
            # the relaxation)
            raise_if_cancelled(cancel, f"export cancelled before {step}")
            report_progress(0.0, step)

        if options.relax is not None:
            if self.relaxation is None:  # built on first use
                check("preparing the relaxation")
                t = time.perf_counter()
                self.relaxation = self._elastic_relaxation(cancel)
                self.timings_s["relaxation"] = time.perf_counter() - t
            relaxation = self.relaxation
            # the relaxation was built with the method's choice of slide_skin
            options = replace(options, relax=relaxation.options)
            if self.options.volume_correction is not None:
                if self._volume_correction is None:
                    check("preparing the volume correction")
                    t = time.perf_counter()
                    self._volume_correction = self._build_volume_correction(relaxation, cancel)
                    self.timings_s["volume correction"] = time.perf_counter() - t
                check("restoring the tissue's volume")
                coords, corrected = self._volume_correction(coords, cancel)
            if self._contact is None and self.options.relax_contact_reach > 0:
                # push the tissue the mapping put into the bones back out first, spread
                # through the tissue behind it: the relaxation then starts from a pose outside
                # the bones
                if self._relax_contact is None:
                    check("preparing the bone contact")
                    t = time.perf_counter()
                    self._relax_contact = self._bone_contact(
                        self.options.relax_contact_reach, cancel
                    )
                    self.timings_s["relaxation contact"] = time.perf_counter() - t
                check("pushing tissue out of the bones")
                coords = np.array(coords, dtype=np.float64, copy=True)
                self._relax_contact.resolve(coords, bone.transforms, cancel)
            check("finding the region to relax")
        region = RelaxedRegion(relaxation, bone.transforms, self._smoothing_stage(bone))
        forward = stage_done
        if stage_done is not None and len(self._midside):

            def forward(stage: str, x: NDArray[np.float64]) -> None:
                stage_done(stage, self._midside.straighten(x))

        coords, report = improve_region(coords, region, options, progress, cancel, forward)
        if len(self._midside):
            coords = self._midside_on_edges(coords, bone)
            report = replace(report, relaxed=self._midside_on_edges(report.relaxed, bone))
        return coords, replace(report, volume_correction=corrected)

    def _build_volume_correction(
        self, relaxation: ElasticRelaxation, cancel: Callable[[], bool] | None = None
    ) -> VolumeCorrection:
        """The volume-restoring step over the soft solids with a relaxable node, moving those
        nodes (the others would only pin it: a whole-body model's far tissue is left out);
        ``cancel`` is asked between the set-up's steps."""
        soft = list(self.setup.parts_of(*SOFT_ROLES))
        free = relaxation.is_free
        rows = {
            etype: np.flatnonzero(np.isin(block.part_ids, soft) & free[block.conn].any(axis=1))
            for etype, block in self.model.blocks.items()
        }
        return VolumeCorrection(
            self.model.blocks,
            rows,
            relaxation.is_free,
            self.model.coords,
            self.options.volume_correction,
            cancel,
        )

    def _midside_on_edges(self, coords: NDArray[np.float64], bone: BonePose) -> NDArray[np.float64]:
        """``coords`` with the mid-side nodes of the 10-node tets on their edges as at rest and
        out of the bones beyond the in-bone check's tolerance
        (:class:`~kneegui.reposition.midside.MidsideNodes`)."""
        size = 0.5 * (self.axes.lateral_fit.radius + self.axes.medial_fit.radius)
        return self._midside.out_of_bones(
            self._midside.straighten(coords),
            self._bone_surfaces(),
            bone.transforms,
            TISSUE_IN_BONE_TOLERANCE * size,
        )

    def _smoothing_stage(self, bone: BonePose):
        """The chain's smoothing for a pose: the soft tissue but the skin moves, bones, fixed
        and unassigned parts stay (:func:`smoothing_parts`), no node goes deeper into a bone
        (:meth:`bone_depth_guard`), elements aim at their initial quality."""
        movable, fixed = smoothing_parts(self.setup)

        def smooth(coords, options, progress, cancel):
            raise_if_cancelled(cancel, "smoothing cancelled")
            quality = self.quality_of(coords, cancel)
            raise_if_cancelled(cancel, "smoothing cancelled")
            guard = self.bone_depth_guard(coords, bone)
            smoothed, report = smooth_posed_model(
                self.model.with_coords(coords),
                movable,
                fixed,
                self.initial_quality(),
                quality=quality,
                options=options,
                position_guard=guard,
                progress=progress,
                cancel=cancel,
            )
            return smoothed.coords, report

        return smooth

    def bone_depth_guard(self, coords: NDArray[np.float64], bone: BonePose) -> BoneDepthGuard:
        """A smoother position guard that keeps the tissue of a pose out of the bones.

        Parameters
        ----------
        coords : (N, 3) ndarray
            The pose about to be smoothed.
        bone : BonePose
            The bones' pose (:meth:`bone_pose`).
        """
        return BoneDepthGuard(self._bone_surfaces(), bone.transforms, coords)

    def tissue_in_bones(
        self, coords: NDArray[np.float64], bone: BonePose, tolerance: float | None = None
    ) -> dict[str, Any]:
        """How much soft tissue of a pose lies inside the bones.

        Every soft-tissue node within ``relax_reach`` condyle radii of the F-E axis (farther
        away tissue moves with its bone) is measured against each moving segment's posed
        surface.

        Parameters
        ----------
        coords : (N, 3) ndarray
            The pose.
        bone : BonePose
            The bones' pose (:meth:`bone_pose`).
        tolerance : float, optional
            Depth (model units) beyond which a node counts as inside; default
            :data:`TISSUE_IN_BONE_TOLERANCE` condyle radii.

        Returns
        -------
        dict
            ``tolerance``, ``nodes`` (deeper than it, any bone), ``deepest`` (model units) and
            per segment ``{"nodes", "deepest"}``.
        """
        size = 0.5 * (self.axes.lateral_fit.radius + self.axes.medial_fit.radius)
        if tolerance is None:
            tolerance = TISSUE_IN_BONE_TOLERANCE * size
        surfaces = self._bone_surfaces()
        segments = [name for name in surfaces if name in bone.transforms]
        nodes = self._soft_near_joint()
        # (nodes, segments), + inside; a node outside a bone's bounding box is outside the
        # bone and is not measured (most of the tissue around a whole-body model's knee)
        depth = np.full((len(nodes), len(segments)), -np.inf)
        for j, name in enumerate(segments):
            rest = bone.transforms[name].inverse().apply(coords[nodes])
            boxed = surfaces[name].in_box(rest)
            depth[boxed, j] = -surfaces[name].query(rest[boxed])[0]
        per_bone = {
            name: {
                "nodes": int(np.sum(depth[:, j] > tolerance)),
                "deepest": float(depth[:, j].max(initial=0.0)) + 0.0,  # + 0.0: no -0.0
            }
            for j, name in enumerate(segments)
        }
        return {
            "tolerance": float(tolerance),
            "nodes": int(np.sum((depth > tolerance).any(axis=1))),
            "deepest": max((b["deepest"] for b in per_bone.values()), default=0.0),
            "bones": per_bone,
        }

    def bone_overlap(self, bone: BonePose) -> list[BoneOverlap]:
        """How deep each rigid segment's surface lies inside another's in a pose (deepest
        first; :mod:`kneegui.reposition.bone_overlap`). The check is built on first use.

        Parameters
        ----------
        bone : BonePose
            The bones' pose (:meth:`bone_pose`).
        """
        if self._overlap_check is None:
            self._overlap_check = BoneOverlapCheck(self._bone_surfaces())
        return self._overlap_check.measure(bone.transforms)

    def with_options(self, **changes: Any) -> Repositioner:
        """A new repositioner with some options changed.

        It recomputes the precompute, unless every changed option is one only the export reads
        (:data:`EXPORT_ONLY_OPTIONS`): then it shares this one's precompute and what its exports
        have built (weights, bone surfaces, the relaxation), so switching the volume step on or
        off in the window costs nothing (a 1M-element model's precompute and relaxation set-up
        take about 20 s). Either way it poses exactly as a repositioner built with those
        options (the same bits); this one is not changed.
        """
        options = replace(self.options, **changes)
        if not set(changes) <= EXPORT_ONLY_OPTIONS:
            return Repositioner(self.model, self.setup, options)
        twin = copy.copy(self)
        twin.options = options
        # what the twin fills in from now on is its own
        twin.timings_s = dict(self.timings_s)
        twin._lifts = dict(self._lifts)
        twin._volume_correction = None  # built for the twin's own options on first use
        return twin
