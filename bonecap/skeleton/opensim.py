"""OpenSim ``.osim`` models -> :class:`~bonecap.model.Skeleton` at the default pose.

The model file is read with :mod:`xml.etree` (the ``opensim`` package is not a
dependency); the bone surfaces come from the model's ``Geometry`` folder
through :func:`bonecap.io.mesh.read_mesh`.

Public API
----------
- :func:`read_osim` ``(path, geometry_dir=None, *, load_meshes=True,
  coordinates=None) -> Skeleton``
- :func:`read_osim_markers` ``(path) -> list[OsimMarker]`` (the same list is in
  ``skeleton.metadata["markers"]``)
- :func:`markers_in_world` ``(skeleton, markers=None) -> dict[str, ndarray]``
- :class:`OsimMarker`, :class:`UnsupportedModelError` (an :class:`InputError`),
  :class:`SimmSpline`

How a model maps onto a ``Skeleton``
------------------------------------
- **Bones.** One :class:`~bonecap.model.Bone` per OpenSim ``Body``, named as
  the body (mapping to bonecap's generic bone names is done elsewhere). The
  ground is not a bone: a body jointed to the ground has ``parent=None``.
  ``Skeleton.bones`` is in parent-before-child order (BodySet order otherwise).
- **Frames.** A bone's frame *is* the OpenSim body frame, in millimetres.
  ``Skeleton.world`` is ``"opensim_ground"``: the model's ground frame (Y up,
  X forward, Z to the right in the usual gait models). ``bone_to_world`` is
  body -> ground with every coordinate at its ``default_value``.
- **Joints.** OpenSim places a child body in its parent as::

      child_in_parent = P . J(q) . inverse(C)

  with ``P`` the parent offset frame in the parent body, ``C`` the child offset
  frame in the child body (OpenSim 4 ``socket_parent_frame`` /
  ``socket_child_frame`` PhysicalOffsetFrames with ``translation`` and
  ``orientation``; OpenSim 3 ``location_in_parent`` / ``orientation_in_parent``
  and ``location`` / ``orientation``). Orientations are body-fixed X-Y-Z Euler
  angles in radians: ``R = Rx(a) Ry(b) Rz(c)``. ``J(q)`` is the mobilizer
  transform, child-offset -> parent-offset:

  ============== ==========================================================
  WeldJoint      identity
  PinJoint       ``Rz(q0)``
  SliderJoint    translation ``q0`` along X
  UniversalJoint ``Rx(q0) Ry(q1)``
  Ball/Gimbal    ``Rx(q0) Ry(q1) Rz(q2)`` (body-fixed X-Y-Z)
  FreeJoint      ``Rx(q0) Ry(q1) Rz(q2)``, translation ``(q3, q4, q5)``
  PlanarJoint    ``Rz(q0)``, translation ``(q1, q2, 0)``
  CustomJoint    ``R = R(a1, f1) R(a2, f2) R(a3, f3)`` and
                 ``t = g1 b1 + g2 b2 + g3 b3``
  ============== ==========================================================

  For the CustomJoint's SpatialTransform ``f_i``/``g_i`` are the functions of
  the TransformAxes ``rotation1..3``/``translation1..3`` evaluated at their
  coordinates, ``a_i``/``b_i`` their (normalised) axes. The rotations compose
  as Simbody's ``MobilizedBody::FunctionBased`` does, ``R1 * R2 * R3``: each
  rotation is about its axis *after* the previous ones (body-fixed), which is
  the same as rotating about parent-fixed axes in the order 3, 2, 1. The
  translation is expressed in the parent offset frame (it is not rotated).
  Functions: ``Constant``, ``LinearFunction`` (``slope intercept``),
  ``SimmSpline`` (OpenSim's spline, *not* a natural spline: the end
  conditions match the third derivative of the cubic through the four end
  points, as in Forsythe-Malcolm-Moler; linear extrapolation with the end
  slopes), ``NaturalCubicSpline``, ``PiecewiseLinearFunction``,
  ``MultiplierFunction`` (``scale * function``), ``PolynomialFunction``
  (coefficients from the highest power down) and ``Sine``.
- **Coordinates** take their ``default_value`` (radians for rotations, model
  length units for translations), unless overridden by the ``coordinates``
  argument. An enforced ``CoordinateCouplerConstraint`` then sets its
  dependent coordinate to ``scale_factor * f(independent coordinates)`` (as
  OpenSim's assembler does: dependent coordinates are not assembly goals);
  this overrides the dependent coordinate's own default value. Prescribed
  coordinates, locking and clamping are ignored.
- **Meshes.** All ``Mesh`` geometry attached to a body, directly or through
  PhysicalOffsetFrames (anywhere in the model) whose chain ends on that body,
  is merged into one :class:`~bonecap.model.Mesh` in the body frame (mm),
  applying each mesh's ``scale_factors`` (in the frame it is attached to; a
  mirroring scale also reverses the face winding) and its frame's offset.
  OpenSim 3 ``VisibleObject`` geometry (``geometry_files`` or
  ``DisplayGeometry`` with ``transform`` = 3 body-fixed XYZ angles then a
  translation) is read too; a VisibleObject's own transform and scale are
  composed outside the DisplayGeometry's. Analytic geometry (spheres,
  cylinders...) and ground geometry are not kept. Mesh files are looked for in
  ``geometry_dir`` when given, else in ``<model dir>/Geometry``, then
  ``<model dir>/../Geometry``, then the model's own folder. Missing or
  unreadable files give **one** warning per model and are listed in
  ``skeleton.metadata["missing_meshes"]`` / ``["unreadable_meshes"]``; a body
  none of whose files was found has ``mesh=None``.
- **Joint centres.** Each bone gets, under the joint's name, the origin of the
  joint's child offset frame in its own frame; its parent bone gets the same
  point (at the default pose) in the parent's frame. A ``PinJoint`` (its Z
  axis) and a ``CustomJoint`` with exactly one coordinate-driven rotation also
  give ``joint_axes`` under the joint's name, in both bones' frames.
- **Markers** (:class:`OsimMarker`): name, body, location in the body frame
  (mm), ``fixed`` and ``virtual``. A marker is *virtual* (not a physical skin
  marker) when its name says it is a joint centre or a computed point --
  case-insensitive, it ends in ``JC`` (``RKJC``, ``LHJC``, ``r_hip_jc``),
  contains ``joint_center``/``jointcentre``/``_centre``/``_center``, or
  contains ``tibial_plateau`` -- or when it lies within 1 mm of one of its
  body's joint centres.

Metadata
--------
``skeleton.metadata``: ``source``, ``format`` (``"opensim"``), ``model_name``,
``opensim_version`` (the document's ``Version``), ``layout`` (``"opensim4"``
or ``"opensim3"``), ``length_units``, ``coordinates`` (name -> value used),
``coupled_coordinates`` (dependent -> constraint name), ``joints`` (name ->
``{"type", "parent", "child", "coordinates"}``, parent ``"ground"`` for the
ground), ``ignored_joints`` (a second joint into the same body, i.e. a closed
loop, is ignored with a warning), ``markers``, ``geometry_dirs``, ``missing_meshes``,
``unreadable_meshes``. ``bone.metadata``: ``opensim_body``, ``joint``,
``joint_type``, ``mesh_files``, ``mass`` (kg, when given).
"""

