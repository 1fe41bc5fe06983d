"""Bone meshes and their motion -> binary glTF 2.0 (``.glb``), and a summary reader.

trimesh writes static glTF scenes but no animation, so this is a small writer
of its own, built on numpy and :mod:`json`. It writes what a viewer (three.js,
Blender, Windows 3D Viewer, https://gltf-viewer.donmccurdy.com) needs to play a
trial, and passes the Khronos glTF validator without errors or warnings.

How our objects map onto glTF
-----------------------------
**Units and up axis.** glTF is defined in metres with +Y up; bonecap works in
millimetres in a Z-up lab. Rather than converting every number, the scene has
one static *root node* (named ``"lab"``) that carries the change of frame:

- ``scale`` = 0.001 (mm -> m), and
- ``rotation`` = -90 deg about X (xyzw ``[-sqrt(1/2), 0, 0, sqrt(1/2)]``), which
  takes the lab's (x, y, z) to glTF's (x, z, -y): lab +Z up becomes +Y up, lab
  +Y becomes -Z. With ``lab_up="y"`` the rotation is the identity.

Below the root, everything is **in our units and our lab frame**: vertex
positions are millimetres in each bone's own frame, and each bone node's
translation is the millimetre translation of its ``bone_to_lab`` transform. A
reader of the file gets back bonecap's numbers unchanged, and a viewer composes
root x bone as usual and shows metres, Y up. A lab point ``(x, y, z)`` mm is
therefore at ``(x, z, -y) / 1000`` in the viewer's world.

**Node hierarchy.** ``scene -> "lab" root -> one child node per bone``, all
bones siblings. A Motion holds ``bone_to_lab`` (world) poses, not poses
relative to a parent bone, so keeping them flat needs no inversion and no
error accumulates down a chain. Each bone node is named after the bone and
references its mesh (``None`` for a bone without a mesh: the node still moves).

**Meshes.** One glTF mesh per bone with a single triangle primitive:

- ``POSITION``: FLOAT VEC3, millimetres, with the ``min``/``max`` the spec requires;
- ``NORMAL``: FLOAT VEC3 per vertex, the area-weighted mean of the adjacent face
  normals, normalised. glTF requires unit normals; a vertex that touches no
  triangle of any area gets the direction from the mesh centroid instead (so
  no normal is ever zero). Without normals three.js draws the bones black.
- indices: UNSIGNED_SHORT below 65 535 vertices, UNSIGNED_INT above (65 535
  itself is the reserved primitive-restart value). Triangles that repeat a
  vertex index are dropped (they cover no area; the validator reports them).
- a PBR metallic-roughness material: bone-coloured (``colors`` overrides),
  non-metallic, fairly rough, and double-sided because real bone meshes are
  not all closed or consistently wound.

**Buffers.** One binary buffer (the GLB ``BIN`` chunk). Every buffer view
starts on a 4-byte boundary; vertex and index views declare their ``target``.
Animation outputs of one kind (all rotations, all translations) share one
view, one accessor per bone at its own offset.

**Animation.** One animation, one sampler per bone and path, sharing a single
*input* accessor of times (FLOAT SCALAR, with ``min``/``max``):

- times are ``motion.times - motion.times[0]``, so the first keyframe is at 0
  (float32 keeps ~1 ms resolution near 3 h, far better near 0). They must
  increase strictly, also after rounding to float32, or :class:`ValueError`;
- ``translation``: LINEAR, FLOAT VEC3, millimetres (the root scales them);
- ``rotation``: LINEAR, FLOAT VEC4 unit quaternions in glTF's order **x, y, z, w**
  (scalar last, which is also scipy's). ``q`` and ``-q`` are the same rotation
  but interpolate the long way round between frames of opposite sign, so the
  sign is chosen frame to frame to keep every consecutive dot product >= 0
  (and the first frame has w >= 0);
- ``scale``: only for bones with invalid frames, see below.

Rotation and translation come from each rigid ``bone_to_lab`` with
:class:`scipy.spatial.transform.Rotation`, vectorised over frames and bones.
A transform that is not rigid (scaled, sheared or mirrored rotation block, or a
bottom row other than ``0 0 0 1``) raises :class:`ValueError`: glTF TRS could
not represent it and an animated node may not use ``matrix``.

**Invalid frames** (``motion.valid`` False or a NaN in the transform): glTF
cannot hold NaN, so the bone is *hidden* there. Its translation and rotation
hold the last valid pose (before its first valid frame: that first valid pose;
a bone never valid stays at the identity), and a ``scale`` channel with
**STEP** interpolation is 1 on valid frames and 0 on invalid ones. STEP makes
visibility exact per frame: the bone neither shrinks gradually into a gap nor
drifts while hidden, and it reappears at its first valid frame. Bones that
are valid throughout get no scale channel. The static TRS of every bone node
is its pose at the first frame (so viewers that ignore animation show frame 0).

Reading
-------
:func:`summarize_gltf` parses a ``.glb`` (or ``.gltf`` JSON) with its own
few-line GLB reader (no third-party dependency) and returns counts for
``bonecap inspect``.
"""

