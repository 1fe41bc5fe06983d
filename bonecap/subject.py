"""The subject folder: what ``bonecap build-subject`` writes and ``bonecap animate`` reads.

Mapping between the files and our objects
-----------------------------------------
``SUBJECT_DIR/subject.yaml`` holds everything but the surfaces:

- ``world``: the name and a description of the frame every position in the
  file (and every mesh) is given in: ``lps`` for a subject built from MRI (the
  DICOM patient frame, mm), ``model`` for a template scaled to a static trial
  (X anterior, Y up, Z right, mm; the template's own frame).
- ``bones``: per bone, in parent-before-child order: ``parent``,
  ``bone_to_world`` (4x4, the bone's ISB frame in ``world`` at the reference
  pose), ``joint_centres``, ``joint_axes`` and ``landmarks`` **in world**
  (mm; easier to read and to edit than bone-frame numbers), ``mesh`` and
  ``inner_mesh`` (paths relative to the folder) and ``metadata``.
- ``markers``: per marker, ``bone`` it is bound to, ``position_world`` (mm, at
  the reference pose), ``source`` (``placed``: on the skin over its landmark;
  ``capsule``: an MRI-visible capsule; ``static``: measured in the static
  trial and carried into the reference pose; ``override``: from the user's
  YAML), and ``weight``.
- ``forearm``: the pronation model per side (see
  :mod:`bonecap.motion.forearm`), or absent for the paper's defaults (a side
  without one takes the other side's: :func:`bonecap.animate.forearm_models`).
  Its ``radius_axis_ulna_mm``, the radius's axis as the forearm stacks showed
  it, is the one entry of the file **not in world**: it is in the ulna's bone
  frame (the model carries it with the solved ulna).
- ``provenance``: the command, inputs, template, marker set and parameters.

``SUBJECT_DIR/meshes/<bone>.ply`` (and ``<bone>_inner.ply``, ``skin.ply``)
hold the surfaces **in world** at the reference pose, so any viewer shows the
whole skeleton in place. On reading, a bone's mesh is moved into its own frame
(``Bone.mesh`` is bone-frame by the data model's rule).

Files are written to temporary names and renamed, so a failed run never
leaves a half-written subject.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from bonecap.errors import DataError, FormatError, InputError
from bonecap.io import load_yaml
from bonecap.io.atomic import atomic_path
from bonecap.io.mesh import read_mesh, write_mesh
from bonecap.model import Bone, Mesh, Skeleton

__all__ = ["MarkerBinding", "Subject", "write_subject", "read_subject", "SUBJECT_FILE", "WORLD_FRAMES"]

SUBJECT_FILE = "subject.yaml"
FORMAT_VERSION = 1

WORLD_FRAMES = {
    "lps": "DICOM patient frame of the MRI: +x left, +y posterior, +z superior (mm)",
    "model": "template frame: +x anterior, +y superior, +z right (mm)",
}


@dataclass
class MarkerBinding:
    """A marker bound to a bone.

    Attributes
    ----------
    name : str
    bone : str
    local : ndarray (3,)
        Position in the bone's own frame (mm).
    source : str
        ``placed``, ``capsule``, ``static`` or ``override``.
    weight : float
        Relative weight in the least-squares solver.
    """

    name: str
    bone: str
    local: np.ndarray
    source: str = "placed"
    weight: float = 1.0

    def __post_init__(self):
        self.local = np.asarray(self.local, dtype=float).reshape(3)


@dataclass
class Subject:
    """A personal skeleton with its bound markers, as stored in a subject folder.

    Attributes
    ----------
    skeleton : Skeleton
        Bones at the reference pose; ``skeleton.world`` names the frame.
    markers : dict of str -> MarkerBinding
    skin : Mesh or None
        Skin surface in world.
    forearm : dict
        Per side (``"r"``, ``"l"``) the forearm model as a plain dict (see
        :mod:`bonecap.motion.forearm`); empty for the paper's defaults.
    marker_set : str
        Name of the marker set the markers came from.
    provenance : dict
    static : dict
        The static trial the markers were bound in, when there was one:
        ``trial`` (path), ``lab_up``, ``markers_lab`` (name -> (3,) mm, the
        static positions) and ``bone_to_lab`` (bone -> 4x4, the solved static
        pose). The paper solver measures its twists and joint-centre offsets
        against it.
    """

    skeleton: Skeleton
    markers: dict[str, MarkerBinding] = field(default_factory=dict)
    skin: Mesh | None = None
    forearm: dict[str, Any] = field(default_factory=dict)
    marker_set: str = ""
    provenance: dict[str, Any] = field(default_factory=dict)
    static: dict[str, Any] = field(default_factory=dict)

    def follows_rhythm(self) -> bool:
        """Whether the solvers turn this subject's scapulae on their clavicles with the arms
        (scapulohumeral rhythm, :func:`bonecap.motion.lsq.rhythm_turns`).

        The rhythm counts from the reference pose: the subject's own girdle at its own arm's
        elevation, as an MRI measured them (``provenance["girdle_rhythm"]``, True from MRI).
        A template scaled to a static trial (no MRI) has the template's girdle and arms at its
        reference, not the subject's: counted from there the rhythm put the no-MRI phantoms'
        shoulder centres 4-5 mm further off and the real Plug-in Gait walk's upper-arm markers
        3 mm (docs/benchmarks.md), so it is off there. A subject folder without the key
        follows its build mode.
        """
        return bool(self.provenance.get("girdle_rhythm", self.provenance.get("mode") != "static"))

    def marker_arrays(self, names: list[str] | None = None) -> tuple[list[str], list[str], np.ndarray]:
        """``(names, bones, local (M, 3))`` for the solvers, in ``names`` order."""
        names = list(self.markers) if names is None else list(names)
        missing = [n for n in names if n not in self.markers]
        if missing:
            raise ValueError(f"markers not bound in the subject: {missing}")
        return (names, [self.markers[n].bone for n in names],
                np.array([self.markers[n].local for n in names]).reshape(-1, 3))

    def marker_world(self, name: str) -> np.ndarray:
        """A marker's position in world at the reference pose (mm)."""
        m = self.markers[name]
        T = self.skeleton.bones[m.bone].bone_to_world
        return T[:3, :3] @ m.local + T[:3, 3]