from __future__ import annotations

import math
import os
import posixpath
import re
import warnings
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

import numpy as np

from bonecap.errors import FormatError, InputError
from bonecap.model import Bone, Mesh, Skeleton

__all__ = [
    "OsimMarker",
    "UnsupportedModelError",
    "read_osim",
    "read_osim_markers",
    "markers_in_world",
    "SimmSpline",
    "SUPPORTED_JOINTS",
    "SUPPORTED_FUNCTIONS",
]

#: Joint types :func:`read_osim` can pose.
SUPPORTED_JOINTS = ("CustomJoint", "PinJoint", "WeldJoint", "UniversalJoint", "BallJoint",
                    "GimbalJoint", "FreeJoint", "SliderJoint", "PlanarJoint")
#: Function types accepted in a SpatialTransform or a CoordinateCouplerConstraint.
SUPPORTED_FUNCTIONS = ("Constant", "LinearFunction", "SimmSpline", "NaturalCubicSpline",
                       "PiecewiseLinearFunction", "MultiplierFunction", "PolynomialFunction",
                       "Sine")

WORLD = "opensim_ground"
_GROUND = "/ground"
_UNIT_TO_MM = {"meters": 1000.0, "meter": 1000.0, "m": 1000.0, "millimeters": 1.0,
               "millimeter": 1.0, "mm": 1.0, "centimeters": 10.0, "centimeter": 10.0,
               "cm": 10.0}
_VIRTUAL_NAME = re.compile(r"(jc$|joint_?cent(er|re)|_cent(er|re)$|tibial_plateau)", re.IGNORECASE)
_VIRTUAL_DISTANCE_MM = 1.0


class UnsupportedModelError(InputError):
    """A valid OpenSim model uses something this reader cannot pose (a joint or
    function type, a reversed joint)."""


@dataclass
class OsimMarker:
    """A marker of an OpenSim MarkerSet.

    Attributes
    ----------
    name : str
    body : str
        OpenSim body name the marker is fixed to (``"ground"`` for the ground).
    location : ndarray, shape (3,)
        Position in the body frame, **mm** (a marker on an offset frame is
        brought into its body's frame).
    fixed : bool
        OpenSim's ``fixed`` flag (not moved by marker placement when scaling).
    virtual : bool
        True for markers that are not physical skin markers (joint centres and
        other computed points); see the module docstring for the rule.
    """

    name: str
    body: str
    location: np.ndarray
    fixed: bool = False
    virtual: bool = False

    def __post_init__(self):
        self.location = np.asarray(self.location, dtype=float).reshape(3)


# --------------------------------------------------------------------------- #
# public functions
# --------------------------------------------------------------------------- #
def read_osim(path: str | os.PathLike, geometry_dir: str | os.PathLike | None = None, *,
              load_meshes: bool = True,
              coordinates: Mapping[str, float] | None = None) -> Skeleton:
    """Read an OpenSim model into a :class:`Skeleton` at its default pose.

    Parameters
    ----------
    path : path-like
        The ``.osim`` file (OpenSim 3 or 4 XML).
    geometry_dir : path-like, optional
        Folder of the mesh files. Default: ``<model dir>/Geometry``, then
        ``<model dir>/../Geometry``, then the model's folder.
    load_meshes : bool
        False skips the mesh files entirely (every ``Bone.mesh`` is ``None``).
    coordinates : mapping, optional
        Coordinate values (radians, or model length units for translations)
        that replace the defaults; coupled (dependent) coordinates are always
        recomputed from their constraint.

    Returns
    -------
    Skeleton
        ``world="opensim_ground"``; see the module docstring for the details
        and the metadata.

    Raises
    ------
    InputError
        The file, or the ``geometry_dir`` given, does not exist.
    FormatError
        Not well-formed XML, not an OpenSim model, or an inconsistent model
        (a joint naming a frame or coordinate that does not exist...).
    UnsupportedModelError
        A joint or function type this reader does not implement.
    """
    model = _OsimModel(path)
    values = model.coordinate_values(coordinates)
    poses = model.body_to_ground(values)
    u = model.unit_to_mm

    bones: dict[str, Bone] = {}
    for body in model.body_order():
        joint = model.joint_of_child.get(body)
        parent = None
        if joint is not None and joint.parent_body != _GROUND:
            parent = _body_name(joint.parent_body)
        T = _to_mm(poses[body], u)
        meta: dict[str, Any] = {"opensim_body": _body_name(body)}
        if joint is not None:
            meta["joint"] = joint.name
            meta["joint_type"] = joint.type
        mass = model.body_mass.get(body)
        if mass is not None:
            meta["mass"] = mass
        bones[_body_name(body)] = Bone(name=_body_name(body), parent=parent, bone_to_world=T,
                                       metadata=meta)

    # Joint centres and axes, in both the child's and the parent's frames.
    for joint in model.joints:
        if joint.child_body not in poses or joint.name in model.ignored_joints:
            continue
        child = bones[_body_name(joint.child_body)]
        centre_child = joint.child_offset[:3, 3] * u
        child.joint_centres[joint.name] = centre_child
        axis = model.joint_axis(joint, values)
        if axis is not None:
            child.joint_axes[joint.name] = joint.child_offset[:3, :3] @ axis
        if joint.parent_body != _GROUND:
            parent = bones[_body_name(joint.parent_body)]
            X = model.child_in_parent(joint, values)
            parent.joint_centres[joint.name] = (X[:3, :3] @ joint.child_offset[:3, 3] + X[:3, 3]) * u
            if axis is not None:
                parent.joint_axes[joint.name] = X[:3, :3] @ joint.child_offset[:3, :3] @ axis

    missing: list[str] = []
    unreadable: list[str] = []
    if load_meshes:
        dirs = model.geometry_dirs(geometry_dir)
        cache: dict[Path, Mesh | None] = {}
        for body in model.body_order():
            items = model.geometry.get(body, [])
            parts: list[Mesh] = []
            files: list[str] = []
            for item in items:
                files.append(item.file)
                found = _find_file(item.file, dirs)
                if found is None:
                    missing.append(item.file)
                    continue
                if found not in cache:
                    cache[found] = _load_mesh(found, u, unreadable)
                mesh = cache[found]
                if mesh is None:
                    continue
                M = np.diag(np.append(item.scale, 1.0))
                part = mesh.transformed(_to_mm(item.transform, u) @ M)
                if np.prod(item.scale) < 0:  # a mirroring scale turns the faces inside out
                    part.faces = part.faces[:, ::-1].copy()
                parts.append(part)
            bone = bones[_body_name(body)]
            bone.metadata["mesh_files"] = files
            if parts:
                bone.mesh = _merge(parts, bone.name)
        if missing or unreadable:
            bad = sorted(set(missing)) + sorted(set(unreadable))
            shown = ", ".join(bad[:5]) + (f" and {len(bad) - 5} more" if len(bad) > 5 else "")
            what = []
            if missing:
                what.append(f"{len(set(missing))} mesh file(s) not found")
            if unreadable:
                what.append(f"{len(set(unreadable))} unreadable")
            warnings.warn(f"{model.path}: {' and '.join(what)} (looked in "
                          f"{', '.join(map(str, dirs)) or 'no folder'}): {shown}", stacklevel=2)
    else:
        dirs = []
        for body in model.body_order():
            bones[_body_name(body)].metadata["mesh_files"] = [g.file for g in model.geometry.get(body, [])]

    metadata = {
        "source": str(model.path),
        "format": "opensim",
        "model_name": model.name,
        "opensim_version": model.version,
        "layout": model.layout,
        "length_units": model.length_units,
        "coordinates": dict(values),
        "coupled_coordinates": {c.dependent: c.name for c in model.couplers},
        "joints": {j.name: {"type": j.type, "parent": _body_name(j.parent_body),
                            "child": _body_name(j.child_body), "coordinates": list(j.coordinates)}
                   for j in model.joints if j.name not in model.ignored_joints},
        "ignored_joints": sorted(model.ignored_joints),
        "markers": model.markers(),
        "geometry_dirs": [str(d) for d in dirs],
        "missing_meshes": sorted(set(missing)),
        "unreadable_meshes": sorted(set(unreadable)),
    }
    return Skeleton(bones=bones, world=WORLD, metadata=metadata)