from __future__ import annotations

import json
import math
import os
import struct
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from bonecap.errors import FormatError, InputError
from bonecap.io.atomic import atomic_path
from bonecap.model import Mesh, Motion

__all__ = ["write_animated_glb", "write_static_glb", "summarize_gltf", "BONE_COLOR"]

#: Default base colour of bone materials, linear RGBA (an ivory off-white).
BONE_COLOR = (0.89, 0.85, 0.76, 1.0)

# glTF enumerations used here (spec section 5, "accessor.componentType" etc.).
_FLOAT = 5126
_UNSIGNED_SHORT = 5123
_UNSIGNED_INT = 5125
_ARRAY_BUFFER = 34962
_ELEMENT_ARRAY_BUFFER = 34963
_TRIANGLES = 4

_GLB_MAGIC = b"glTF"
_CHUNK_JSON = 0x4E4F534A  # "JSON" little-endian
_CHUNK_BIN = 0x004E4942  # "BIN\0"

# Lab (x, y, z) -> glTF (x, z, -y): -90 degrees about +X, as xyzw.
_ROOT_ROTATION = {"z": [-math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5)], "y": [0.0, 0.0, 0.0, 1.0]}

# Largest entry of |R - R(q)| (the rotation block against the rotation of its
# quaternion) and of |bottom row - (0 0 0 1)| accepted as rigid. Transforms
# built in float64 are ~1e-15 off; 1e-4 still admits float32 input and
# rejects any real scaling (a 1 % scale is 0.01 off).
_RIGID_TOL = 1e-4


# --------------------------------------------------------------------------- #
# Public writers
# --------------------------------------------------------------------------- #