def _to_world(T: np.ndarray, p: np.ndarray) -> list[float]:
    return [round(float(v), 4) for v in T[:3, :3] @ p + T[:3, 3]]


def _to_local(T: np.ndarray, p) -> np.ndarray:
    p = np.asarray(p, dtype=float).reshape(3)
    return T[:3, :3].T @ (p - T[:3, 3])


def _safe_name(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name)


def write_subject(subject: Subject, out_dir: str | os.PathLike, *, extra: dict[str, Any] | None = None) -> Path:
    """Write ``subject.yaml`` and ``meshes/*.ply`` into ``out_dir``.

    Parameters
    ----------
    subject : Subject
    out_dir : path-like
        Created if needed. Existing files of the same names are replaced.
    extra : dict, optional
        More top-level entries for ``subject.yaml`` (e.g. a report summary).

    Returns
    -------
    Path
        The ``subject.yaml`` written.
    """
    out_dir = Path(out_dir)
    mesh_dir = out_dir / "meshes"
    mesh_dir.mkdir(parents=True, exist_ok=True)
    sk = subject.skeleton
    bones: dict[str, Any] = {}
    for name, b in sk.bones.items():
        T = b.bone_to_world
        entry: dict[str, Any] = {
            "parent": b.parent,
            "bone_to_world": [[round(float(v), 8) for v in row] for row in T],
            "joint_centres": {k: _to_world(T, v) for k, v in b.joint_centres.items()},
            "joint_axes": {k: [round(float(x), 8) for x in T[:3, :3] @ v] for k, v in b.joint_axes.items()},
            "landmarks": {k: _to_world(T, v) for k, v in b.landmarks.items()},
        }
        for key, mesh in (("mesh", b.mesh), ("inner_mesh", b.inner_mesh)):
            if mesh is not None:
                rel = f"meshes/{_safe_name(name)}{'_inner' if key == 'inner_mesh' else ''}.ply"
                write_mesh(mesh.transformed(T, sk.world), out_dir / rel)
                entry[key] = rel
        if b.metadata:
            entry["metadata"] = _plain(b.metadata)
        bones[name] = entry
    doc: dict[str, Any] = {
        "format": "bonecap subject",
        "version": FORMAT_VERSION,
        "world": {"name": sk.world, "description": WORLD_FRAMES.get(sk.world, "")},
        "units": "mm",
        "marker_set": subject.marker_set,
        "bones": bones,
        "markers": {
            n: {"bone": m.bone,
                "position_world": _to_world(sk.bones[m.bone].bone_to_world, m.local),
                "source": m.source, "weight": float(m.weight)}
            for n, m in subject.markers.items()
        },
    }
    if subject.skin is not None:
        write_mesh(subject.skin, mesh_dir / "skin.ply")
        doc["skin"] = "meshes/skin.ply"
    if subject.forearm:
        doc["forearm"] = _plain(subject.forearm)
    if subject.static:
        doc["static"] = _plain(subject.static)
    doc["provenance"] = _plain(subject.provenance)
    if sk.metadata:
        doc["skeleton_metadata"] = _plain(sk.metadata)
    if extra:
        doc.update(_plain(extra))
    path = out_dir / SUBJECT_FILE
    with atomic_path(path) as tmp:
        tmp.write_text(yaml.safe_dump(doc, sort_keys=False, width=120))
    return path


