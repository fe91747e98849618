"""The joint setup file (``kneegui-setup`` JSON, version 1): load, validate against a model, save.

A setup says which parts are which bones and tissues, where the landmarks are, which side the knee
is on, which segment moves and which kinematic tables drive the bones. See docs/setup-format.md
and ``resources/setup.schema.json``. :func:`load_setup` checks everything against the model it is
used with and raises :class:`~kneegui.errors.SetupError` naming the offending key and value.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np
from numpy.typing import NDArray

from kneegui.errors import SetupError
from kneegui.geometry.transforms import best_fit_transform
from kneegui.model import Model
from kneegui.setup.kinematic_tables import QUANTITIES, KinematicTable, resolve_table

FORMAT_NAME = "kneegui-setup"
FORMAT_VERSION = 1

#: Bones: moved rigidly.
RIGID_ROLES: tuple[str, ...] = ("femur", "tibia", "fibula", "patella")
#: Soft tissues: repositioned by the skin / soft-tissue steps.
DEFORMABLE_ROLES: tuple[str, ...] = ("skin", "flesh", "ligament", "meniscus", "tendon", "capsule")
#: Every role, in the order of the file.
ROLES: tuple[str, ...] = (*RIGID_ROLES, *DEFORMABLE_ROLES, "fixed")
#: The rigid groups the kinematics moves, and the roles in each.
SEGMENT_ROLES: Mapping[str, tuple[str, ...]] = MappingProxyType(
    {"femur": ("femur",), "tibia": ("tibia", "fibula"), "patella": ("patella",)}
)
SIDES = ("right", "left")
MOVING_SEGMENTS = ("tibia", "femur")
CONDYLE_KEYS = ("lateral_condyle", "medial_condyle")
AXIS_KEYS = ("lr_axis", "femur_axis", "tibia_axis")
#: Which rigid group carries each axis landmark (coordinates given as [x, y, z] move with it).
AXIS_SEGMENT: Mapping[str, str] = MappingProxyType(
    {"lr_axis": "tibia", "femur_axis": "femur", "tibia_axis": "tibia"}
)
MIN_CONDYLE_NODES = 5
DEFAULT_SKIN_CONTOURS = 86
REQUIRED_KEYS = ("format", "version", "side", "roles", "landmarks")
OPTIONAL_KEYS = ("moving_segment", "kinematics", "skin_contours", "description", "model", "units")
#: Number of bone nodes a coordinate landmark is attached to (for tracking it after posing).
N_ANCHORS = 12


@dataclass(frozen=True, eq=False)
class LandmarkPoint:
    """One axis point: a node of the model or a fixed coordinate attached to a bone.

    Attributes
    ----------
    node_id : int or None
        Node id when the landmark is a node.
    node_index : int or None
        Index of that node in ``Model.coords``.
    coords : (3,) ndarray of float
        Position in the model the setup was validated on.
    segment : str
        Rigid group it moves with (``femur`` or ``tibia``).
    anchor_indices : (K,) ndarray of int
        For a coordinate landmark, the nearest nodes of its segment; it follows their best-fit
        rigid motion. Empty for a node landmark.
    anchor_coords : (K, 3) ndarray of float
        Positions of the anchors in the initial model.
    """

    node_id: int | None
    node_index: int | None
    coords: NDArray[np.float64]
    segment: str
    anchor_indices: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    anchor_coords: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 3)))

    def position(self, coords: NDArray[np.float64]) -> NDArray[np.float64]:
        """Where the landmark is in the (possibly posed) node coordinates ``coords`` (N, 3)."""
        if self.node_index is not None:
            return np.array(coords[self.node_index], dtype=np.float64)
        current = coords[self.anchor_indices]
        if np.array_equal(current, self.anchor_coords):
            return self.coords.copy()
        return best_fit_transform(self.anchor_coords, current).apply(self.coords)

    def to_json(self) -> int | list[float]:
        """The file form: the node id, or ``[x, y, z]``."""
        if self.node_id is not None:
            return int(self.node_id)
        return [float(v) for v in self.coords]


@dataclass(frozen=True, eq=False)
class JointSetup:
    """A validated setup, bound to the model it was checked against. Immutable.

    Attributes
    ----------
    side : str
        ``"right"`` or ``"left"``.
    moving_segment : str
        ``"tibia"`` (the leg moves, default) or ``"femur"`` (the thigh moves).
    roles : Mapping[str, tuple of int]
        Role -> part ids, for every role in :data:`ROLES` (empty tuples allowed).
    lateral_condyle_ids, medial_condyle_ids : tuple of int
        Node ids of the posterior condyle sets.
    lateral_condyle, medial_condyle : (M,) ndarray of int
        Their node indices.
    lr_axis, femur_axis, tibia_axis : tuple of two LandmarkPoint
        ``(proximal, distal)``.
    kinematics : Mapping[str, str]
        Quantity -> table choice as written (``"default"``, a shipped name or a path).
    tables : Mapping[str, KinematicTable]
        Quantity -> the loaded table.
    skin_contours : int
        Number of skin cross-sections.
    unassigned_parts : tuple of int
        Parts in no role (they stay fixed).
    warnings : tuple of str
        Non-fatal findings (unassigned parts, condyle nodes off the femur, ...).
    extras : Mapping[str, Any]
        Optional informative keys kept as read (``description``, ``model``, ``units``).
    path : Path or None
        The file it was read from.
    n_nodes : int
        Node count of the model it was validated against.
    segment_nodes : Mapping[str, ndarray of int]
        Node indices of each rigid group (``femur``, ``tibia`` = tibia + fibula, ``patella``):
        every node of an element of those parts.
    """

    side: str
    moving_segment: str
    roles: Mapping[str, tuple[int, ...]]
    lateral_condyle_ids: tuple[int, ...]
    medial_condyle_ids: tuple[int, ...]
    lateral_condyle: NDArray[np.int64]
    medial_condyle: NDArray[np.int64]
    lr_axis: tuple[LandmarkPoint, LandmarkPoint]
    femur_axis: tuple[LandmarkPoint, LandmarkPoint]
    tibia_axis: tuple[LandmarkPoint, LandmarkPoint]
    kinematics: Mapping[str, str]
    tables: Mapping[str, KinematicTable]
    skin_contours: int
    unassigned_parts: tuple[int, ...]
    warnings: tuple[str, ...]
    extras: Mapping[str, Any]
    path: Path | None
    n_nodes: int
    segment_nodes: Mapping[str, NDArray[np.int64]]

    @property
    def side_sign(self) -> int:
        """``+1`` for a right knee, ``-1`` for a left one (mirrors every rotation sign)."""
        return 1 if self.side == "right" else -1

    def segment_parts(self, segment: str) -> tuple[int, ...]:
        """Part ids of a rigid group: ``femur``, ``tibia`` (tibia + fibula) or ``patella``."""
        return tuple(p for role in SEGMENT_ROLES[segment] for p in self.roles[role])

    def parts_of(self, *roles: str) -> tuple[int, ...]:
        """Part ids of the given roles, concatenated."""
        return tuple(p for r in roles for p in self.roles[r])

    def axis(self, key: str) -> tuple[LandmarkPoint, LandmarkPoint]:
        """One of :data:`AXIS_KEYS` as ``(proximal, distal)``."""
        if key not in AXIS_KEYS:
            raise KeyError(key)
        return getattr(self, key)

    def to_dict(self) -> dict[str, Any]:
        """The setup in its file form (version 1), ready for ``json.dump``."""
        out: dict[str, Any] = {"format": FORMAT_NAME, "version": FORMAT_VERSION}
        for key in ("description", "model", "units"):
            if key in self.extras:
                out[key] = self.extras[key]
        out["side"] = self.side
        out["moving_segment"] = self.moving_segment
        out["roles"] = {r: [int(p) for p in self.roles[r]] for r in ROLES}
        out["landmarks"] = {
            "lateral_condyle": [int(n) for n in self.lateral_condyle_ids],
            "medial_condyle": [int(n) for n in self.medial_condyle_ids],
            **{k: [p.to_json() for p in self.axis(k)] for k in AXIS_KEYS},
        }
        out["kinematics"] = {
            q: (
                self.kinematics[q]
                if self.kinematics[q] == self.tables[q].name or self.kinematics[q] == "default"
                else str(self.tables[q].path)
            )
            for q in QUANTITIES
        }
        out["skin_contours"] = int(self.skin_contours)
        return out


# ---------------------------------------------------------------------------- helpers
def _is_int(value: Any) -> bool:
    return isinstance(value, int | np.integer) and not isinstance(value, bool | np.bool_)


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float | np.integer | np.floating) and not isinstance(
        value, bool | np.bool_
    )


def _short(value: Any, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


class _Checker:
    """Validation state: the model, the file path, collected warnings."""

    def __init__(self, model: Model, path: Path | None):
        self.model = model
        self.path = path
        self.warnings: list[str] = []
        self.part_ids = set(model.part_ids().tolist())
        bbox = model.bounding_box()
        self.scale = float(np.linalg.norm(bbox[1] - bbox[0])) or 1.0

    def error(self, message: str, key: str) -> SetupError:
        return SetupError(message, key=key, path=self.path)

    def node_ids(self, value: Any, key: str) -> tuple[tuple[int, ...], NDArray[np.int64]]:
        if not isinstance(value, list | tuple):
            raise self.error(f"expected a list of node ids, got {_short(value)}", key)
        for v in value:
            if not _is_int(v):
                raise self.error(f"node id must be an integer, got {_short(v)}", key)
        ids = tuple(int(v) for v in value)
        seen: set[int] = set()
        for nid in ids:
            if nid in seen:
                raise self.error(f"node id {nid} is listed twice", key)
            seen.add(nid)
        if ids:
            known = self.model.has_nodes(np.array(ids, dtype=np.int64))
            if not known.all():
                bad = ids[int(np.flatnonzero(~known)[0])]
                raise self.error(f"node id {bad} is not in the model", key)
        idx = self.model.node_index(np.array(ids, dtype=np.int64)) if ids else np.zeros(0, np.int64)
        return ids, idx

    def point(self, value: Any, key: str) -> tuple[int | None, int | None, NDArray[np.float64]]:
        if _is_int(value):
            nid = int(value)
            if not self.model.has_nodes(np.array([nid]))[0]:
                raise self.error(f"node id {nid} is not in the model", key)
            index = int(self.model.node_index(np.array([nid]))[0])
            return nid, index, np.array(self.model.coords[index])
        if (
            isinstance(value, list | tuple)
            and len(value) == 3
            and all(_is_number(v) for v in value)
        ):
            xyz = np.array([float(v) for v in value])
            if not np.all(np.isfinite(xyz)):
                raise self.error(f"coordinate is not finite: {_short(value)}", key)
            return None, None, xyz
        raise self.error(f"expected a node id or an [x, y, z] coordinate, got {_short(value)}", key)


def _read_json(path: Path) -> dict[str, Any]:
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise SetupError(f"cannot read setup: {exc.strerror or exc}", path=path) from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise SetupError(
            f"not valid JSON (line {exc.lineno}, column {exc.colno}): {exc.msg}", path=path
        ) from None
    return data


def _anchors(
    model: Model, segment_nodes: NDArray[np.int64], xyz: NDArray[np.float64]
) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """The bone nodes nearest to ``xyz`` (at least 3 non-collinear ones)."""
    pts = model.coords[segment_nodes]
    d = np.linalg.norm(pts - xyz, axis=1)
    k = min(N_ANCHORS, len(segment_nodes))
    nearest = np.argsort(d, kind="stable")[:k]
    sel = segment_nodes[nearest]
    spread = np.linalg.svd(model.coords[sel] - model.coords[sel].mean(axis=0), compute_uv=False)
    if len(sel) < 3 or spread[1] <= 1e-9 * max(spread[0], 1e-300):
        # nearest nodes degenerate: spread the anchors over the whole segment instead
        step = max(1, len(segment_nodes) // N_ANCHORS)
        sel = segment_nodes[::step][:N_ANCHORS]
    anchor_coords = np.array(model.coords[sel])
    anchor_coords.flags.writeable = False
    return np.array(sel, dtype=np.int64), anchor_coords


def load_setup(source: str | Path | Mapping[str, Any], model: Model) -> JointSetup:
    """Read and validate a setup against a model.

    Parameters
    ----------
    source : str, Path or mapping
        A ``*.json`` file or the already-parsed dictionary.
    model : Model
        The model the setup refers to (part ids, node ids, coordinates).

    Returns
    -------
    JointSetup
        Immutable, with landmarks resolved to node indices and coordinates.

    Raises
    ------
    SetupError
        Anything wrong: unreadable file, bad JSON, unknown key, wrong type, unknown format or
        version, unknown role, unknown or repeated part id, node id not in the model, fewer than
        5 condyle nodes, coincident axis points, unknown kinematic table... The message names the
        key (``SetupError.key``) and the bad value.
    """
    path: Path | None = None
    if isinstance(source, str | Path):
        path = Path(source)
        data = _read_json(path)
    elif isinstance(source, Mapping):
        data = dict(source)
    else:
        raise SetupError(f"expected a file path or a mapping, got {type(source).__name__}")
    chk = _Checker(model, path)
    if not isinstance(data, dict):
        raise chk.error(f"the setup must be a JSON object, got {type(data).__name__}", "")

    for key in data:
        if key not in REQUIRED_KEYS and key not in OPTIONAL_KEYS:
            raise chk.error(f"unknown key {key!r}", str(key))
    for key in REQUIRED_KEYS:
        if key not in data:
            raise chk.error("missing", key)
    if data["format"] != FORMAT_NAME:
        raise chk.error(f"expected {FORMAT_NAME!r}, got {_short(data['format'])}", "format")
    if not _is_int(data["version"]) or data["version"] != FORMAT_VERSION:
        raise chk.error(
            f"unsupported version {_short(data['version'])} (this kneegui reads {FORMAT_VERSION})",
            "version",
        )
    side = data["side"]
    if side not in SIDES:
        raise chk.error(f"expected 'right' or 'left', got {_short(side)}", "side")
    moving = data.get("moving_segment", "tibia")
    if moving not in MOVING_SEGMENTS:
        raise chk.error(f"expected 'tibia' or 'femur', got {_short(moving)}", "moving_segment")
    extras: dict[str, Any] = {}
    for key in ("description", "model", "units"):
        if key in data:
            if not isinstance(data[key], str):
                raise chk.error(f"expected a string, got {_short(data[key])}", key)
            extras[key] = data[key]
    if "units" in extras and extras["units"] != "mm":
        chk.warnings.append(
            f"units {extras['units']!r}: radius and RMS warnings assume millimetres"
        )

    roles = _check_roles(chk, data["roles"])
    segment_nodes = {}
    for segment, seg_roles in SEGMENT_ROLES.items():
        pids = [p for r in seg_roles for p in roles[r]]
        segment_nodes[segment] = model.part_node_indices(pids)
    for segment in ("femur", "tibia"):
        if len(segment_nodes[segment]) == 0:
            key = f"roles.{segment}"
            raise chk.error(f"the parts {list(roles[segment])} have no elements", key)
    _warn_shared_bone_nodes(chk, segment_nodes)
    if roles["fixed"]:
        fixed_nodes = model.part_node_indices(roles["fixed"])
        moving_nodes = np.union1d(segment_nodes[moving], segment_nodes["patella"])
        shared = np.intersect1d(fixed_nodes, moving_nodes)
        if len(shared):
            chk.warnings.append(
                f"{len(shared)} node(s) of 'fixed' parts belong to the moving {moving} or the "
                "patella: they will move and stretch the fixed elements"
            )

    landmarks = data["landmarks"]
    if not isinstance(landmarks, dict):
        raise chk.error(f"expected an object, got {_short(landmarks)}", "landmarks")
    for key in landmarks:
        if key not in CONDYLE_KEYS and key not in AXIS_KEYS:
            raise chk.error(f"unknown landmark {key!r}", f"landmarks.{key}")
    for key in (*CONDYLE_KEYS, *AXIS_KEYS):
        if key not in landmarks:
            raise chk.error("missing", f"landmarks.{key}")
    condyles = {}
    for key in CONDYLE_KEYS:
        ids, idx = chk.node_ids(landmarks[key], f"landmarks.{key}")
        if len(ids) < MIN_CONDYLE_NODES:
            raise chk.error(
                f"needs at least {MIN_CONDYLE_NODES} node ids, got {len(ids)}", f"landmarks.{key}"
            )
        off = np.setdiff1d(idx, segment_nodes["femur"])
        if len(off):
            chk.warnings.append(
                f"landmarks.{key}: {len(off)} of {len(ids)} nodes are not on the femur parts"
            )
        condyles[key] = (ids, idx)
    common = set(condyles["lateral_condyle"][0]) & set(condyles["medial_condyle"][0])
    if common:
        raise chk.error(
            f"node id {min(common)} is in both condyle sets", "landmarks.medial_condyle"
        )
    axes = {}
    for key in AXIS_KEYS:
        value = landmarks[key]
        lkey = f"landmarks.{key}"
        if not isinstance(value, list | tuple) or len(value) != 2:
            raise chk.error(f"expected [proximal, distal], got {_short(value)}", lkey)
        points = []
        segment = AXIS_SEGMENT[key]
        for i, v in enumerate(value):
            nid, index, xyz = chk.point(v, f"{lkey}[{i}]")
            if nid is None:
                anchor_idx, anchor_xyz = _anchors(model, segment_nodes[segment], xyz)
                points.append(
                    LandmarkPoint(None, None, _frozen(xyz), segment, anchor_idx, anchor_xyz)
                )
            else:
                points.append(LandmarkPoint(nid, index, _frozen(xyz), segment))
        if np.linalg.norm(points[0].coords - points[1].coords) <= 1e-9 * chk.scale:
            raise chk.error(
                f"the two points coincide ({_short(value[0])} and {_short(value[1])})", lkey
            )
        axes[key] = (points[0], points[1])

    kin_choices, tables = _check_kinematics(chk, data.get("kinematics", {}))
    contours = data.get("skin_contours", DEFAULT_SKIN_CONTOURS)
    if not _is_int(contours) or contours < 2:
        raise chk.error(f"expected an integer >= 2, got {_short(contours)}", "skin_contours")

    assigned = {p for pids in roles.values() for p in pids}
    unassigned = tuple(sorted(chk.part_ids - assigned))
    if unassigned:
        shown = ", ".join(str(p) for p in unassigned[:10])
        more = f" (+{len(unassigned) - 10} more)" if len(unassigned) > 10 else ""
        chk.warnings.insert(0, f"{len(unassigned)} part(s) in no role stay fixed: {shown}{more}")
    lat_ids, lat_idx = condyles["lateral_condyle"]
    med_ids, med_idx = condyles["medial_condyle"]
    return JointSetup(
        side=side,
        moving_segment=moving,
        roles=MappingProxyType(roles),
        lateral_condyle_ids=lat_ids,
        medial_condyle_ids=med_ids,
        lateral_condyle=_frozen(lat_idx),
        medial_condyle=_frozen(med_idx),
        lr_axis=axes["lr_axis"],
        femur_axis=axes["femur_axis"],
        tibia_axis=axes["tibia_axis"],
        kinematics=MappingProxyType(kin_choices),
        tables=MappingProxyType(tables),
        skin_contours=int(contours),
        unassigned_parts=unassigned,
        warnings=tuple(chk.warnings),
        extras=MappingProxyType(extras),
        path=path,
        n_nodes=model.n_nodes,
        segment_nodes=MappingProxyType({k: _frozen(v) for k, v in segment_nodes.items()}),
    )


def _frozen(arr: NDArray[Any]) -> NDArray[Any]:
    out = np.array(arr)
    out.flags.writeable = False
    return out


def _check_roles(chk: _Checker, value: Any) -> dict[str, tuple[int, ...]]:
    if not isinstance(value, dict):
        raise chk.error(f"expected an object of role -> part ids, got {_short(value)}", "roles")
    owner: dict[int, str] = {}
    roles: dict[str, tuple[int, ...]] = {}
    for role, pids in value.items():
        key = f"roles.{role}"
        if role not in ROLES:
            raise chk.error(f"unknown role {role!r} (roles: {', '.join(ROLES)})", key)
        if not isinstance(pids, list | tuple):
            raise chk.error(f"expected a list of part ids, got {_short(pids)}", key)
        for pid in pids:
            if not _is_int(pid):
                raise chk.error(f"part id must be an integer, got {_short(pid)}", key)
            pid = int(pid)
            if pid not in chk.part_ids:
                raise chk.error(f"unknown part id {pid}", key)
            if pid in owner:
                where = "twice" if owner[pid] == role else f"also in role {owner[pid]!r}"
                raise chk.error(f"part id {pid} is listed {where}", key)
            owner[pid] = role
        roles[role] = tuple(int(p) for p in pids)
    for role in ROLES:
        roles.setdefault(role, ())
    for role in ("femur", "tibia"):
        if not roles[role]:
            raise chk.error("at least one part is required", f"roles.{role}")
    return {r: roles[r] for r in ROLES}


def _warn_shared_bone_nodes(chk: _Checker, segment_nodes: Mapping[str, NDArray[np.int64]]):
    names = list(segment_nodes)
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            shared = np.intersect1d(segment_nodes[a], segment_nodes[b])
            if len(shared):
                chk.warnings.append(
                    f"{len(shared)} node(s) are shared by the {a} and {b} groups; they cannot "
                    "follow both rigid motions"
                )


def _check_kinematics(
    chk: _Checker, value: Any
) -> tuple[dict[str, str], dict[str, KinematicTable]]:
    if not isinstance(value, dict):
        raise chk.error(f"expected an object, got {_short(value)}", "kinematics")
    for key in value:
        if key not in QUANTITIES:
            raise chk.error(f"unknown key {key!r}", f"kinematics.{key}")
    choices, tables = {}, {}
    base = chk.path.parent if chk.path is not None else None
    for q in QUANTITIES:
        choice = value.get(q, "default")
        if not isinstance(choice, str):
            raise chk.error(
                f"expected a table name or a CSV path, got {_short(choice)}", f"kinematics.{q}"
            )
        try:
            tables[q] = resolve_table(q, choice, base)
        except SetupError as exc:
            raise SetupError(exc.message, key=exc.key, path=chk.path) from None
        choices[q] = choice
    return choices, tables


# ---------------------------------------------------------------------------- saving
def _format_json(obj: Any, indent: int = 0, width: int = 100) -> str:
    """JSON with objects indented and lists of scalars kept inline (wrapped at ``width``)."""
    pad = "  " * indent
    if isinstance(obj, dict):
        if not obj:
            return "{}"
        items = [
            f"{pad}  {json.dumps(k)}: {_format_json(v, indent + 1, width)}" for k, v in obj.items()
        ]
        return "{\n" + ",\n".join(items) + "\n" + pad + "}"
    if isinstance(obj, list | tuple):
        if all(not isinstance(v, dict | list | tuple) for v in obj):
            parts = [json.dumps(v) for v in obj]
            one_line = "[" + ", ".join(parts) + "]"
            if len(one_line) + len(pad) <= width:
                return one_line
            lines, line = [], ""
            for p in parts:
                if line and len(pad) + 2 + len(line) + len(p) + 2 > width:
                    lines.append(line.rstrip())
                    line = ""
                line += p + ", "
            lines.append(line.rstrip(", "))
            return "[\n" + ",\n".join(f"{pad}  {ln.rstrip(',')}" for ln in lines) + "\n" + pad + "]"
        inner = [f"{pad}  {_format_json(v, indent + 1, width)}" for v in obj]
        one_line = "[" + ", ".join(_format_json(v, 0, 10**9) for v in obj) + "]"
        if len(one_line) + len(pad) <= width:
            return one_line
        return "[\n" + ",\n".join(inner) + "\n" + pad + "]"
    if isinstance(obj, float) and not math.isfinite(obj):
        raise ValueError("non-finite number in setup")
    return json.dumps(obj)


def setup_to_json(setup: JointSetup | Mapping[str, Any]) -> str:
    """The JSON text of a setup (a :class:`JointSetup` or its dict form)."""
    data = setup.to_dict() if isinstance(setup, JointSetup) else dict(setup)
    return _format_json(data) + "\n"


def save_setup(setup: JointSetup | Mapping[str, Any], path: str | Path) -> Path:
    """Write a setup atomically (temporary file in the same folder, fsync, ``os.replace``).

    Parameters
    ----------
    setup : JointSetup or mapping
        The setup (a dict is written as given).
    path : str or Path
        Destination ``*.json``.

    Returns
    -------
    Path
        The written path.
    """
    path = Path(path)
    text = setup_to_json(setup)
    folder = path.parent if str(path.parent) else Path(".")
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=folder)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    return path