def write_animated_glb(
    path: str | os.PathLike,
    meshes: Mapping[str, Mesh],
    motion: Motion,
    *,
    lab_up: str = "z",
    colors: Mapping[str, Sequence[float]] | Sequence[float] | None = None,
) -> None:
    """Write bone meshes driven by a :class:`~bonecap.model.Motion` to a ``.glb``.

    Parameters
    ----------
    path : path-like
        Target file (written atomically; a ``.glb`` extension is expected but
        not enforced).
    meshes : mapping of str -> Mesh
        Each bone's surface in its **own bone frame**, millimetres. Keys must
        be bones of ``motion``; a bone of ``motion`` without a mesh becomes an
        animated node without geometry. ``Mesh.frame`` must be ``""`` or the
        bone's name (a mesh in another frame is almost surely a mistake).
    motion : Motion
        ``bone_to_lab`` transforms in mm, ``times`` in seconds, ``valid`` flags.
    lab_up : {"z", "y"}
        Up axis of the lab; the root node turns it to glTF's +Y.
    colors : mapping of str -> RGB(A), or one RGB(A), optional
        Linear base colours in 0..1, per bone or for all; default
        :data:`BONE_COLOR`.

    Raises
    ------
    ValueError
        Times not strictly increasing (also after float32 rounding) or not
        finite; no frames; a valid transform that is not rigid; meshes for
        bones not in the motion; a mesh in a foreign frame; a bad colour or
        ``lab_up``.
    OSError
        The file could not be written (nothing is left behind).

    Notes
    -----
    Invalid frames hide the bone with a STEP scale channel (0) while holding
    its last valid pose; see the module docstring.
    """
    names = list(motion.bones)
    if not names:
        raise ValueError("nothing to write: the motion has no bones")
    times = np.asarray(motion.times, dtype=float)
    if times.ndim != 1 or len(times) == 0:
        raise ValueError("motion has no frames")
    if not np.all(np.isfinite(times)):
        raise ValueError("motion.times contains NaN or infinite values")
    if len(times) > 1 and not np.all(np.diff(times) > 0):
        k = int(np.argmin(np.diff(times) > 0))
        raise ValueError(f"motion.times must increase strictly (frame {k + 1}: "
                         f"{times[k + 1]:.9g} s after {times[k]:.9g} s)")
    times = times - times[0]  # keyframes start at 0, where float32 is finest
    times32 = times.astype(np.float32)
    if len(times) > 1 and not np.all(np.diff(times32) > 0):
        raise ValueError("motion.times are too close to stay strictly increasing in float32 "
                         "(the precision of glTF keyframe times)")

    transforms = np.asarray(motion.transforms, dtype=float)
    F, B = len(times), len(names)
    if transforms.shape != (F, B, 4, 4):
        raise ValueError(f"motion.transforms must have shape ({F}, {B}, 4, 4), got {transforms.shape}")
    valid = np.isfinite(transforms).all(axis=(2, 3))
    if motion.valid is not None:
        valid &= np.asarray(motion.valid, dtype=bool)

    quats, trans = _rigid_to_trs(_hold_last_valid(transforms, valid), names)

    builder = _GlbBuilder()
    gltf = _scene(builder, names, meshes, quats[0], trans[0], valid[0], lab_up, colors)
    gltf["animations"] = [_animation(builder, Path(path).stem or "motion", times32, quats, trans, valid)]
    gltf["asset"]["extras"]["first_frame"] = int(motion.first_frame)
    gltf["asset"]["extras"]["time_offset_s"] = float(motion.times[0])
    _write_glb(path, gltf, builder)


def write_static_glb(
    path: str | os.PathLike,
    meshes: Mapping[str, Mesh],
    transforms: Mapping[str, np.ndarray],
    *,
    lab_up: str = "z",
    colors: Mapping[str, Sequence[float]] | Sequence[float] | None = None,
) -> None:
    """Write bone meshes at one pose (a skeleton, or a single mesh) to a ``.glb``.

    Same scene as :func:`write_animated_glb` without the animation: a root node
    (mm -> m, lab up -> +Y) and one child node per entry of ``transforms``.

    Parameters
    ----------
    path : path-like
        Target file, written atomically.
    meshes : mapping of str -> Mesh
        Surfaces in each bone's own frame (mm); keys must be in ``transforms``.
    transforms : mapping of str -> ndarray (4, 4)
        ``bone_to_lab`` of each node, rigid, mm. Order gives the node order. A
        transform with NaN hides its node (scale 0 at the identity).
    lab_up : {"z", "y"}
        Up axis of the lab frame.
    colors : mapping of str -> RGB(A), or one RGB(A), optional
        As in :func:`write_animated_glb`.

    Raises
    ------
    ValueError
        A transform is not 4x4 or not rigid; a mesh has no transform or is in
        a foreign frame; a bad colour or ``lab_up``.
    OSError
        The file could not be written (nothing is left behind).
    """
    names = list(transforms)
    if not names:
        raise ValueError("nothing to write: no transforms")
    stack = np.empty((1, len(names), 4, 4))
    for b, name in enumerate(names):
        T = np.asarray(transforms[name], dtype=float)
        if T.shape != (4, 4):
            raise ValueError(f"transform of {name!r} must be 4x4, got shape {T.shape}")
        stack[0, b] = T
    valid = np.isfinite(stack).all(axis=(2, 3))
    quats, trans = _rigid_to_trs(_hold_last_valid(stack, valid), names)
    builder = _GlbBuilder()
    gltf = _scene(builder, names, meshes, quats[0], trans[0], valid[0], lab_up, colors)
    _write_glb(path, gltf, builder)