def read_osim_markers(path: str | os.PathLike) -> list[OsimMarker]:
    """The model's MarkerSet, in file order (no mesh is read).

    Same list as ``read_osim(path).metadata["markers"]``. Locations are in mm
    in their body's frame; place them with :func:`markers_in_world`.
    """
    return _OsimModel(path).markers()


def markers_in_world(skeleton: Skeleton,
                     markers: Iterable[OsimMarker] | None = None) -> dict[str, np.ndarray]:
    """Marker positions (mm) in the skeleton's world frame at its reference pose.

    ``markers`` defaults to ``skeleton.metadata["markers"]``. A marker on
    ``"ground"`` is returned as stored; one on a body that is not a bone raises
    ``KeyError``.
    """
    if markers is None:
        markers = skeleton.metadata.get("markers", [])
    out: dict[str, np.ndarray] = {}
    for m in markers:
        if m.body == "ground":
            out[m.name] = m.location.copy()
            continue
        T = skeleton.bones[m.body].bone_to_world
        out[m.name] = T[:3, :3] @ m.location + T[:3, 3]
    return out


# --------------------------------------------------------------------------- #
# model parsing
# --------------------------------------------------------------------------- #
@dataclass
class _Frame:
    path: str
    parent: str | None          # absolute path of the parent frame; None for ground and bodies
    T: np.ndarray               # this frame -> parent frame (model units)


@dataclass
class _Geometry:
    file: str
    scale: np.ndarray
    transform: np.ndarray       # geometry frame -> body frame (model units)


@dataclass
class _Joint:
    name: str
    type: str
    element: ET.Element
    parent_body: str = ""
    child_body: str = ""
    parent_offset: np.ndarray = field(default_factory=lambda: np.eye(4))
    child_offset: np.ndarray = field(default_factory=lambda: np.eye(4))
    coordinates: list[str] = field(default_factory=list)
    spatial: list[tuple[str, np.ndarray, list[str], Callable[..., float]]] | None = None


@dataclass
class _Coupler:
    name: str
    dependent: str
    independent: list[str]
    function: Callable[..., float]
    scale: float


