"""Tests of bonecap.io.mesh: reading PLY/STL/OBJ/VTP/VTK, writing PLY/STL/OBJ/GLB."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from bonecap.errors import FormatError, InputError, OutputError
from bonecap.io.mesh import read_mesh, write_mesh
from bonecap.model import Mesh

# Read in place, never copied; the ``shared_data`` fixture (conftest.py) skips
# the tests that need it when the folder is absent.
SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"
OPENSIM = SHARED / "bones" / "opensim"


def sphere_mesh() -> Mesh:
    """A closed icosphere of radius 50 mm away from the origin (non-trivial coordinates)."""
    s = trimesh.creation.icosphere(subdivisions=2, radius=50.0)
    return Mesh(s.vertices + [123.456, -78.9, 1000.25], s.faces, "lps")


# --------------------------------------------------------------------------- #
# Real files
# --------------------------------------------------------------------------- #

@pytest.mark.shared
def test_every_opensim_vtp_reads(shared_data):
    files = sorted((OPENSIM / "Geometry").glob("*.vtp"))
    assert len(files) > 90
    for f in files:
        mesh = read_mesh(f, units="m")
        assert len(mesh.faces) > 0, f.name
        assert mesh.frame == ""
        assert np.isfinite(mesh.vertices).all()
        # OpenSim geometry is metres: once scaled, every bone is 1 mm .. 2 m across.
        extent = np.ptp(mesh.vertices, axis=0).max()
        assert 1.0 < extent < 2000.0, (f.name, extent)


@pytest.mark.shared
def test_femur_vtp_in_metres_is_a_femur(shared_data):
    path = OPENSIM / "Geometry" / "femur_r.vtp"
    in_m = read_mesh(path, units="m")
    length = np.ptp(in_m.vertices, axis=0).max()
    assert 350.0 < length < 500.0  # an adult femur, in mm
    as_stored = read_mesh(path, units="mm")
    np.testing.assert_allclose(as_stored.vertices * 1000.0, in_m.vertices)
    # units=None recognises a 0.45-unit bone as metres.
    np.testing.assert_allclose(read_mesh(path, units=None).vertices, in_m.vertices)
    # A triangle soup would have 3 vertices per face; this one is shared (456 v, 908 f).
    assert len(in_m.vertices) < len(in_m.faces)


@pytest.mark.shared
def test_rajagopal_ply_read_and_agree_with_vtp(shared_data):
    folder = OPENSIM / "rajagopal2016_default_pose_ply"
    plys = sorted(folder.glob("*.ply"))
    assert len(plys) > 20
    for f in plys:
        assert len(read_mesh(f, units="m").faces) > 0, f.name

    # The derived PLY is the VTP placed by the body's frame: a cross-check of
    # both readers, vertex order included.
    frames = {}
    for line in (folder / "body_frames_in_ground.txt").read_text().splitlines():
        if line and not line.startswith("#"):
            name, *values = line.split()
            frames[name] = np.array(values, float).reshape(4, 4)
    T = frames["femur_r"].copy()
    T[:3, 3] *= 1000.0
    vtp = read_mesh(OPENSIM / "Geometry" / "r_femur.vtp", units="m")
    ply = read_mesh(folder / "femur_r__r_femur.ply", units="m")
    assert len(ply.faces) == len(vtp.faces)
    np.testing.assert_allclose(vtp.transformed(T).vertices, ply.vertices, atol=1e-3)


# --------------------------------------------------------------------------- #
# Round trips
# --------------------------------------------------------------------------- #

@pytest.mark.parametrize("ext", [".ply", ".stl", ".obj"])
def test_round_trip(tmp_path, ext):
    mesh = sphere_mesh()
    path = tmp_path / f"sphere{ext}"
    write_mesh(mesh, path)
    back = read_mesh(path)
    assert len(back.faces) == len(mesh.faces)
    assert len(back.vertices) == len(mesh.vertices)  # STL corners are welded again
    # float32 keeps ~7 significant digits: 1e-7 of ~1000 mm.
    tol = 1e-7 * np.abs(mesh.vertices).max() * 2
    # Compare triangle corners, which survive STL's re-indexing.
    np.testing.assert_allclose(back.vertices[back.faces], mesh.vertices[mesh.faces], atol=tol)
    if ext != ".stl":
        np.testing.assert_allclose(back.vertices, mesh.vertices, atol=tol)
        np.testing.assert_array_equal(back.faces, mesh.faces)
    # Nothing but the target is left in the folder (atomic write).
    assert [p.name for p in tmp_path.iterdir()] == [path.name]


def test_ply_is_binary(tmp_path):
    write_mesh(sphere_mesh(), tmp_path / "s.ply")
    head = (tmp_path / "s.ply").read_bytes()[:200]
    assert b"format binary_little_endian" in head


def test_write_glb_opens_in_metres_y_up(tmp_path):
    mesh = sphere_mesh()
    path = tmp_path / "sphere.glb"
    write_mesh(mesh, path)
    # trimesh applies the scene graph: what a viewer shows.
    scene = trimesh.load(path, force="scene")
    shown = np.concatenate([g.vertices for g in scene.dump()])
    x, y, z = mesh.vertices.T
    np.testing.assert_allclose(shown, np.c_[x, z, -y] / 1000.0, atol=1e-6)

    write_mesh(mesh, tmp_path / "y_up.glb", up="y")
    shown = np.concatenate([g.vertices for g in trimesh.load(tmp_path / "y_up.glb", force="scene").dump()])
    np.testing.assert_allclose(shown, mesh.vertices / 1000.0, atol=1e-6)


def test_write_errors(tmp_path):
    with pytest.raises(OutputError, match="xyz"):
        write_mesh(sphere_mesh(), tmp_path / "s.xyz")
    with pytest.raises(ValueError, match="without triangles"):
        write_mesh(Mesh(np.zeros((3, 3)), np.zeros((0, 3), int)), tmp_path / "e.ply")
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- #
# VTK specifics
# --------------------------------------------------------------------------- #

def test_vtk_polygons_triangulated_lines_dropped(tmp_path):
    path = tmp_path / "quad.vtk"
    path.write_text(
        "# vtk DataFile Version 3.0\nquad and a line\nASCII\nDATASET POLYDATA\n"
        "POINTS 5 float\n0 0 0  1 0 0  1 1 0  0 1 0  5 5 5\n"
        "POLYGONS 1 5\n4 0 1 2 3\n"
        "LINES 1 3\n2 0 4\n")
    mesh = read_mesh(path)
    assert mesh.faces.shape == (2, 3)
    assert set(mesh.faces.ravel()) == {0, 1, 2, 3}


def test_vtp_strips_and_verts(tmp_path):
    import pyvista as pv

    points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, 2, 0], [9, 9, 9]], float)
    poly = pv.PolyData(points, strips=[5, 0, 1, 2, 3, 4], verts=[1, 5])
    path = tmp_path / "strip.vtp"
    poly.save(path)
    mesh = read_mesh(path, units="m")
    assert mesh.faces.shape == (3, 3)  # a strip of 5 points is 3 triangles
    assert 5 not in mesh.faces  # the vertex cell is not a surface
    np.testing.assert_allclose(mesh.vertices, points * 1000.0)


# --------------------------------------------------------------------------- #
# Bad input
# --------------------------------------------------------------------------- #

@pytest.mark.parametrize("ext", [".ply", ".stl", ".obj", ".vtp", ".vtk"])
@pytest.mark.parametrize("content", [b"this is not a mesh\x00\x01\x02 at all\n", b""], ids=["garbage", "empty"])
def test_bad_file_is_format_error(tmp_path, ext, content):
    path = tmp_path / f"bad{ext}"
    path.write_bytes(content)
    with pytest.raises(FormatError) as info:
        read_mesh(path)
    message = str(info.value)
    assert message.startswith(str(path) + ": ")
    assert "\n" not in message


@pytest.mark.shared
def test_truncated_vtp_is_format_error(tmp_path, shared_data):
    data = (OPENSIM / "Geometry" / "femur_r.vtp").read_bytes()
    path = tmp_path / "cut.vtp"
    path.write_bytes(data[: len(data) // 3])
    with pytest.raises(FormatError):
        read_mesh(path)


def test_point_cloud_ply_is_format_error(tmp_path):
    path = tmp_path / "cloud.ply"
    trimesh.PointCloud(np.random.default_rng(0).random((10, 3))).export(path)
    with pytest.raises(FormatError, match="no triangles"):
        read_mesh(path)


def test_missing_folder_and_unknown_extension(tmp_path):
    with pytest.raises(InputError, match="no such file") as info:
        read_mesh(tmp_path / "nope.ply")
    assert not isinstance(info.value, FormatError)
    with pytest.raises(InputError, match="folder"):
        read_mesh(tmp_path)
    (tmp_path / "mesh.off").write_text("OFF\n")
    with pytest.raises(FormatError, match="unsupported"):
        read_mesh(tmp_path / "mesh.off")
    with pytest.raises(ValueError, match="units"):
        read_mesh(tmp_path / "mesh.off", units="cm")