# --------------------------------------------------------------------------- #
# Reading
# --------------------------------------------------------------------------- #

def summarize_gltf(path: str | os.PathLike) -> dict[str, Any]:
    """Describe a glTF file for ``bonecap inspect``.

    Parameters
    ----------
    path : path-like
        A binary ``.glb`` or a JSON ``.gltf`` (the content decides, not the
        extension). External buffers are not opened: only the JSON is read.

    Returns
    -------
    dict
        JSON-able: ``format`` ("gltf"), ``path``, ``container`` ("glb" or "json"),
        ``version``, ``generator``, ``nodes`` (count), ``node_names``,
        ``meshes`` (count), ``triangles`` (over all mesh primitives, each mesh
        counted once however many nodes use it), ``animations`` (count),
        ``animation_channels`` (list, per animation), ``duration`` (seconds,
        from the input accessors' min/max over all animations; 0 without
        animation) and ``frames`` (keyframes of the first sampler of the first
        animation; 0 without animation).

    Raises
    ------
    InputError
        The file does not exist.
    FormatError
        Not GLB/glTF JSON, truncated, or the JSON lacks glTF structure.
    """
    gltf = _read_gltf_json(path)
    try:
        accessors = gltf.get("accessors", [])
        nodes = gltf.get("nodes", [])
        meshes = gltf.get("meshes", [])
        animations = gltf.get("animations", [])
        triangles = 0
        for mesh in meshes:
            for prim in mesh.get("primitives", []):
                mode = prim.get("mode", _TRIANGLES)
                if "indices" in prim:
                    n = accessors[prim["indices"]]["count"]
                else:
                    n = accessors[prim["attributes"]["POSITION"]]["count"]
                triangles += {4: n // 3, 5: max(n - 2, 0), 6: max(n - 2, 0)}.get(mode, 0)
        t_min, t_max = math.inf, -math.inf
        for anim in animations:
            for sampler in anim.get("samplers", []):
                acc = accessors[sampler["input"]]
                t_min = min(t_min, float(acc.get("min", [0.0])[0]))
                t_max = max(t_max, float(acc.get("max", [0.0])[0]))
        frames = 0
        if animations and animations[0].get("samplers"):
            frames = int(accessors[animations[0]["samplers"][0]["input"]]["count"])
        asset = gltf["asset"]
        return {
            "format": "gltf",
            "path": os.fspath(path),
            "container": gltf.pop("__container__"),
            "version": str(asset.get("version", "")),
            "generator": str(asset.get("generator", "")),
            "nodes": len(nodes),
            "node_names": [str(n.get("name", "")) for n in nodes],
            "meshes": len(meshes),
            "triangles": int(triangles),
            "animations": len(animations),
            "animation_channels": [len(a.get("channels", [])) for a in animations],
            # Rounded to the microsecond: float32 times print as 0.49000000953674316.
            "duration": round(t_max - t_min, 6) if t_max >= t_min else 0.0,
            "frames": frames,
        }
    except (KeyError, IndexError, TypeError, AttributeError, ValueError) as exc:
        raise FormatError(f"malformed glTF JSON ({type(exc).__name__}: {exc})", path) from None


def _read_gltf_json(path: str | os.PathLike) -> dict[str, Any]:
    """The JSON document of a GLB or glTF file, with ``__container__`` added."""
    path = Path(path)
    if not path.is_file():
        raise InputError("no such file" if not path.exists() else "not a file", path)
    data = path.read_bytes()
    if data[:4] == _GLB_MAGIC:
        # GLB: 12-byte header (magic, version, total length), then chunks of
        # (length, type, payload); the first chunk must be the JSON.
        if len(data) < 20:
            raise FormatError("truncated GLB header", path)
        _, version, length = struct.unpack_from("<4sII", data, 0)
        if version != 2:
            raise FormatError(f"GLB version {version} (only 2 is supported)", path)
        if length > len(data):
            raise FormatError(f"truncated GLB: header says {length} bytes, file has {len(data)}", path)
        chunk_len, chunk_type = struct.unpack_from("<II", data, 12)
        if chunk_type != _CHUNK_JSON:
            raise FormatError("first GLB chunk is not JSON", path)
        if 20 + chunk_len > length:
            raise FormatError("truncated GLB JSON chunk", path)
        text, container = data[20:20 + chunk_len], "glb"
    elif data.lstrip()[:1] == b"{":
        text, container = data, "json"
    else:
        raise FormatError("not a glTF file (neither GLB magic nor JSON)", path)
    try:
        gltf = json.loads(text.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise FormatError(f"invalid glTF JSON: {exc}", path) from None
    if not isinstance(gltf, dict) or not isinstance(gltf.get("asset"), dict):
        raise FormatError("JSON has no glTF 'asset' object", path)
    gltf["__container__"] = container
    return gltf


# --------------------------------------------------------------------------- #
# Pose arithmetic (vectorised over frames and bones)
# --------------------------------------------------------------------------- #

def _hold_last_valid(T: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Replace invalid poses of ``T (F, B, 4, 4)`` by the last valid one.

    Before a bone's first valid frame its first valid pose is used; a bone
    never valid gets the identity. No Python loop over frames.
    """
    if valid.all():
        return T  # the common case: no copy of a (F, B, 4, 4) array
    F, B = valid.shape
    frame = np.arange(F)[:, None]
    last = np.maximum.accumulate(np.where(valid, frame, -1), axis=0)
    first = np.argmax(valid, axis=0)  # 0 for a bone never valid (fixed below)
    src = np.where(last < 0, first[None, :], last)
    out = T[src, np.arange(B)[None, :]]
    never = ~valid.any(axis=0)
    out[:, never] = np.eye(4)
    return out


def _rigid_to_trs(T: np.ndarray, names: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """Unit xyzw quaternions ``(F, B, 4)`` and translations ``(F, B, 3)`` of ``T (F, B, 4, 4)``.

    Quaternion signs are made continuous along axis 0 (frames): each one is
    flipped when its dot product with the previous (already chosen) one would
    be negative, and the first frame has w >= 0.

    Raises ValueError naming the first (frame, bone) whose transform is not
    rigid. The test is a round trip: the rotation block is converted to a
    quaternion and back, and must come back unchanged. Any rotation matrix
    does (to rounding); a scaled, sheared or mirrored block cannot, since no
    rotation is closer to it than its distance from the rotation group. This
    costs two cheap conversions instead of a Gram matrix and a determinant per
    transform (4x faster at 300 000 transforms).
    """
    from scipy.spatial.transform import Rotation

    F, B = T.shape[:2]
    R = T[..., :3, :3].reshape(-1, 3, 3)
    try:
        # The round trip below checks validity, so skip scipy's own
        # orthogonalisation (10x faster; ``assume_valid`` is scipy >= 1.16).
        rot = Rotation.from_matrix(R, assume_valid=True)
    except TypeError:
        rot = Rotation.from_matrix(R)
    q = rot.as_quat().reshape(F, B, 4)
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    back = Rotation.from_quat(q.reshape(-1, 4)).as_matrix().reshape(F, B, 3, 3)
    off = np.abs(back - T[..., :3, :3]).max(axis=(-2, -1))
    bottom = np.abs(T[..., 3, :] - [0.0, 0.0, 0.0, 1.0]).max(axis=-1)
    bad = ~((off <= _RIGID_TOL) & (bottom <= _RIGID_TOL))  # also catches NaN
    if bad.any():
        f, b = (int(i) for i in np.argwhere(bad)[0])
        Rfb = T[f, b, :3, :3]
        what = (f"bottom row {T[f, b, 3].tolist()}" if not bottom[f, b] <= _RIGID_TOL
                else f"det = {np.linalg.det(Rfb):.6g}, "
                     f"max |R^T R - I| = {np.abs(Rfb.T @ Rfb - np.eye(3)).max():.3g}")
        raise ValueError(f"transform of bone {names[b]!r} at frame {f} is not rigid: {what} "
                         f"({int(bad.sum())} such transforms)")

    # Sign of frame k relative to frame k-1 of the *raw* sequence; the running
    # product of those signs makes every chosen neighbour pair agree.
    step = np.where(np.einsum("fbi,fbi->fb", q[1:], q[:-1]) < 0, -1.0, 1.0)
    sign = np.cumprod(np.concatenate([np.where(q[:1, :, 3] < 0, -1.0, 1.0), step]), axis=0)
    q *= sign[..., None]
    return q, T[..., :3, 3].copy()


# --------------------------------------------------------------------------- #
# Scene assembly
# --------------------------------------------------------------------------- #

class _GlbBuilder:
    """Accumulates the binary buffer, buffer views and accessors of one GLB."""

    def __init__(self) -> None:
        self.blobs: list[bytes] = []
        self.size = 0
        self.buffer_views: list[dict[str, Any]] = []
        self.accessors: list[dict[str, Any]] = []

    def view(self, array: np.ndarray, target: int | None = None) -> int:
        """Append ``array``'s bytes as a new buffer view (4-byte aligned); its index."""
        data = np.ascontiguousarray(array).tobytes()
        view = {"buffer": 0, "byteOffset": self.size, "byteLength": len(data)}
        if target is not None:
            view["target"] = target
        self.blobs.append(data)
        pad = -len(data) % 4  # the next view must start on a 4-byte boundary
        if pad:
            self.blobs.append(b"\0" * pad)
        self.size += len(data) + pad
        self.buffer_views.append(view)
        return len(self.buffer_views) - 1

    def accessor(self, view: int, array: np.ndarray, byte_offset: int = 0, bounds: bool = False) -> int:
        """Describe ``array`` (already stored in ``view`` at ``byte_offset``); its index.

        ``array`` is float32 (SCALAR/VEC3/VEC4 from its last axis) or
        uint16/uint32 indices. ``bounds`` adds the exact per-component min/max.
        """
        comp = {np.dtype(np.float32): _FLOAT, np.dtype(np.uint16): _UNSIGNED_SHORT,
                np.dtype(np.uint32): _UNSIGNED_INT}[array.dtype]
        width = 1 if array.ndim == 1 else array.shape[-1]
        acc = {"bufferView": view, "componentType": comp, "count": int(array.shape[0]),
               "type": {1: "SCALAR", 3: "VEC3", 4: "VEC4"}[width]}
        if byte_offset:
            acc["byteOffset"] = int(byte_offset)
        if bounds:
            flat = array.reshape(len(array), width)
            # float32 -> Python float is exact, so these equal the stored data
            # bit for bit (the validator compares them exactly).
            acc["min"] = [_num(v) for v in flat.min(axis=0)]
            acc["max"] = [_num(v) for v in flat.max(axis=0)]
        self.accessors.append(acc)
        return len(self.accessors) - 1

    def add(self, array: np.ndarray, target: int | None = None, bounds: bool = False) -> int:
        """Store ``array`` in its own view and return the accessor index."""
        return self.accessor(self.view(array, target), array, bounds=bounds)


def _num(v: Any) -> int | float:
    return int(v) if isinstance(v, np.integer) else float(v)


def _scene(builder: _GlbBuilder, names: list[str], meshes: Mapping[str, Mesh],
           quat0: np.ndarray, trans0: np.ndarray, visible0: np.ndarray,
           lab_up: str, colors) -> dict[str, Any]:
    """The glTF document for root + bone nodes with their meshes and materials."""
    if lab_up not in _ROOT_ROTATION:
        raise ValueError(f"lab_up must be 'z' or 'y', got {lab_up!r}")
    unknown = [k for k in meshes if k not in names]
    if unknown:
        raise ValueError(f"meshes given for bones that have no pose: {', '.join(map(repr, unknown))}")

    from bonecap import __version__

    materials: list[dict[str, Any]] = []
    material_of: dict[tuple[float, ...], int] = {}
    gltf_meshes: list[dict[str, Any]] = []
    nodes: list[dict[str, Any]] = [{
        "name": "lab",
        "rotation": _ROOT_ROTATION[lab_up],
        "scale": [0.001, 0.001, 0.001],
        "children": list(range(1, len(names) + 1)),
        "extras": {"note": f"children are bone_to_lab poses in mm, lab {lab_up.upper()} up"},
    }]
    for b, name in enumerate(names):
        node: dict[str, Any] = {
            "name": name,
            "translation": [float(v) for v in trans0[b]],
            "rotation": [float(v) for v in quat0[b]],
        }
        if not visible0[b]:
            node["scale"] = [0.0, 0.0, 0.0]
        mesh = meshes.get(name)
        if mesh is not None:
            if mesh.frame not in ("", name):
                raise ValueError(f"mesh of bone {name!r} is in frame {mesh.frame!r}; "
                                 f"expected the bone's own frame ({name!r})")
            rgba = _color(colors, name)
            prim = _primitive(builder, mesh)
            if prim is not None:  # a mesh without triangles leaves an empty node
                if rgba not in material_of:  # one material per distinct colour
                    material_of[rgba] = len(materials)
                    materials.append({
                        "name": "bone" if rgba == BONE_COLOR else f"bone_{len(materials)}",
                        "pbrMetallicRoughness": {"baseColorFactor": list(rgba),
                                                 "metallicFactor": 0.0, "roughnessFactor": 0.7},
                        "doubleSided": True,
                    })
                prim["material"] = material_of[rgba]
                node["mesh"] = len(gltf_meshes)
                gltf_meshes.append({"name": name, "primitives": [prim]})
        nodes.append(node)

    gltf: dict[str, Any] = {
        "asset": {"version": "2.0", "generator": f"bonecap {__version__}",
                  "extras": {"length_unit_below_root": "mm", "lab_up": lab_up}},
        "scene": 0,
        "scenes": [{"name": "bonecap", "nodes": [0]}],
        "nodes": nodes,
    }
    if gltf_meshes:
        gltf["meshes"] = gltf_meshes
        gltf["materials"] = materials
    return gltf


def _color(colors, name: str) -> tuple[float, ...]:
    """RGBA tuple for ``name`` from the ``colors`` argument (validated)."""
    if colors is None:
        return BONE_COLOR
    value = colors.get(name, BONE_COLOR) if isinstance(colors, Mapping) else colors
    rgba = [float(c) for c in value]
    if len(rgba) == 3:
        rgba.append(1.0)
    if len(rgba) != 4 or not all(0.0 <= c <= 1.0 for c in rgba):
        raise ValueError(f"colour for {name!r} must be 3 or 4 values in 0..1, got {value!r}")
    return tuple(rgba)


def _primitive(builder: _GlbBuilder, mesh: Mesh) -> dict[str, Any] | None:
    """Store one mesh's POSITION, NORMAL and indices; None if it has no triangle."""
    faces = mesh.faces
    # Index-degenerate triangles cover nothing; the validator flags them.
    keep = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    faces = faces[keep]
    if len(faces) == 0:
        return None
    if not np.all(np.isfinite(mesh.vertices)):
        raise ValueError("mesh vertices contain NaN or infinite values")
    positions = mesh.vertices.astype(np.float32)
    normals = _vertex_normals(mesh.vertices, faces).astype(np.float32)
    index_type = np.uint16 if len(positions) < 65535 else np.uint32
    return {
        "attributes": {
            "POSITION": builder.add(positions, _ARRAY_BUFFER, bounds=True),
            "NORMAL": builder.add(normals, _ARRAY_BUFFER),
        },
        "indices": builder.add(faces.astype(index_type).reshape(-1), _ELEMENT_ARRAY_BUFFER),
        "mode": _TRIANGLES,
    }


def _vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit per-vertex normals: area-weighted face normals, never zero.

    The cross product of two edges is the face normal times twice the area,
    so summing raw cross products per vertex weights faces by area. Vertices
    with no such contribution point away from the centroid instead (and +Z
    if they sit on it), because glTF requires every NORMAL to be unit length.
    """
    v = vertices[faces]
    cross = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    # Scatter-add each face's vector to its three corners (bincount is the
    # fast unbuffered scatter-add in numpy).
    corners = faces.reshape(-1)
    normals = np.stack([np.bincount(corners, weights=np.repeat(cross[:, i], 3), minlength=len(vertices))
                        for i in range(3)], axis=1)
    norm = np.linalg.norm(normals, axis=1)
    bad = ~(norm > 1e-12 * max(1.0, float(np.abs(vertices).max(initial=0.0))) ** 2)
    if bad.any():
        radial = vertices[bad] - vertices.mean(axis=0)
        rnorm = np.linalg.norm(radial, axis=1)
        radial[rnorm == 0] = [0.0, 0.0, 1.0]
        normals[bad] = radial
        norm = np.linalg.norm(normals, axis=1)
    return normals / norm[:, None]


def _animation(builder: _GlbBuilder, name: str, times32: np.ndarray, quats: np.ndarray,
               trans: np.ndarray, valid: np.ndarray) -> dict[str, Any]:
    """Samplers and channels for every bone (node ``b + 1``), sharing one time accessor."""
    F, B = valid.shape
    time_acc = builder.add(times32, bounds=True)
    samplers: list[dict[str, Any]] = []
    channels: list[dict[str, Any]] = []

    def add_path(path: str, data: np.ndarray, bones: Sequence[int], interpolation: str) -> None:
        # data: (len(bones), F, width) float32, contiguous -> one view, one
        # accessor per bone at offset b * F * width * 4 (a multiple of 4).
        view = builder.view(data)
        stride = F * data.shape[-1] * 4
        for i, b in enumerate(bones):
            acc = builder.accessor(view, data[i], byte_offset=i * stride)
            channels.append({"sampler": len(samplers), "target": {"node": b + 1, "path": path}})
            samplers.append({"input": time_acc, "output": acc, "interpolation": interpolation})

    every = list(range(B))
    add_path("translation", np.ascontiguousarray(trans.transpose(1, 0, 2), dtype=np.float32), every, "LINEAR")
    add_path("rotation", np.ascontiguousarray(quats.transpose(1, 0, 2), dtype=np.float32), every, "LINEAR")
    hidden = [b for b in every if not valid[:, b].all()]
    if hidden:
        scale = np.repeat(valid[:, hidden].T[:, :, None], 3, axis=2).astype(np.float32)
        add_path("scale", scale, hidden, "STEP")
    return {"name": name, "samplers": samplers, "channels": channels}


def _write_glb(path: str | os.PathLike, gltf: dict[str, Any], builder: _GlbBuilder) -> None:
    """Pack the JSON and binary chunks into a GLB and write it atomically."""
    # glTF forbids empty arrays and zero-length buffers: a scene of empty
    # nodes (no mesh, no animation) has no binary chunk at all.
    if builder.size:
        gltf["accessors"] = builder.accessors
        gltf["bufferViews"] = builder.buffer_views
        gltf["buffers"] = [{"byteLength": builder.size}]
    text = json.dumps(gltf, separators=(",", ":"), allow_nan=False).encode("utf-8")
    text += b" " * (-len(text) % 4)  # the JSON chunk is padded with spaces
    total = 12 + 8 + len(text) + (8 + builder.size if builder.size else 0)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(struct.pack("<4sII", _GLB_MAGIC, 2, total))
            fh.write(struct.pack("<II", len(text), _CHUNK_JSON))
            fh.write(text)
            if builder.size:
                fh.write(struct.pack("<II", builder.size, _CHUNK_BIN))
                for blob in builder.blobs:
                    fh.write(blob)