def _plain(obj: Any) -> Any:
    """Numpy values to plain Python for YAML."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _plain(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    import dataclasses

    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        # e.g. the OpenSim markers a template keeps in its metadata
        return _plain(dataclasses.asdict(obj))
    if obj is None or isinstance(obj, (str, int, float, bool)):
        return obj
    return str(obj)


def read_subject(subject_dir: str | os.PathLike, *, load_meshes: bool = True) -> Subject:
    """Read a subject folder written by :func:`write_subject`.

    Raises
    ------
    InputError
        If the folder or its ``subject.yaml`` is missing.
    FormatError
        If ``subject.yaml`` is not a bonecap subject or is malformed.
    """
    subject_dir = Path(subject_dir)
    path = subject_dir / SUBJECT_FILE if subject_dir.is_dir() else subject_dir
    if not path.is_file():
        raise InputError("not a subject folder (no subject.yaml): run `bonecap build-subject` first", subject_dir)
    base = path.parent
    try:
        doc = load_yaml(path.read_text())
    except yaml.YAMLError as exc:
        raise FormatError(f"not valid YAML ({str(exc).splitlines()[0]})", path) from None
    if not isinstance(doc, dict) or doc.get("format") != "bonecap subject":
        raise FormatError("not a bonecap subject file", path)
    world = doc.get("world", {}).get("name", "model")
    bones: dict[str, Bone] = {}
    try:
        for name, e in doc["bones"].items():
            T = np.asarray(e["bone_to_world"], dtype=float)
            mesh = inner = None
            if load_meshes and e.get("mesh"):
                mesh = read_mesh(base / e["mesh"]).transformed(np.linalg.inv(T), name)
            if load_meshes and e.get("inner_mesh"):
                inner = read_mesh(base / e["inner_mesh"]).transformed(np.linalg.inv(T), name)
            bones[name] = Bone(
                name=name, parent=e.get("parent"), mesh=mesh, inner_mesh=inner, bone_to_world=T,
                joint_centres={k: _to_local(T, v) for k, v in (e.get("joint_centres") or {}).items()},
                joint_axes={k: T[:3, :3].T @ np.asarray(v, float) for k, v in (e.get("joint_axes") or {}).items()},
                landmarks={k: _to_local(T, v) for k, v in (e.get("landmarks") or {}).items()},
                metadata=e.get("metadata") or {},
            )
        skeleton = Skeleton(bones=bones, world=world, metadata=doc.get("skeleton_metadata") or {})
        markers = {}
        for n, m in (doc.get("markers") or {}).items():
            if m["bone"] not in bones:
                raise DataError(f"marker {n!r} is bound to bone {m['bone']!r}, which the subject lacks", path)
            T = bones[m["bone"]].bone_to_world
            markers[n] = MarkerBinding(n, m["bone"], _to_local(T, m["position_world"]),
                                       m.get("source", "placed"), float(m.get("weight", 1.0)))
    except (KeyError, TypeError, ValueError) as exc:
        raise FormatError(f"malformed subject file ({type(exc).__name__}: {exc})", path) from None
    skin = read_mesh(base / doc["skin"]) if load_meshes and doc.get("skin") else None
    static = doc.get("static") or {}
    if static:
        static = {**static,
                  "markers_lab": {k: np.asarray(v, float) for k, v in (static.get("markers_lab") or {}).items()},
                  "bone_to_lab": {k: np.asarray(v, float) for k, v in (static.get("bone_to_lab") or {}).items()}}
    return Subject(skeleton=skeleton, markers=markers, skin=skin, forearm=doc.get("forearm") or {},
                   marker_set=doc.get("marker_set", ""), provenance=doc.get("provenance") or {}, static=static)
