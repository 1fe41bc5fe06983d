"""Triangle mesh files <-> :class:`bonecap.model.Mesh`.

Formats and libraries
---------------------
=========  ==========  ======  =====================================================
extension  read        write   library
=========  ==========  ======  =====================================================
``.ply``   yes         yes     trimesh (written binary little-endian)
``.stl``   yes         yes     trimesh (written binary)
``.obj``   yes         yes     trimesh (vertices and faces only)
``.vtp``   yes         no      pyvista / VTK XML PolyData (OpenSim ``Geometry/``)
``.vtk``   yes         no      pyvista / VTK legacy (PolyData or UnstructuredGrid)
``.glb``   no          yes     :mod:`bonecap.io.gltf` (a static one-node scene)
=========  ==========  ======  =====================================================

How a file maps onto a ``Mesh``
-------------------------------
- **Vertices** become ``Mesh.vertices`` (float64, shape ``(N, 3)``) in the
  file's own order, so per-vertex correspondences survive a round trip. STL is
  the exception: it stores three private corners per triangle, so exact
  duplicate corners are welded on read (the only connectivity STL can carry).
- **Faces** become ``Mesh.faces``. Polygons are split into triangles; VTK
  triangle strips are converted too, while VTK *lines* and *vertices* cells (no
  surface) are dropped. The winding is kept as stored: ``Mesh`` expects
  counter-clockwise seen from outside, which is what OpenSim and every mesher
  we use write, but a file is not corrected if it disagrees.
- **Units.** None of these formats records a length unit: a number ``0.43`` is
  as good a femur in metres as ``430`` is in millimetres. ``Mesh`` is always in
  millimetres, so the caller states what the file holds with ``units``:
  ``"mm"`` (default, no scaling), ``"m"`` (multiply by 1000; OpenSim
  ``Geometry/*.vtp`` files are in metres) or ``None`` to guess from the size
  (see :func:`read_mesh`).
- **Frame.** A file does not name its coordinate frame either, so
  ``Mesh.frame`` is left ``""`` for the caller to set (``"lps"``, a bone name...).
- Colours, normals, texture coordinates and other attributes are not kept:
  ``Mesh`` is geometry only, and normals are recomputed where needed.

Writing
-------
:func:`write_mesh` picks the format from the extension and always writes
through :func:`bonecap.io.atomic.atomic_path`, so a failure leaves no partial
file. Millimetres are written as is to PLY/STL/OBJ (the usual unit of medical
meshes). A ``.glb`` is different: glTF is defined in metres with +Y up, so the
mesh goes under a root node that scales by 0.001 and turns the Z-up frame Y-up,
exactly as the animated skeleton files of :mod:`bonecap.io.gltf` do; the file
then opens at the right size and the right way up in any glTF viewer.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np

from bonecap.errors import FormatError, InputError, OutputError
from bonecap.io.atomic import atomic_path
from bonecap.model import Mesh

__all__ = ["read_mesh", "write_mesh", "READ_EXTENSIONS", "WRITE_EXTENSIONS"]

#: Extensions :func:`read_mesh` understands (lower case, with the dot).
READ_EXTENSIONS = (".ply", ".stl", ".obj", ".vtp", ".vtk")
#: Extensions :func:`write_mesh` understands (lower case, with the dot).
WRITE_EXTENSIONS = (".ply", ".stl", ".obj", ".glb")

_UNIT_SCALE = {"mm": 1.0, "m": 1000.0}

# A mesh whose bounding-box diagonal is below this many file units is taken to
# be in metres by ``units=None``: no bone is 3 mm across, and no skeleton is
# 3 m tall, so the two readings never overlap for the data we handle.
_METRE_GUESS_LIMIT = 3.0


def read_mesh(path: str | os.PathLike, *, units: str | None = "mm") -> Mesh:
    """Read a triangle mesh from PLY, STL, OBJ, VTP or legacy VTK.

    Parameters
    ----------
    path : path-like
        The mesh file; its extension selects the reader (see
        :data:`READ_EXTENSIONS`, case-insensitive).
    units : {"mm", "m", None}
        The length unit of the numbers in the file, which the formats do not
        record. ``"mm"`` keeps them, ``"m"`` multiplies by 1000 (OpenSim
        geometry). ``None`` guesses: a mesh whose bounding-box diagonal is
        below 3 file units is taken as metres, anything larger as millimetres.

    Returns
    -------
    Mesh
        Vertices in millimetres, triangular faces, ``frame=""``.

    Raises
    ------
    InputError
        The file does not exist or is a folder.
    FormatError
        The extension is not supported, the content cannot be parsed, or the
        file holds no triangle (a point cloud, only lines, an empty file).
    ValueError
        ``units`` is not one of the accepted values.
    """
    if units is not None and units not in _UNIT_SCALE:
        raise ValueError(f"units must be 'mm', 'm' or None, got {units!r}")
    path = Path(path)
    if not path.exists():
        raise InputError("no such file", path)
    if path.is_dir():
        raise InputError("is a folder, not a mesh file", path)
    ext = path.suffix.lower()
    if ext in (".vtp", ".vtk"):
        vertices, faces = _read_vtk(path, ext)
    elif ext in (".ply", ".stl", ".obj"):
        vertices, faces = _read_trimesh(path, ext)
    else:
        raise FormatError(
            f"unsupported mesh extension {path.suffix or '(none)'!r}; "
            f"expected one of {', '.join(READ_EXTENSIONS)}", path)

    if len(faces) == 0:
        raise FormatError("contains no triangles", path)
    if not np.all(np.isfinite(vertices)):
        raise FormatError("has non-finite vertex coordinates", path)

    if units is None:
        extent = float(np.linalg.norm(np.ptp(vertices, axis=0)))
        units = "m" if extent < _METRE_GUESS_LIMIT else "mm"
    vertices = vertices * _UNIT_SCALE[units]
    return Mesh(vertices, faces)


def _read_trimesh(path: Path, ext: str) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and faces of a PLY/STL/OBJ file via trimesh, unprocessed."""
    import trimesh

    try:
        # process=False: keep the file's vertex order and count (no merging,
        # no removal), so indices stay meaningful to the caller.
        tm = trimesh.load_mesh(path, process=False)
    except Exception as exc:  # trimesh raises a zoo of types on bad input
        raise FormatError(f"cannot read as {ext[1:].upper()}: {_one_line(exc)}", path) from None
    if not isinstance(tm, trimesh.Trimesh):
        # A point cloud (PLY with vertices only) or an empty scene.
        raise FormatError("contains no triangles", path)
    if ext == ".stl" and len(tm.faces):
        # STL repeats every corner; weld the exact duplicates back together.
        tm.merge_vertices(merge_tex=True, merge_norm=True)
    return np.asarray(tm.vertices, dtype=float), np.asarray(tm.faces, dtype=np.int64)