class _OsimModel:
    """The kinematic content of one .osim file, in model units (metres)."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        if not self.path.exists():
            raise InputError("no such file", self.path)
        if self.path.is_dir():
            raise InputError("is a folder, not an .osim file", self.path)
        try:
            root = ET.parse(self.path).getroot()
        except ET.ParseError as exc:
            raise FormatError(f"not well-formed XML ({exc})", self.path) from None
        model = root.find("Model") if root.tag == "OpenSimDocument" else (
            root if root.tag == "Model" else None)
        if model is None:
            raise FormatError(f"not an OpenSim model (root element <{root.tag}>, "
                              "expected <OpenSimDocument> with a <Model>)", self.path)
        self.model = model
        self.name = model.get("name", "")
        try:
            self.version = int(root.get("Version", "0"))
        except ValueError:
            self.version = 0
        self.length_units = (model.findtext("length_units") or "meters").strip()
        if self.length_units.lower() not in _UNIT_TO_MM:
            raise FormatError(f"unknown length_units {self.length_units!r}", self.path)
        self.unit_to_mm = _UNIT_TO_MM[self.length_units.lower()]

        self.frames: dict[str, _Frame] = {_GROUND: _Frame(_GROUND, None, np.eye(4))}
        self.bodies: list[str] = []             # body paths in BodySet order
        self.body_mass: dict[str, float] = {}
        self.joints: list[_Joint] = []
        self.coordinates: dict[str, float] = {}  # name -> default value
        self.coordinate_joint: dict[str, str] = {}
        self.geometry: dict[str, list[_Geometry]] = {}
        self._raw_geometry: list[tuple[str, str, np.ndarray, str]] = []  # (frame, file, scale, mesh path)
        self._raw_markers: list[tuple[str, str, np.ndarray, bool]] = []  # (name, frame, loc, fixed)
        self.ignored_joints: set[str] = set()

        bodyset = _objects(model.find("BodySet"))
        jointset = _objects(model.find("JointSet"))
        nested = any(b.find("Joint") is not None for b in bodyset)
        if jointset or not nested:
            self.layout = "opensim4"
            self._parse_v4(bodyset, jointset)
        else:
            self.layout = "opensim3"
            self._parse_v3(bodyset)
        self._parse_couplers()
        self._resolve_joints()
        self._resolve_geometry()

    # ----------------------------------------------------------------- v4
    def _parse_v4(self, bodyset: list[ET.Element], jointset: list[ET.Element]) -> None:
        ground = self.model.find("Ground")
        if ground is not None:
            self._collect_frame_children(ground, _GROUND)
        for b in bodyset:
            name = self._name(b, "Body")
            p = f"/bodyset/{name}"
            self.frames[p] = _Frame(p, None, np.eye(4))
            self.bodies.append(p)
            self._read_mass(b, p)
            self._collect_frame_children(b, p)
        for c in _objects(self.model.find("ComponentSet")):
            self._collect_component(c, f"/componentset/{self._name(c, c.tag)}")
        comps = self.model.find("components")
        if comps is not None:
            for c in comps:
                self._collect_component(c, f"/{self._name(c, c.tag)}")
        for j in jointset:
            name = self._name(j, j.tag)
            jp = f"/jointset/{name}"
            frames = j.find("frames")
            if frames is not None:
                for f in frames:
                    self._collect_component(f, f"{jp}/{self._name(f, f.tag)}")
            joint = _Joint(name=name, type=j.tag, element=j)
            joint.parent_body = self._join(jp, self._text(j, "socket_parent_frame", name))
            joint.child_body = self._join(jp, self._text(j, "socket_child_frame", name))
            coords = j.find("coordinates")
            for c in (coords if coords is not None else []):
                if c.tag == "Coordinate":
                    self._add_coordinate(c, name)
                    joint.coordinates.append(c.get("name"))
            self.joints.append(joint)
        for m in _objects(self.model.find("MarkerSet")):
            if m.tag != "Marker":
                continue
            name = self._name(m, "Marker")
            parent = m.findtext("socket_parent_frame") or m.findtext("body")
            if parent is None:
                raise FormatError(f"marker {name!r} names no parent frame", self.path)
            self._raw_markers.append((name, self._join(f"/markerset/{name}", parent.strip()),
                                      self._vec(m, "location", 3, f"marker {name!r}"),
                                      _bool(m.findtext("fixed"))))

    def _collect_component(self, el: ET.Element, path: str) -> None:
        """A PhysicalOffsetFrame (or other component) at ``path``, with its children."""
        if el.tag == "PhysicalOffsetFrame":
            parent = el.findtext("socket_parent")
            if parent is None:
                raise FormatError(f"PhysicalOffsetFrame {path!r} has no socket_parent", self.path)
            T = _transform(self._vec(el, "orientation", 3, path, default=(0, 0, 0)),
                           self._vec(el, "translation", 3, path, default=(0, 0, 0)))
            self.frames[path] = _Frame(path, self._join(path, parent.strip()), T)
        self._collect_frame_children(el, path)

    def _collect_frame_children(self, el: ET.Element, path: str) -> None:
        geoms = el.find("attached_geometry")
        if geoms is not None:
            for g in geoms:
                if g.tag != "Mesh":
                    continue
                gname = g.get("name") or "mesh"
                gpath = f"{path}/{gname}"
                frame = (g.findtext("socket_frame") or "..").strip()
                mesh_file = (g.findtext("mesh_file") or "").strip()
                if mesh_file:
                    self._raw_geometry.append((self._join(gpath, frame), mesh_file,
                                               self._vec(g, "scale_factors", 3, gpath,
                                                         default=(1, 1, 1)), gpath))
        comps = el.find("components")
        if comps is not None:
            for c in comps:
                self._collect_component(c, f"{path}/{self._name(c, c.tag)}")

    # ----------------------------------------------------------------- v3
    def _parse_v3(self, bodyset: list[ET.Element]) -> None:
        names = [self._name(b, "Body") for b in bodyset]
        ground_name = "ground" if "ground" in names else None
        if ground_name is None:
            # OpenSim 3 grounds the body that has no joint.
            for b, n in zip(bodyset, names):
                jel = b.find("Joint")
                if jel is None or len(jel) == 0:
                    ground_name = n
                    break
        paths = {n: (_GROUND if n == ground_name else f"/bodyset/{n}") for n in names}
        for b, n in zip(bodyset, names):
            p = paths[n]
            if p != _GROUND:
                self.frames[p] = _Frame(p, None, np.eye(4))
                self.bodies.append(p)
                self._read_mass(b, p)
            self._collect_v3_geometry(b, p)
        for b, n in zip(bodyset, names):
            jel = b.find("Joint")
            if jel is None or len(jel) == 0:
                continue
            j = jel[0]
            name = self._name(j, j.tag)
            if _bool(j.findtext("reverse")):
                raise UnsupportedModelError(f"{j.tag} {name!r} is reversed (reverse=true), "
                                            "which is not supported", self.path)
            pname = (j.findtext("parent_body") or "").strip()
            if pname not in paths:
                raise FormatError(f"joint {name!r} names a parent body {pname!r} that is not in "
                                  "the BodySet", self.path)
            jp = f"/jointset/{name}"
            pf, cf = f"{jp}/parent_offset", f"{jp}/child_offset"
            where = f"joint {name!r}"
            self.frames[pf] = _Frame(pf, paths[pname], _transform(
                self._vec(j, "orientation_in_parent", 3, where, default=(0, 0, 0)),
                self._vec(j, "location_in_parent", 3, where, default=(0, 0, 0))))
            self.frames[cf] = _Frame(cf, paths[n], _transform(
                self._vec(j, "orientation", 3, where, default=(0, 0, 0)),
                self._vec(j, "location", 3, where, default=(0, 0, 0))))
            joint = _Joint(name=name, type=j.tag, element=j, parent_body=pf, child_body=cf)
            for c in _objects(j.find("CoordinateSet")):
                if c.tag == "Coordinate":
                    self._add_coordinate(c, name)
                    joint.coordinates.append(c.get("name"))
            self.joints.append(joint)
        for m in _objects(self.model.find("MarkerSet")):
            if m.tag != "Marker":
                continue
            name = self._name(m, "Marker")
            body = (m.findtext("body") or m.findtext("socket_parent_frame") or "").strip()
            if body not in paths:
                raise FormatError(f"marker {name!r} is on body {body!r}, which is not in the "
                                  "BodySet", self.path)
            self._raw_markers.append((name, paths[body],
                                      self._vec(m, "location", 3, f"marker {name!r}"),
                                      _bool(m.findtext("fixed"))))

    def _collect_v3_geometry(self, b: ET.Element, body_path: str) -> None:
        vo = b.find("VisibleObject")
        if vo is None:
            return
        where = f"VisibleObject of {body_path}"
        outer_scale = self._vec(vo, "scale_factors", 3, where, default=(1, 1, 1))
        outer = self._vec(vo, "transform", 6, where, default=(0,) * 6)
        T_outer = _transform(outer[:3], outer[3:])
        items: list[tuple[str, np.ndarray, np.ndarray]] = []
        gs = _objects(vo.find("GeometrySet"))
        for dg in gs:
            f = (dg.findtext("geometry_file") or "").strip()
            if not f:
                continue
            inner = self._vec(dg, "transform", 6, where, default=(0,) * 6)
            items.append((f, outer_scale * self._vec(dg, "scale_factors", 3, where, default=(1, 1, 1)),
                          T_outer @ _transform(inner[:3], inner[3:])))
        if not gs:
            for f in (vo.findtext("geometry_files") or "").split():
                items.append((f, outer_scale, T_outer))
        for k, (f, s, T) in enumerate(items):
            fp = f"{body_path}/_geometry_{k}"
            self.frames[fp] = _Frame(fp, body_path, T)
            self._raw_geometry.append((fp, f, s, fp))

    # ----------------------------------------------------------------- common
    def _read_mass(self, b: ET.Element, p: str) -> None:
        m = b.findtext("mass")
        if m is not None:
            try:
                self.body_mass[p] = float(m)
            except ValueError:
                pass

    def _add_coordinate(self, c: ET.Element, joint: str) -> None:
        name = c.get("name")
        if not name:
            raise FormatError(f"a Coordinate of joint {joint!r} has no name", self.path)
        if name in self.coordinates:
            raise FormatError(f"coordinate {name!r} is defined twice", self.path)
        self.coordinates[name] = self._float(c.findtext("default_value"), f"coordinate {name!r}",
                                             default=0.0)
        self.coordinate_joint[name] = joint

    def _parse_couplers(self) -> None:
        self.couplers: list[_Coupler] = []
        for c in _objects(self.model.find("ConstraintSet")):
            if c.tag != "CoordinateCouplerConstraint":
                continue
            name = c.get("name", "")
            if not _bool(c.findtext("isEnforced"), True) or _bool(c.findtext("isDisabled"), False):
                continue
            dep = (c.findtext("dependent_coordinate_name") or "").strip()
            ind = (c.findtext("independent_coordinate_names") or "").split()
            for q in [dep, *ind]:
                if q not in self.coordinates:
                    raise FormatError(f"CoordinateCouplerConstraint {name!r} names a coordinate "
                                      f"{q!r} that no joint defines", self.path)
            fel = c.find("coupled_coordinates_function")
            if fel is None:
                raise FormatError(f"CoordinateCouplerConstraint {name!r} has no "
                                  "coupled_coordinates_function", self.path)
            fn = _function_of(fel, f"CoordinateCouplerConstraint {name!r}", self.path)
            scale = self._float(c.findtext("scale_factor"), name, default=1.0)
            self.couplers.append(_Coupler(name, dep, ind, fn, scale))

    def _resolve_joints(self) -> None:
        self.joint_of_child: dict[str, _Joint] = {}
        for joint in self.joints:
            where = f"{joint.type} {joint.name!r}"
            if joint.type not in SUPPORTED_JOINTS:
                raise UnsupportedModelError(
                    f"joint type {joint.type} (joint {joint.name!r}) is not supported; supported: "
                    f"{', '.join(SUPPORTED_JOINTS)}", self.path)
            joint.parent_body, joint.parent_offset = self._frame_in_body(joint.parent_body, where)
            joint.child_body, joint.child_offset = self._frame_in_body(joint.child_body, where)
            if joint.child_body == _GROUND:
                raise UnsupportedModelError(f"{where} has the ground as its child (a reversed "
                                            "joint), which is not supported", self.path)
            for q in joint.coordinates:
                if q is None:
                    raise FormatError(f"{where} has a Coordinate without a name", self.path)
            self._check_joint_coordinates(joint, where)
            if joint.type == "CustomJoint":
                joint.spatial = self._spatial_transform(joint, where)
            if joint.child_body in self.joint_of_child:
                other = self.joint_of_child[joint.child_body]
                warnings.warn(f"{self.path}: body {_body_name(joint.child_body)!r} is the child of "
                              f"joints {other.name!r} and {joint.name!r}; the second is ignored "
                              "(kinematic loop)", stacklevel=4)
                self.ignored_joints.add(joint.name)
                continue
            self.joint_of_child[joint.child_body] = joint
        # Every body must hang from the ground through joints, without cycles.
        for body in self.bodies:
            seen = []
            b = body
            while b != _GROUND:
                if b in seen:
                    raise FormatError(f"the joints form a cycle through body {_body_name(b)!r}",
                                      self.path)
                seen.append(b)
                j = self.joint_of_child.get(b)
                if j is None:
                    raise FormatError(f"body {_body_name(b)!r} is not connected to the ground by "
                                      "any joint", self.path)
                b = j.parent_body

    _DOF = {"WeldJoint": 0, "PinJoint": 1, "SliderJoint": 1, "UniversalJoint": 2, "BallJoint": 3,
            "GimbalJoint": 3, "FreeJoint": 6, "PlanarJoint": 3}

    def _check_joint_coordinates(self, joint: _Joint, where: str) -> None:
        n = self._DOF.get(joint.type)
        if n is not None and len(joint.coordinates) != n:
            raise FormatError(f"{where} has {len(joint.coordinates)} coordinates, expected {n}",
                              self.path)

    def _spatial_transform(self, joint: _Joint, where: str):
        st = joint.element.find("SpatialTransform")
        if st is None:
            raise FormatError(f"{where} has no SpatialTransform", self.path)
        axes = {ta.get("name"): ta for ta in st.findall("TransformAxis")}
        out = []
        for key in ("rotation1", "rotation2", "rotation3", "translation1", "translation2",
                    "translation3"):
            ta = axes.get(key)
            if ta is None:
                continue
            axis = self._vec(ta, "axis", 3, f"{where} {key}")
            norm = float(np.linalg.norm(axis))
            coords = (ta.findtext("coordinates") or "").split()
            for q in coords:
                if q not in self.coordinates:
                    raise FormatError(f"{where} {key} uses coordinate {q!r}, which no joint "
                                      "defines", self.path)
            fn = _function_of(ta, f"{where} {key}", self.path, optional=True)
            if fn is None:  # OpenSim's default: the coordinate itself, or zero
                fn = (lambda *x: float(x[0])) if coords else (lambda *x: 0.0)
            if norm == 0.0:
                continue
            out.append((key, axis / norm, coords, fn))
        return out

    def _frame_in_body(self, path: str, where: str) -> tuple[str, np.ndarray]:
        """(body path, frame -> body transform) of a frame path."""
        T = np.eye(4)
        p = self._lookup(path, where)
        seen = set()
        while self.frames[p].parent is not None:
            if p in seen:
                raise FormatError(f"offset frames form a cycle at {p!r} ({where})", self.path)
            seen.add(p)
            f = self.frames[p]
            T = f.T @ T
            p = self._lookup(f.parent, f"frame {f.path!r}")
        return p, T

    def _lookup(self, path: str, where: str) -> str:
        if path in self.frames:
            return path
        # Fall back on the last path element (old files use other path styles).
        base = path.rstrip("/").rsplit("/", 1)[-1]
        if base == "ground":
            return _GROUND
        if f"/bodyset/{base}" in self.frames:
            return f"/bodyset/{base}"
        hits = [k for k in self.frames if k.rsplit("/", 1)[-1] == base]
        if len(hits) == 1:
            return hits[0]
        raise FormatError(f"{where} refers to frame {path!r}, which is not in the model", self.path)

    def _resolve_geometry(self) -> None:
        for frame, file, scale, gpath in self._raw_geometry:
            try:
                body, T = self._frame_in_body(frame, f"mesh {gpath!r}")
            except FormatError:
                warnings.warn(f"{self.path}: mesh {gpath!r} ({file}) is attached to an unknown "
                              f"frame {frame!r}; ignored", stacklevel=4)
                continue
            if body == _GROUND:
                continue
            self.geometry.setdefault(body, []).append(_Geometry(file, scale, T))

    # ----------------------------------------------------------------- evaluation
    def coordinate_values(self, overrides: Mapping[str, float] | None = None) -> dict[str, float]:
        values = dict(self.coordinates)
        for k, v in (overrides or {}).items():
            if k not in values:
                raise KeyError(f"no coordinate {k!r} in model {self.name!r}")
            values[k] = float(v)
        # Couplers may chain: apply in dependency order (at most len passes).
        pending = list(self.couplers)
        for _ in range(len(pending) + 1):
            if not pending:
                break
            deps = {c.dependent for c in pending}
            rest = []
            for c in pending:
                if any(q in deps for q in c.independent):
                    rest.append(c)
                    continue
                values[c.dependent] = c.scale * float(c.function(*(values[q] for q in c.independent)))
            if len(rest) == len(pending):
                raise FormatError("CoordinateCouplerConstraints depend on each other in a cycle",
                                  self.path)
            pending = rest
        return values

    def joint_transform(self, joint: _Joint, values: Mapping[str, float]) -> np.ndarray:
        """The mobilizer transform J(q): child offset frame -> parent offset frame."""
        q = [values[c] for c in joint.coordinates]
        t = joint.type
        if t == "WeldJoint":
            return np.eye(4)
        if t == "PinJoint":
            return _transform_R(_rot([0, 0, 1], q[0]))
        if t == "SliderJoint":
            return _transform_R(np.eye(3), [q[0], 0, 0])
        if t == "UniversalJoint":
            return _transform_R(_rot([1, 0, 0], q[0]) @ _rot([0, 1, 0], q[1]))
        if t in ("BallJoint", "GimbalJoint"):
            return _transform(q[:3], (0, 0, 0))
        if t == "FreeJoint":
            return _transform(q[:3], q[3:6])
        if t == "PlanarJoint":
            return _transform_R(_rot([0, 0, 1], q[0]), [q[1], q[2], 0])
        if t == "CustomJoint":
            R = np.eye(3)
            p = np.zeros(3)
            for key, axis, coords, fn in joint.spatial or []:
                v = float(fn(*(values[c] for c in coords)))
                if key.startswith("rotation"):
                    R = R @ _rot(axis, v)
                else:
                    p = p + v * axis
            return _transform_R(R, p)
        raise UnsupportedModelError(f"joint type {t} (joint {joint.name!r}) is not supported",
                                    self.path)

    def child_in_parent(self, joint: _Joint, values: Mapping[str, float]) -> np.ndarray:
        """Child body frame -> parent body frame: P . J(q) . inverse(C)."""
        return joint.parent_offset @ self.joint_transform(joint, values) @ _inv(joint.child_offset)

    def joint_axis(self, joint: _Joint, values: Mapping[str, float]) -> np.ndarray | None:
        """The single rotation axis of a joint in its child offset frame, if it has one."""
        if joint.type == "PinJoint":
            return np.array([0.0, 0.0, 1.0])
        if joint.type == "CustomJoint":
            driven = [(k, a) for k, a, c, fn in joint.spatial or []
                      if k.startswith("rotation") and c and not getattr(fn, "constant", False)]
            if len(driven) == 1:
                return driven[0][1].copy()
        return None

    def body_order(self) -> list[str]:
        order: list[str] = []
        placed = set()

        def visit(b: str) -> None:
            if b in placed or b == _GROUND:
                return
            visit(self.joint_of_child[b].parent_body)
            placed.add(b)
            order.append(b)

        for b in self.bodies:
            visit(b)
        return order

    def body_to_ground(self, values: Mapping[str, float]) -> dict[str, np.ndarray]:
        poses = {_GROUND: np.eye(4)}
        for b in self.body_order():
            j = self.joint_of_child[b]
            poses[b] = poses[j.parent_body] @ self.child_in_parent(j, values)
        del poses[_GROUND]
        return poses

    def joint_centres_by_body(self) -> dict[str, list[np.ndarray]]:
        """Joint centres (model units) of each body, from both sides of its joints."""
        out: dict[str, list[np.ndarray]] = {}
        values = self.coordinate_values()
        for j in self.joints:
            if j.name in self.ignored_joints:
                continue
            out.setdefault(j.child_body, []).append(j.child_offset[:3, 3].copy())
            X = self.child_in_parent(j, values)
            out.setdefault(j.parent_body, []).append(X[:3, :3] @ j.child_offset[:3, 3] + X[:3, 3])
            out[j.parent_body].append(j.parent_offset[:3, 3].copy())
        return out

    def markers(self) -> list[OsimMarker]:
        centres = self.joint_centres_by_body()
        out = []
        for name, frame, loc, fixed in self._raw_markers:
            body, T = self._frame_in_body(frame, f"marker {name!r}")
            p = T[:3, :3] @ loc + T[:3, 3]
            virtual = bool(_VIRTUAL_NAME.search(name))
            if not virtual:
                for c in centres.get(body, []):
                    if np.linalg.norm(p - c) * self.unit_to_mm <= _VIRTUAL_DISTANCE_MM:
                        virtual = True
                        break
            out.append(OsimMarker(name=name, body=_body_name(body), location=p * self.unit_to_mm,
                                  fixed=fixed, virtual=virtual))
        return out

    def geometry_dirs(self, geometry_dir: str | os.PathLike | None) -> list[Path]:
        if geometry_dir is not None:
            d = Path(geometry_dir)
            if not d.is_dir():
                raise InputError("geometry folder does not exist", d)
            return [d]
        here = self.path.resolve().parent
        cands = [here / "Geometry", here.parent / "Geometry", here]
        return [d for d in cands if d.is_dir()]

    # ----------------------------------------------------------------- helpers
    def _name(self, el: ET.Element, what: str) -> str:
        name = el.get("name")
        if not name:
            raise FormatError(f"a <{el.tag}> ({what}) has no name", self.path)
        return name

    def _text(self, el: ET.Element, tag: str, owner: str) -> str:
        t = el.findtext(tag)
        if t is None or not t.strip():
            raise FormatError(f"{el.tag} {owner!r} has no <{tag}>", self.path)
        return t.strip()

    def _join(self, owner: str, rel: str) -> str:
        rel = rel.strip()
        if rel.startswith("/"):
            return posixpath.normpath(rel)
        return posixpath.normpath(posixpath.join(owner, rel))

    def _float(self, text: str | None, where: str, default: float | None = None) -> float:
        if text is None or not text.strip():
            if default is None:
                raise FormatError(f"{where}: missing number", self.path)
            return default
        try:
            return float(text)
        except ValueError:
            raise FormatError(f"{where}: {text.strip()!r} is not a number", self.path) from None

    def _vec(self, el: ET.Element, tag: str, n: int, where: str,
             default: Iterable[float] | None = None) -> np.ndarray:
        text = el.findtext(tag)
        if text is None or not text.strip():
            if default is None:
                raise FormatError(f"{where}: missing <{tag}>", self.path)
            return np.asarray(list(default), dtype=float)
        try:
            v = np.array([float(x) for x in text.split()], dtype=float)
        except ValueError:
            raise FormatError(f"{where}: <{tag}> {text.strip()!r} is not {n} numbers",
                              self.path) from None
        if v.shape != (n,):
            raise FormatError(f"{where}: <{tag}> has {v.size} numbers, expected {n}", self.path)
        return v


# --------------------------------------------------------------------------- #
# functions (OpenSim Function subclasses)
# --------------------------------------------------------------------------- #
def _function_of(owner: ET.Element, where: str, path: Path, optional: bool = False):
    """The function held by ``owner`` (a TransformAxis, a MultiplierFunction's
    ``function`` property, a constraint's ``coupled_coordinates_function``).

    OpenSim 4 writes the function as a direct child (``<SimmSpline
    name="function">``); OpenSim 3 wraps it in ``<function>``.
    """
    el = None
    for child in owner:
        if child.tag in ("coordinates", "axis", "scale", "value", "coefficients", "x", "y"):
            continue
        if child.tag == "function":
            inner = [c for c in child if isinstance(c.tag, str)]
            if inner:
                el = inner[0]
                break
            continue
        if child.tag[:1].isupper():
            el = child
            break
    if el is None:
        if optional:
            return None
        raise FormatError(f"{where}: no function", path)
    return _make_function(el, where, path)


def _numbers(el: ET.Element, tag: str, where: str, path: Path) -> np.ndarray:
    text = el.findtext(tag)
    if text is None:
        raise FormatError(f"{where}: {el.tag} has no <{tag}>", path)
    try:
        return np.array([float(x) for x in text.split()], dtype=float)
    except ValueError:
        raise FormatError(f"{where}: {el.tag} <{tag}> is not a list of numbers", path) from None


def _make_function(el: ET.Element, where: str, path: Path):
    t = el.tag
    if t == "Constant":
        v = float(_numbers(el, "value", where, path)[0]) if el.findtext("value") else 0.0
        fn = lambda *x: v  # noqa: E731
        fn.constant = True
        return fn
    if t == "LinearFunction":
        c = _numbers(el, "coefficients", where, path)
        if c.size != 2:
            raise FormatError(f"{where}: LinearFunction needs 2 coefficients, has {c.size}", path)
        return lambda x, *rest: c[0] * x + c[1]
    if t in ("SimmSpline", "NaturalCubicSpline", "PiecewiseLinearFunction"):
        x = _numbers(el, "x", where, path)
        y = _numbers(el, "y", where, path)
        if x.size != y.size or x.size < 1 or np.any(np.diff(x) <= 0):
            raise FormatError(f"{where}: {t} needs increasing x and as many y "
                              f"(has {x.size} x, {y.size} y)", path)
        if t == "SimmSpline":
            return SimmSpline(x, y)
        if t == "NaturalCubicSpline":
            return _NaturalSpline(x, y)
        return _PiecewiseLinear(x, y)
    if t == "MultiplierFunction":
        inner = _function_of(el, f"{where} MultiplierFunction", path)
        s = float(el.findtext("scale") or 1.0)
        return lambda *x: s * inner(*x)
    if t == "PolynomialFunction":
        c = _numbers(el, "coefficients", where, path)
        return lambda x, *rest: float(np.polyval(c, x))
    if t == "Sine":
        a = float(el.findtext("amplitude") or 1.0)
        w = float(el.findtext("omega") or 1.0)
        ph = float(el.findtext("phase") or 0.0)
        off = float(el.findtext("offset") or 0.0)
        return lambda x, *rest: a * math.sin(w * x + ph) + off
    raise UnsupportedModelError(f"{where}: function type {t} is not supported; supported: "
                                f"{', '.join(SUPPORTED_FUNCTIONS)}", path)


class SimmSpline:
    """OpenSim's ``SimmSpline``: an interpolating cubic spline.

    Not a natural spline: the end conditions make the spline's third
    derivative at each end equal that of the cubic through the four nearest
    points (Forsythe, Malcolm & Moler's ``spline``), so a cubic polynomial is
    reproduced exactly. Outside ``[x[0], x[-1]]`` it continues along the end
    tangent. Two points give a straight line.
    """

    def __init__(self, x: np.ndarray, y: np.ndarray):
        x = np.asarray(x, dtype=float)
        y = np.asarray(y, dtype=float)
        self.x, self.y = x, y
        n = x.size
        if n == 1:
            self.b = self.c = self.d = np.zeros(1)
            return
        h = np.diff(x)
        if n == 2:
            s = (y[1] - y[0]) / h[0]
            self.b, self.c, self.d = np.full(2, s), np.zeros(2), np.zeros(2)
            return
        delta = np.diff(y) / h
        # Tridiagonal system for sigma (= second derivative / 6 at the knots).
        diag = np.empty(n)
        off = h.copy()              # off[i] couples i and i+1
        rhs = np.empty(n)
        diag[1:-1] = 2.0 * (h[:-1] + h[1:])
        rhs[1:-1] = delta[1:] - delta[:-1]
        diag[0], diag[-1] = -h[0], -h[-1]
        rhs[0] = rhs[-1] = 0.0
        if n > 3:
            # Third divided differences of the end cubics.
            r0 = rhs[2] / (x[3] - x[1]) - rhs[1] / (x[2] - x[0])
            rn = rhs[n - 2] / (x[n - 1] - x[n - 3]) - rhs[n - 3] / (x[n - 2] - x[n - 4])
            rhs[0] = r0 * h[0] ** 2 / (x[3] - x[0])
            rhs[-1] = -rn * h[-1] ** 2 / (x[n - 1] - x[n - 4])
        # Thomas algorithm (the matrix is symmetric: sub = super = h).
        diag = diag.copy()
        for i in range(1, n):
            t = off[i - 1] / diag[i - 1]
            diag[i] -= t * off[i - 1]
            rhs[i] -= t * rhs[i - 1]
        sig = np.empty(n)
        sig[-1] = rhs[-1] / diag[-1]
        for i in range(n - 2, -1, -1):
            sig[i] = (rhs[i] - off[i] * sig[i + 1]) / diag[i]
        b = np.empty(n)
        c = np.empty(n)
        d = np.empty(n)
        b[:-1] = delta - h * (sig[1:] + 2.0 * sig[:-1])
        b[-1] = delta[-1] + h[-1] * (sig[-2] + 2.0 * sig[-1])
        d[:-1] = (sig[1:] - sig[:-1]) / h
        d[-1] = d[-2]
        c[:] = 3.0 * sig
        self.b, self.c, self.d = b, c, d

    def __call__(self, x: float, *rest: float) -> float:
        xs, ys = self.x, self.y
        n = xs.size
        if n == 1:
            return float(ys[0])
        if x < xs[0]:
            return float(ys[0] + (x - xs[0]) * self.b[0])
        if x > xs[-1]:
            return float(ys[-1] + (x - xs[-1]) * self.b[-1])
        k = int(np.clip(np.searchsorted(xs, x, side="right") - 1, 0, n - 2))
        dx = x - xs[k]
        return float(ys[k] + dx * (self.b[k] + dx * (self.c[k] + dx * self.d[k])))


class _NaturalSpline:
    """OpenSim ``NaturalCubicSpline`` (zero second derivative at both ends)."""

    def __init__(self, x: np.ndarray, y: np.ndarray):
        from scipy.interpolate import CubicSpline

        self.x, self.y = x, y
        self.s = CubicSpline(x, y, bc_type="natural") if x.size > 2 else None

    def __call__(self, x: float, *rest: float) -> float:
        xs, ys = self.x, self.y
        if self.s is None:
            return float(np.interp(x, xs, ys)) if xs.size > 1 else float(ys[0])
        if x < xs[0]:
            return float(ys[0] + (x - xs[0]) * self.s(xs[0], 1))
        if x > xs[-1]:
            return float(ys[-1] + (x - xs[-1]) * self.s(xs[-1], 1))
        return float(self.s(x))


class _PiecewiseLinear:
    """OpenSim ``PiecewiseLinearFunction``, extrapolated along the end segments."""

    def __init__(self, x: np.ndarray, y: np.ndarray):
        self.x, self.y = x, y

    def __call__(self, x: float, *rest: float) -> float:
        xs, ys = self.x, self.y
        if xs.size == 1:
            return float(ys[0])
        if x < xs[0]:
            return float(ys[0] + (x - xs[0]) * (ys[1] - ys[0]) / (xs[1] - xs[0]))
        if x > xs[-1]:
            return float(ys[-1] + (x - xs[-1]) * (ys[-1] - ys[-2]) / (xs[-1] - xs[-2]))
        return float(np.interp(x, xs, ys))


# --------------------------------------------------------------------------- #
# small helpers
# --------------------------------------------------------------------------- #
def _objects(el: ET.Element | None) -> list[ET.Element]:
    """The children of a Set's ``<objects>`` (empty when absent)."""
    if el is None:
        return []
    objs = el.find("objects")
    return [c for c in objs if isinstance(c.tag, str)] if objs is not None else []


def _bool(text: str | None, default: bool = False) -> bool:
    if text is None or not text.strip():
        return default
    return text.strip().lower() in ("true", "1", "yes")


def _body_name(path: str) -> str:
    return "ground" if path == _GROUND else path.rsplit("/", 1)[-1]


def _rot(axis, angle: float) -> np.ndarray:
    """Rotation matrix of ``angle`` radians about the unit ``axis`` (Rodrigues)."""
    a = np.asarray(axis, dtype=float)
    a = a / np.linalg.norm(a)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1.0 - math.cos(angle)) * (K @ K)


def _transform(xyz_body_fixed, translation) -> np.ndarray:
    """4x4 from body-fixed X-Y-Z Euler angles (radians) and a translation."""
    a, b, c = (float(v) for v in xyz_body_fixed)
    R = _rot([1, 0, 0], a) @ _rot([0, 1, 0], b) @ _rot([0, 0, 1], c)
    return _transform_R(R, translation)


def _transform_R(R: np.ndarray, t=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=float)
    return T


def _inv(T: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def _to_mm(T: np.ndarray, unit_to_mm: float) -> np.ndarray:
    out = T.copy()
    out[:3, 3] *= unit_to_mm
    return out


def _find_file(name: str, dirs: list[Path]) -> Path | None:
    p = Path(name)
    if p.is_absolute():
        return p if p.is_file() else None
    for d in dirs:
        if (d / p).is_file():
            return d / p
    return None


def _load_mesh(path: Path, unit_to_mm: float, unreadable: list[str]) -> Mesh | None:
    """One geometry file (in the model's length unit, metres as a rule) as a
    Mesh in mm, or None if it cannot be read."""
    from bonecap.io.mesh import read_mesh

    try:
        mesh = read_mesh(path, units="m")
    except InputError:
        unreadable.append(path.name)
        return None
    if unit_to_mm != 1000.0:
        mesh.vertices *= unit_to_mm / 1000.0
    return mesh


def _merge(parts: list[Mesh], frame: str) -> Mesh:
    verts = []
    faces = []
    n = 0
    for m in parts:
        verts.append(m.vertices)
        faces.append(m.faces + n)
        n += len(m.vertices)
    return Mesh(np.concatenate(verts), np.concatenate(faces), frame)
