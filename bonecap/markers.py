"""Marker sets: anatomical marker definitions, label matching, and placement on a skeleton.

A marker set (``marker_sets/*.yaml``) defines each marker anatomically -- the
bone that carries it, a landmark of that bone, and the offset from the bone
surface to the marker centre along the skin normal -- plus the bones it
tracks and the other labels labs give it. Because it names landmarks, not
coordinates, the same set places markers on the generic template, on a
personal skeleton warped from it, or on an imported OpenSim model (whose own
MarkerSet becomes a marker set with coordinates already bound to bodies).

A set may ``extend`` another (the paper's set extends Plug-in Gait) and may
carry a ``paper_solver`` table: for each bone, where the paper's rule-based
solver takes the proximal and distal joint centres and the twist marker pair.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from bonecap.errors import BonecapError, DataError, FormatError, InputError
from bonecap.io import load_yaml
from bonecap.model import Skeleton

__all__ = ["MarkerDef", "MarkerSet", "MARKER_SET_DIR", "available_marker_sets", "load_marker_set",
           "marker_set_from_osim", "check_marker_set", "place_markers", "match_labels",
           "LIMB_LONG_BONES", "limb_side_directions", "midline_directions", "MIDLINE_TOLERANCE_MM",
           "joint_centre_axis", "subject_parameter", "joint_width_placement", "DEFAULT_MARKER_DIAMETER_MM"]

#: Folder of the marker sets shipped with bonecap (beside the package in the source tree).
MARKER_SET_DIR = Path(__file__).resolve().parents[1] / "marker_sets"


@dataclass
class MarkerDef:
    """One marker, defined on the anatomy.

    Attributes
    ----------
    name : str
        The label the set uses (``"RASI"``).
    bone : str
        Bone that carries the landmark (or, for an OpenSim marker, its body).
    landmark : str or None
        Landmark name on ``bone``; ``None`` when ``location`` is given instead.
    offset_mm : float
        Distance from the bone surface to the marker centre along the outward
        surface normal at the landmark (soft tissue + marker radius).
    tracks : list of str
        Bones whose motion the marker follows.
    aliases : list of str
        Other labels for the same marker, matched case-insensitively.
    location : ndarray (3,) or None
        Marker position in the ``bone`` frame in mm, when the set gives it
        directly (OpenSim MarkerSets) rather than by landmark.
    virtual : bool
        A computed point (a joint centre), never expected in a trial.
    direction : ndarray (3,) or None
        Where the marker leaves the bone, as a unit vector in the ``bone``
        frame (X anterior, Y up, Z to the right on both sides), from the
        set's ``direction`` words (``lateral``, ``posterior`` ...; lateral and
        medial resolved by the bone's side suffix). ``None``: the surface
        normal rule of :func:`place_markers`.
    width : tuple of (str, str) or None
        ``(parameter, joint)`` from the set's ``width: {parameter: LKneeWidth,
        joint: knee}``: the marker sits on the side of ``joint`` and the
        subject's measured width of that joint (a trial's
        ``subject_parameters[parameter]``) sets how far out it is
        (:func:`joint_width_placement`).
    """

    name: str
    bone: str
    landmark: str | None = None
    offset_mm: float = 0.0
    tracks: list[str] = field(default_factory=list)
    aliases: list[str] = field(default_factory=list)
    description: str = ""
    location: np.ndarray | None = None
    virtual: bool = False
    optional: bool = False
    direction: np.ndarray | None = None
    width: tuple[str, str] | None = None


@dataclass
class MarkerSet:
    """A named collection of :class:`MarkerDef` plus solver hints."""

    name: str
    markers: dict[str, MarkerDef]
    description: str = ""
    paper_solver: dict[str, dict[str, Any]] = field(default_factory=dict)
    source: str = ""

    @property
    def physical(self) -> list[str]:
        """Names of the markers expected in a trial (not virtual, not optional)."""
        return [n for n, m in self.markers.items() if not m.virtual and not m.optional]


def available_marker_sets() -> list[str]:
    """Names of the marker sets shipped in ``marker_sets/``."""
    return sorted(p.stem for p in MARKER_SET_DIR.glob("*.yaml"))


def _resolve_path(name_or_path: str | os.PathLike) -> Path:
    p = Path(name_or_path)
    if p.suffix.lower() in (".yaml", ".yml", ".osim"):
        if not p.is_file():
            raise InputError("no such marker-set file", p)
        return p
    candidate = MARKER_SET_DIR / f"{name_or_path}.yaml"
    if not candidate.is_file():
        raise InputError(f"unknown marker set (shipped: {', '.join(available_marker_sets())})", name_or_path)
    return candidate


#: Direction words of a marker set, in a bone frame (X anterior, Y up, Z right). ``lateral`` and
#: ``medial`` depend on the side: the bone name's ``_r`` / ``_l`` suffix.
DIRECTION_WORDS = {"anterior": (1, 0, 0), "posterior": (-1, 0, 0), "superior": (0, 1, 0), "proximal": (0, 1, 0),
                   "inferior": (0, -1, 0), "distal": (0, -1, 0), "right": (0, 0, 1), "left": (0, 0, -1)}


def _parse_direction(spec: Any, bone: str, name: str, path: Path) -> np.ndarray | None:
    """``"lateral"``, ``"anterior lateral"``, ``[x, y, z]`` (bone frame) -> unit vector, or None."""
    if spec is None:
        return None
    if isinstance(spec, str):
        v = np.zeros(3)
        for word in spec.replace("-", " ").replace(",", " ").split():
            w = word.lower()
            if w in ("lateral", "medial"):
                side = bone[-2:]
                if side not in ("_r", "_l"):
                    raise FormatError(f"marker {name!r}: {w!r} needs a side, but bone {bone!r} has no _r/_l suffix",
                                      path)
                v += np.array([0.0, 0.0, 1.0 if (side == "_r") == (w == "lateral") else -1.0])
            elif w in DIRECTION_WORDS:
                v += np.array(DIRECTION_WORDS[w], float)
            else:
                raise FormatError(f"marker {name!r}: unknown direction word {word!r} (use "
                                  f"{', '.join([*DIRECTION_WORDS, 'lateral', 'medial'])})", path)
    else:
        try:
            v = np.asarray(spec, dtype=float).reshape(3)
        except (TypeError, ValueError):
            raise FormatError(f"marker {name!r}: direction must be words or [x, y, z]", path) from None
    if not np.isfinite(v).all() or np.linalg.norm(v) < 1e-9:
        raise FormatError(f"marker {name!r}: the direction is zero", path)
    return v / np.linalg.norm(v)


def _parse_marker(name: str, spec: Any, path: Path, optional: bool) -> MarkerDef:
    if not isinstance(spec, dict) or "bone" not in spec:
        raise FormatError(f"marker {name!r} needs a mapping with at least 'bone'", path)
    if "landmark" not in spec and "location" not in spec:
        raise FormatError(f"marker {name!r} needs a 'landmark' or a 'location'", path)
    location = spec.get("location")
    if location is not None:
        location = np.asarray(location, dtype=float).reshape(3)
    width = spec.get("width")
    if width is not None:
        if not (isinstance(width, dict) and isinstance(width.get("parameter"), str)
                and isinstance(width.get("joint"), str)):
            raise FormatError(f"marker {name!r}: 'width' needs {{parameter: NAME, joint: JOINT}}, got {width!r}",
                              path)
        width = (width["parameter"], width["joint"])
    return MarkerDef(
        width=width,
        direction=_parse_direction(spec.get("direction"), str(spec["bone"]), name, path),
        name=str(name), bone=str(spec["bone"]), landmark=spec.get("landmark"),
        offset_mm=float(spec.get("offset_mm", 0.0)), tracks=list(spec.get("tracks", [spec["bone"]])),
        aliases=[str(a) for a in spec.get("aliases", [])], description=str(spec.get("description", "")),
        location=location, virtual=bool(spec.get("virtual", False)), optional=optional,
    )


def load_marker_set(name_or_path: str | os.PathLike, _seen: tuple[str, ...] = ()) -> MarkerSet:
    """Load a marker set by shipped name (``"plug_in_gait_full_body"``) or YAML path.

    Parameters
    ----------
    name_or_path : str or path-like
        A name listed by :func:`available_marker_sets`, a ``.yaml`` file, or an
        OpenSim ``.osim`` model (its MarkerSet, see :func:`marker_set_from_osim`).

    Returns
    -------
    MarkerSet
        With the markers of any ``extends`` chain merged in (the extending
        set's definitions win).

    Raises
    ------
    InputError
        Unknown name or missing file.
    FormatError
        The YAML is malformed or a marker lacks its bone or landmark.
    """
    path = _resolve_path(name_or_path)
    if path.suffix.lower() == ".osim":
        from bonecap.skeleton.opensim import read_osim_markers

        return marker_set_from_osim(read_osim_markers(path), name=path.stem, source=str(path))
    try:
        doc = load_yaml(path.read_text())
    except yaml.YAMLError as exc:
        raise FormatError(f"not valid YAML ({str(exc).splitlines()[0]})", path) from None
    if not isinstance(doc, dict) or not isinstance(doc.get("markers"), dict):
        raise FormatError("a marker set needs a 'markers' mapping", path)
    markers: dict[str, MarkerDef] = {}
    paper: dict[str, dict[str, Any]] = {}
    parent = doc.get("extends")
    chain = _seen + (str(path.resolve()),)
    if parent:
        if str(_resolve_path(parent).resolve()) in chain:
            raise FormatError(f"marker sets extend each other in a loop (through {parent})", path)
        base = load_marker_set(parent, chain)
        markers.update(base.markers)
        paper.update(base.paper_solver)
    for section, optional in (("markers", False), ("optional", True)):
        for name, spec in (doc.get(section) or {}).items():
            markers[str(name)] = _parse_marker(name, spec, path, optional)
    paper.update(doc.get("paper_solver") or {})
    for bone, rule in paper.items():
        for key in ("proximal", "distal", "twist"):
            if key not in rule:
                raise FormatError(f"paper_solver entry for {bone!r} lacks {key!r}", path)
    return MarkerSet(name=str(doc.get("name", path.stem)), markers=markers,
                     description=str(doc.get("description", "")), paper_solver=paper, source=str(path))


def marker_set_from_osim(markers, name: str = "opensim", source: str = "") -> MarkerSet:
    """A marker set from an OpenSim MarkerSet (:func:`bonecap.skeleton.opensim.read_osim_markers`).

    OpenSim binds each marker to a body at a fixed location, so the markers
    are given by ``location`` (mm, body frame) rather than by landmark. Virtual
    markers (joint centres such as ``RKJC`` or ``R_tibial_plateau``) keep
    their flag: they are never expected in a trial.
    """
    defs = {m.name: MarkerDef(name=m.name, bone=m.body, location=np.asarray(m.location, dtype=float),
                              tracks=[m.body], virtual=bool(m.virtual),
                              description="virtual (computed point)" if m.virtual else "OpenSim marker")
            for m in markers}
    return MarkerSet(name=name, markers=defs, description=f"MarkerSet of {name}", source=source)


def check_marker_set(marker_set: MarkerSet, skeleton: Skeleton) -> None:
    """Raise a clear error if the set names a bone or landmark the skeleton lacks.

    Raises
    ------
    DataError
        Naming every missing bone/landmark with the markers that need them.
    """
    problems = []
    for m in marker_set.markers.values():
        bone = skeleton.bones.get(m.bone)
        if bone is None:
            problems.append(f"{m.name}: no bone {m.bone!r}")
        elif m.location is None and m.landmark not in bone.landmarks and m.landmark not in bone.joint_centres:
            problems.append(f"{m.name}: bone {m.bone!r} has no landmark {m.landmark!r}")
        for t in m.tracks:
            if t not in skeleton.bones:
                problems.append(f"{m.name}: tracks unknown bone {t!r}")
    for bone in marker_set.paper_solver:
        if bone not in skeleton.bones:
            problems.append(f"paper_solver: no bone {bone!r}")
    if problems:
        raise DataError(f"marker set {marker_set.name!r} does not fit the skeleton: " + "; ".join(problems),
                        marker_set.source or None)


def _nearest_surface_normals(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Outward normal of the mesh surface nearest to each point (bone frame, mm).

    Exact nearest triangle without building an R-tree: a triangle nearer than the
    nearest vertex (distance ``d``) has all its vertices within ``d`` + the longest
    edge, so only the triangles touching those vertices (one k-d tree query) are
    tested. Landmarks usually sit exactly on a vertex, where several triangles are
    equally near: their area-weighted normals are averaged, so the direction does not
    depend on which of them a search returns first.
    """
    import trimesh
    from scipy.spatial import cKDTree

    V = np.asarray(vertices, float)
    Fc = np.asarray(faces)
    tri_all = V[Fc]
    edge = float(np.linalg.norm(tri_all - np.roll(tri_all, 1, axis=1), axis=2).max())
    tree = cKDTree(V)
    d_v, _ = tree.query(points)
    out = np.zeros((len(points), 3))
    # faces around each vertex, once (vertex -> faces as a CSR-like table)
    order = np.argsort(Fc.ravel(), kind="stable")
    starts = np.searchsorted(Fc.ravel()[order], np.arange(len(V) + 1))
    for i, p in enumerate(np.asarray(points, float)):
        near_v = np.asarray(tree.query_ball_point(p, d_v[i] + edge + 1e-9), dtype=np.int64)
        cand = np.unique(np.concatenate([order[starts[v]:starts[v + 1]] for v in near_v]) // 3)
        tri = tri_all[cand]
        q = trimesh.triangles.closest_point(tri, np.repeat(p[None], len(cand), axis=0))
        d = np.linalg.norm(q - p, axis=1)
        near = d <= d.min() + 1e-6
        n = np.cross(tri[near, 1] - tri[near, 0], tri[near, 2] - tri[near, 0]).sum(axis=0)
        out[i] = n / max(float(np.linalg.norm(n)), 1e-12)
    return out


#: Long bones of the limbs (name prefixes): their markers sit on the side of the limb.
LIMB_LONG_BONES = ("femur", "tibia", "fibula", "humerus", "radius", "ulna")


def limb_side_directions(vertices: np.ndarray, points: np.ndarray, normals: np.ndarray,
                         min_radius_mm: float = 3.0) -> np.ndarray:
    """Directions from a long bone's shaft axis out through landmarks (bone frame).

    A skin marker over a limb's long bone sits on the *side* of the limb: the
    thigh marker on the lateral thigh, the wrist markers beside the styloids.
    The surface normal at the landmark says so poorly: at a styloid or a
    malleolus it points along the limb (a ray along it runs through the hand
    or the heel), and on a shaft with a ridge (linea aspera) or after a few
    millimetres of shape variation the extreme point's normal can turn by
    60-90 degrees. The bone's own long axis is stable: the line through the
    mesh centroid along its principal direction (the ISB Y axis of femur,
    tibia, humerus, radius and ulna is this axis up to a few degrees). The
    direction is the landmark's offset from that line, perpendicular to it;
    where the landmark lies on the axis (closer than ``min_radius_mm``) the
    surface normal with its axial part removed; where that vanishes too, the
    normal unchanged.

    Parameters
    ----------
    vertices : ndarray (V, 3)
        The bone mesh, bone frame (mm).
    points : ndarray (M, 3)
        Landmarks, bone frame (mm).
    normals : ndarray (M, 3)
        Unit outward surface normals at the landmarks.
    min_radius_mm : float

    Returns
    -------
    ndarray (M, 3)
        Unit directions, bone frame.
    """
    V = np.asarray(vertices, float)
    c = V.mean(axis=0)
    _, _, vt = np.linalg.svd(V - c, full_matrices=False)
    axis = vt[0]
    out = np.array(normals, dtype=float, copy=True)
    for i, p in enumerate(np.asarray(points, float)):
        r = (p - c) - ((p - c) @ axis) * axis
        if np.linalg.norm(r) >= min_radius_mm:
            out[i] = r / np.linalg.norm(r)
            continue
        n = out[i] - (out[i] @ axis) * axis
        if np.linalg.norm(n) > 0.3:
            out[i] = n / np.linalg.norm(n)
    return out


#: A landmark of a midline bone this close to its sagittal plane (bone-frame Z, mm) is on the midline.
MIDLINE_TOLERANCE_MM = 5.0


def midline_directions(points: np.ndarray, normals: np.ndarray,
                       tolerance_mm: float = MIDLINE_TOLERANCE_MM) -> np.ndarray:
    """Surface normals at midline landmarks turned into the mid-sagittal plane (bone frame).

    A marker over a landmark on the body's midline (C7 and T10 over their
    spinous processes, CLAV and STRN on the sternum, SACR) sits on the
    midline: the placement manuals put it there, and by symmetry the
    surface normal there has no left-right part. On a mesh the normal at a
    ridge's tip (a spinous process is 5-8 mm wide) is ill-conditioned: the
    nearest triangles of a warped template leaned C7's normal 22-25 degrees
    to one side, and a ray along it met the skin 20-30 mm off the midline
    (phantom seeds 1 and 2). The left-right component (the bone frame's Z,
    ISB and OpenSim alike) is removed where the landmark lies within
    ``tolerance_mm`` of the sagittal plane; a normal that would vanish
    (pointing sideways) is left as it is.

    Parameters
    ----------
    points : ndarray (M, 3)
        Landmarks in a midline bone's frame (mm; Z to the right).
    normals : ndarray (M, 3)
        Unit outward surface normals there.
    tolerance_mm : float

    Returns
    -------
    ndarray (M, 3)
        Unit directions, bone frame.
    """
    out = np.array(normals, dtype=float, copy=True)
    on_mid = np.abs(np.asarray(points, float)[:, 2]) < tolerance_mm
    sag = out.copy()
    sag[:, 2] = 0.0
    norm = np.linalg.norm(sag, axis=1)
    turn = on_mid & (norm > 0.3)
    out[turn] = sag[turn] / norm[turn, None]
    return out


def place_markers(marker_set: MarkerSet, skeleton: Skeleton, names: list[str] | None = None
                  ) -> dict[str, np.ndarray]:
    """Place markers on a skeleton at its reference pose.

    Each marker sits at its landmark pushed ``offset_mm`` along the outward
    normal of the bone surface nearest to the landmark (averaged over equally
    near triangles, e.g. at a vertex; a bone without a mesh uses the direction
    from the bone origin). On the limbs' long bones (:data:`LIMB_LONG_BONES`)
    the push is away from the shaft axis instead (:func:`limb_side_directions`):
    limb markers sit on the side of the limb, never over the end of a bone; on
    a midline bone (no ``_r``/``_l`` suffix) a landmark on the sagittal plane is
    pushed within that plane (:func:`midline_directions`).
    A marker whose set gives a ``direction`` (:attr:`MarkerDef.direction`) is
    pushed that way: the placement manuals say "lateral thigh", and a
    direction in the bone frame is the same on every subject, while a
    surface normal at a landmark differs between two bones by tens of
    degrees (the lateral malleolus, the tibial shaft: 20-30 mm of marker
    placement difference between the phantom and its warped template). Markers given by ``location``
    (an OpenSim MarkerSet's) are points of the template's body, so they scale with it as OpenSim's
    ScaleTool scales them: the location times the bone's ``metadata["scale_factor"]``
    (:func:`bonecap.scaling.scale_skeleton`), then mapped to the world.

    Parameters
    ----------
    marker_set : MarkerSet
    skeleton : Skeleton
    names : list of str, optional
        The markers to place (default: every non-virtual marker).

    Returns
    -------
    dict of str -> ndarray (3,)
        Marker centres in the skeleton's world frame, mm.
    """
    check_marker_set(marker_set, skeleton)
    names = names if names is not None else [n for n, m in marker_set.markers.items() if not m.virtual]
    by_bone: dict[str, list[MarkerDef]] = {}
    for n in names:
        m = marker_set.markers[n]
        by_bone.setdefault(m.bone, []).append(m)
    out: dict[str, np.ndarray] = {}
    for bone_name, defs in by_bone.items():
        bone = skeleton.bones[bone_name]
        # unscaled, a location stayed where the template had it: the static fit then read every
        # scaled bone as too short again and the factors ran up to their limits (pelvis 1.45)
        scale = float(bone.metadata.get("scale_factor", 1.0))
        local = np.array([scale * np.asarray(m.location, float) if m.location is not None else
                          (bone.landmarks.get(m.landmark) if m.landmark in bone.landmarks
                           else bone.joint_centres[m.landmark]) for m in defs])
        offsets = np.array([0.0 if m.location is not None else m.offset_mm for m in defs])
        if bone.mesh is not None and len(bone.mesh.faces) and np.any(offsets):
            normals = _nearest_surface_normals(bone.mesh.vertices, bone.mesh.faces, local)
            if bone_name.startswith(LIMB_LONG_BONES):
                normals = limb_side_directions(bone.mesh.vertices, local, normals)
            elif not bone_name.endswith(("_r", "_l")):
                normals = midline_directions(local, normals)
        else:
            normals = local / np.maximum(np.linalg.norm(local, axis=1, keepdims=True), 1e-9)
        # a direction the set states (the placement manual's "lateral thigh") wins over any surface rule
        for i, m in enumerate(defs):
            if m.direction is not None and m.location is None:
                normals[i] = m.direction
        local = local + offsets[:, None] * normals
        world = local @ bone.bone_to_world[:3, :3].T + bone.bone_to_world[:3, 3]
        out.update({m.name: p for m, p in zip(defs, world)})
    return {n: out[n] for n in names}


#: Plug-in Gait's marker diameter (mm) when a trial does not store ``MARKERDIAMETER``: the 14 mm markers
#: of its manual, which the phantom wears too.
DEFAULT_MARKER_DIAMETER_MM = 14.0

#: A measured joint width outside this range (mm) is a typing error or another unit, not a knee.
_WIDTH_RANGE_MM = (20.0, 300.0)


def joint_centre_axis(skeleton: Skeleton, bone: str, joint: str) -> tuple[np.ndarray, np.ndarray]:
    """The centre and unit axis of ``joint`` near ``bone``, in the skeleton's world frame (reference pose).

    A joint's centre is stored on both bones it joins, its axis on the bone
    that turns about it (the knee's on the tibia): ``bone`` is searched
    first, then its parent, then its children.

    Raises
    ------
    ValueError
        No bone around ``bone`` has a centre and an axis for ``joint``.
    """
    if bone not in skeleton.bones:
        raise ValueError(f"no bone {bone!r} in the skeleton")
    parent = skeleton.bones[bone].parent
    near = [bone] + ([parent] if parent else []) + [n for n in skeleton.names if skeleton.bones[n].parent == bone]
    centre = axis = None
    for n in near:
        b = skeleton.bones[n]
        if centre is None and joint in b.joint_centres:
            centre = b.bone_to_world[:3, :3] @ np.asarray(b.joint_centres[joint], float) + b.bone_to_world[:3, 3]
        if axis is None and joint in b.joint_axes:
            axis = b.bone_to_world[:3, :3] @ np.asarray(b.joint_axes[joint], float)
    if centre is None or axis is None or not np.linalg.norm(axis) > 0:
        raise ValueError(f"no centre and axis of joint {joint!r} on {bone!r}, its parent or its children")
    return centre, axis / np.linalg.norm(axis)


def subject_parameter(parameters: dict[str, float], name: str) -> float | None:
    """``parameters[name]`` by Plug-in Gait's names: case-insensitive, ``L``/``R`` or ``Left``/``Right``.

    Nexus writes ``LKneeWidth`` into a trial's ``PROCESSING`` group and
    ``LeftKneeWidth`` into the subject's VSK; both name the same measurement.
    """
    up = {str(k).strip().upper(): v for k, v in parameters.items()}
    key = name.strip().upper()
    keys = [key]
    if key.startswith("LEFT") or key.startswith("RIGHT"):
        keys.append(key[0] + key[4 if key.startswith("LEFT") else 5:])
    elif key[:1] in ("L", "R"):
        keys.append(("LEFT" if key[0] == "L" else "RIGHT") + key[1:])
    for k in keys:
        if k in up and np.isfinite(up[k]):
            return float(up[k])
    return None


def joint_width_placement(marker_set: MarkerSet, skeleton: Skeleton, placed: dict[str, np.ndarray],
                          parameters: dict[str, float]) -> tuple[dict[str, np.ndarray], dict[str, dict]]:
    """Markers over the side of a joint set out at the depth the subject's measured joint width gives.

    A template's tissue depth over the knee or the malleoli is a typical
    adult's; a subject's is not (the Plug-in Gait subject of ``../shared``,
    85 kg: knee widths of 139-144 mm, where the template's skin gives about
    82). Gait labs measure these widths with callipers and store them with
    the trials (C3D ``PROCESSING``: ``LKneeWidth``, ``LAnkleWidth``,
    ``LElbowWidth``), and Plug-in Gait puts the joint centre half the width
    plus a marker radius in from the marker, along the joint's axis (the
    chord function; Davis et al. 1991). Here a marker whose set gives
    ``width: {parameter, joint}`` keeps its place around the joint's axis
    (where the template's landmark is, along and around the axis) and its
    distance from the joint centre *along* the axis becomes ``width / 2 +
    marker radius``, the marker diameter from ``MARKERDIAMETER`` or
    :data:`DEFAULT_MARKER_DIAMETER_MM`. Without the parameter the marker is
    left where it was.

    Parameters
    ----------
    marker_set : MarkerSet
    skeleton : Skeleton
        Where the markers were placed (world frame, reference pose).
    placed : dict of str -> ndarray (3,)
        Marker centres from :func:`place_markers` (world, mm).
    parameters : dict of str -> float
        The trial's ``subject_parameters`` (mm).

    Returns
    -------
    placed : dict of str -> ndarray (3,)
        The same markers, those with a measured width moved along the joint axis.
    report : dict
        Per moved marker: ``width_mm``, ``depth_mm`` (marker centre to joint
        centre along the axis) and ``moved_mm``.

    Raises
    ------
    ValueError
        A width or the marker diameter outside what a joint or a marker can be
        (the parameter named, with its value).

    References
    ----------
    .. [1] Davis RB, Ounpuu S, Tyburski D, Gage JR (1991). A gait analysis data collection and reduction
           technique. Hum Mov Sci 10(5):575-587.
    .. [2] Vicon Motion Systems. Plug-in Gait Reference Guide, "Lower body modeling: knee and ankle joint
           centres".
    """
    diameter = subject_parameter(parameters, "MarkerDiameter")
    if diameter is None:
        diameter = DEFAULT_MARKER_DIAMETER_MM
    if not 0 < diameter < 60:
        raise ValueError(f"marker diameter {diameter} mm (MARKERDIAMETER) is not a marker's")
    out = dict(placed)
    report: dict[str, dict] = {}
    for name, p in placed.items():
        m = marker_set.markers.get(name)
        if m is None or m.width is None:
            continue
        width = subject_parameter(parameters, m.width[0])
        if width is None or width == 0:          # Nexus stores 0 for a measurement never taken
            continue
        if not _WIDTH_RANGE_MM[0] <= width <= _WIDTH_RANGE_MM[1]:
            raise ValueError(f"{m.width[0]} = {width:g} mm is not a joint width (expected "
                             f"{_WIDTH_RANGE_MM[0]:g}-{_WIDTH_RANGE_MM[1]:g} mm)")
        centre, axis = joint_centre_axis(skeleton, m.bone, m.width[1])
        along = float((np.asarray(p, float) - centre) @ axis)
        if along < 0:                           # the axis's sign is the template's; the marker's side wins
            axis, along = -axis, -along
        depth = width / 2 + diameter / 2
        out[name] = np.asarray(p, float) + (depth - along) * axis
        report[name] = {"width_mm": round(width, 1), "depth_mm": round(depth, 1),
                        "moved_mm": round(depth - along, 1)}
    return out, report


def match_labels(marker_set: MarkerSet, labels: list[str]) -> dict[str, str]:
    """Map each marker of the set to the trial label that names it.

    Labels are compared without case and without spaces, first by the
    marker's own name, then by its aliases.

    Returns
    -------
    dict of str -> str
        ``{marker name: trial label}`` for the markers found.

    Raises
    ------
    BonecapError
        If two markers of the set claim the same trial label.
    """
    def key(s: str) -> str:
        return s.replace(" ", "").replace("_", "").lower()

    index = {key(lab): lab for lab in labels}
    found: dict[str, str] = {}
    for name, m in marker_set.markers.items():
        for cand in [name, *m.aliases]:
            if key(cand) in index:
                found[name] = index[key(cand)]
                break
    claimed: dict[str, str] = {}
    for name, lab in found.items():
        if lab in claimed:
            raise BonecapError(f"trial label {lab!r} matches both {claimed[lab]!r} and {name!r} "
                               f"of marker set {marker_set.name!r}")
        claimed[lab] = name
    return found