def _read_vtk(path: Path, ext: str) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles of a VTK XML PolyData or legacy VTK file via pyvista."""
    import pyvista as pv

    # VTK's readers do not fail on garbage: they print to stderr and return an
    # empty data set. Look at the first bytes ourselves so that a file of the
    # wrong kind gets a clean error without the noise.
    with open(path, "rb") as fh:
        head = fh.read(512)
    if ext == ".vtp" and b"<VTKFile" not in head:
        raise FormatError("not a VTK XML file (no <VTKFile> element)", path)
    if ext == ".vtk" and not head.lstrip().lower().startswith(b"# vtk datafile"):
        raise FormatError("not a legacy VTK file (no '# vtk DataFile' header)", path)

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with pv.VtkErrorCatcher(raise_errors=True, send_to_logging=False, emit_warnings=False):
                data = pv.read(path)
    except Exception as exc:
        raise FormatError(f"cannot read as VTK: {_one_line(exc)}", path) from None

    if isinstance(data, pv.UnstructuredGrid):
        data = data.extract_surface()
    if not isinstance(data, pv.PolyData):
        raise FormatError(f"holds a {type(data).__name__}, not a surface (PolyData)", path)
    if data.n_points == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    # Splits polygons and strips into triangles; lines and vertex cells are
    # passed through to data.lines / data.verts, which we simply do not read.
    tri = data.triangulate()
    cells = np.asarray(tri.faces, dtype=np.int64)
    if cells.size % 4 or (cells.size and np.any(cells[::4] != 3)):
        raise FormatError("could not be split into triangles", path)
    faces = cells.reshape(-1, 4)[:, 1:]
    return np.asarray(tri.points, dtype=float), faces


def write_mesh(mesh: Mesh, path: str | os.PathLike, *, up: str = "z") -> None:
    """Write a mesh to PLY, STL, OBJ or binary glTF, atomically.

    Parameters
    ----------
    mesh : Mesh
        Vertices in millimetres.
    path : path-like
        Target file; its extension selects the format (:data:`WRITE_EXTENSIONS`).
        PLY and STL are written binary, OBJ as text; all three in millimetres.
    up : {"z", "y"}
        ``.glb`` only: which axis of the mesh's frame points up. ``"z"`` (the
        lab and LPS convention) is turned to glTF's +Y by the root node; the
        root also scales millimetres to metres. Ignored for other formats.

    Raises
    ------
    OutputError
        The extension is not supported.
    ValueError
        The mesh has no triangles.
    OSError
        The file system refused the write (nothing is left behind).
    """
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in WRITE_EXTENSIONS:
        raise OutputError(
            f"cannot write meshes as {path.suffix or '(no extension)'!r}; "
            f"use one of {', '.join(WRITE_EXTENSIONS)}", path)
    if len(mesh.faces) == 0:
        raise ValueError("cannot write a mesh without triangles")

    if ext == ".glb":
        # Reuse the skeleton writer: one node at the identity under the
        # mm -> m, Z-up -> Y-up root. The frame name becomes the node name.
        from bonecap.io.gltf import write_static_glb

        name = mesh.frame or path.stem or "mesh"
        write_static_glb(path, {name: Mesh(mesh.vertices, mesh.faces, name)},
                         {name: np.eye(4)}, lab_up=up)
        return

    tm = mesh.to_trimesh()
    if ext == ".ply":
        data = tm.export(file_type="ply", encoding="binary", vertex_normal=False)
    elif ext == ".stl":
        data = tm.export(file_type="stl")
    else:
        # No normals: they would make readers split vertices by normal index.
        data = tm.export(file_type="obj", include_normals=False, include_color=False,
                         include_texture=False, header="written by bonecap (units: mm)")
    with atomic_path(path) as tmp:
        tmp.write_bytes(data if isinstance(data, bytes) else data.encode("utf-8"))


def _one_line(exc: BaseException) -> str:
    """An exception's message on one line, for ``bonecap: error: PATH: ...``."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= 200 else text[:197] + "..."
