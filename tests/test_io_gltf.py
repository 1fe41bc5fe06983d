"""Tests of bonecap.io.gltf: the animated/static GLB writer and the summary reader.

The files are checked three independent ways: by the Khronos glTF validator
(Node, ``tests/gltf_validate.mjs``), by pygltflib (a separate parser) with
the glTF transform rules applied by hand, and by trimesh's scene loader.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from bonecap.errors import FormatError, InputError
from bonecap.io.gltf import BONE_COLOR, summarize_gltf, write_animated_glb, write_static_glb
from bonecap.model import Mesh, Motion
from gltf_validation import assert_clean, run_validator

pygltflib = pytest.importorskip("pygltflib")

REPO = Path(__file__).resolve().parents[1]
F = 50
RATE = 100.0
NAMES = ["pelvis", "femur_r", "tibia_r"]


# --------------------------------------------------------------------------- #
# Helpers
# --------------------------------------------------------------------------- #

def load(path: Path):
    gltf = pygltflib.GLTF2().load(str(path))
    return gltf, gltf.binary_blob()


def accessor(gltf, blob, index: int) -> np.ndarray:
    """Decode one accessor (tightly packed, as this writer stores them)."""
    acc = gltf.accessors[index]
    view = gltf.bufferViews[acc.bufferView]
    assert view.byteStride is None
    dtype = {5126: np.float32, 5123: np.uint16, 5125: np.uint32}[acc.componentType]
    width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[acc.type]
    start = (view.byteOffset or 0) + (acc.byteOffset or 0)
    assert (acc.byteOffset or 0) + acc.count * width * np.dtype(dtype).itemsize <= view.byteLength
    data = np.frombuffer(blob, dtype, count=acc.count * width, offset=start)
    return data if width == 1 else data.reshape(acc.count, width)


def node_index(gltf, name: str) -> int:
    return [n.name for n in gltf.nodes].index(name)


def channels(gltf, blob, name: str) -> dict[str, tuple[np.ndarray, np.ndarray, str]]:
    """path -> (times, values, interpolation) of the animation channels of node ``name``."""
    target = node_index(gltf, name)
    out = {}
    for ch in gltf.animations[0].channels:
        if ch.target.node == target:
            s = gltf.animations[0].samplers[ch.sampler]
            out[ch.target.path] = (accessor(gltf, blob, s.input), accessor(gltf, blob, s.output), s.interpolation)
    return out


def lab_to_gltf(p_mm: np.ndarray) -> np.ndarray:
    """Where a lab point (mm, Z up) must appear in a glTF viewer (m, Y up)."""
    x, y, z = np.asarray(p_mm, float).T
    return np.stack([x, z, -y], axis=-1) / 1000.0


def bone_meshes() -> dict[str, Mesh]:
    box = trimesh.creation.box(extents=(160.0, 120.0, 90.0))
    cyl = trimesh.creation.cylinder(radius=25.0, height=420.0, sections=24)
    ico = trimesh.creation.icosphere(subdivisions=2, radius=40.0)
    return {
        "pelvis": Mesh(box.vertices, box.faces, "pelvis"),
        "femur_r": Mesh(cyl.vertices + [0.0, 0.0, -210.0], cyl.faces, "femur_r"),
        "tibia_r": Mesh(ico.vertices * [1.0, 1.0, 4.0] + [0.0, 0.0, -180.0], ico.faces, ""),
    }


def make_transforms() -> np.ndarray:
    """Known motion: pelvis translates, femur spins twice about z, tibia swings."""
    t = np.arange(F) / RATE
    T = np.tile(np.eye(4), (F, 3, 1, 1))
    T[:, 0, :3, 3] = np.c_[1000.0 * t, 50.0 * np.sin(6 * t), np.full(F, 950.0)]
    T[:, 1, :3, :3] = Rotation.from_euler("z", np.linspace(0.0, 720.0, F)[:, None], degrees=True).as_matrix()
    T[:, 1, :3, 3] = T[:, 0, :3, 3] + [0.0, -80.0, -60.0]
    axis = np.array([1.0, 0.3, -0.2]) / np.linalg.norm([1.0, 0.3, -0.2])
    T[:, 2, :3, :3] = Rotation.from_rotvec(np.outer(np.linspace(-1.2, 2.5, F), axis)).as_matrix()
    T[:, 2, :3, 3] = T[:, 1, :3, 3] + np.c_[30.0 * np.cos(4 * t), np.zeros(F), np.full(F, -420.0)]
    return T


def motion_with_gaps() -> Motion:
    """Pelvis missing at frames 0-4, tibia NaN at 10-19 and flagged invalid at 30."""
    T = make_transforms()
    T[0:5, 0] = np.nan
    T[10:20, 2] = np.nan
    valid = np.isfinite(T).all(axis=(2, 3))
    valid[30, 2] = False
    return Motion(NAMES, 12.5 + np.arange(F) / RATE, T, valid=valid, first_frame=1251)


@pytest.fixture
def animated(tmp_path) -> tuple[Path, Motion]:
    motion = Motion(NAMES, np.arange(F) / RATE, make_transforms())
    path = tmp_path / "walk.glb"
    write_animated_glb(path, bone_meshes(), motion)
    return path, motion


@pytest.fixture
def gappy(tmp_path) -> tuple[Path, Motion]:
    motion = motion_with_gaps()
    path = tmp_path / "gaps.glb"
    write_animated_glb(path, bone_meshes(), motion)
    return path, motion


# --------------------------------------------------------------------------- #
# Validator
# --------------------------------------------------------------------------- #

def test_validator_animated_with_gaps_is_clean(gappy):
    path, motion = gappy
    report = run_validator(path)
    assert_clean(report)
    info = report["info"]
    assert info["animationCount"] == 1
    assert info["totalTriangleCount"] == sum(len(m.faces) for m in bone_meshes().values())


def test_validator_static_is_clean(tmp_path):
    T = make_transforms()[7]
    path = tmp_path / "pose.glb"
    write_static_glb(path, bone_meshes(), dict(zip(NAMES, T)))
    assert_clean(run_validator(path))


@pytest.mark.shared
def test_validator_real_opensim_meshes_is_clean(tmp_path, shared_data):
    from bonecap.io.mesh import read_mesh

    files = sorted((shared_data / "bones" / "opensim" / "Geometry").glob("*.vtp"))
    meshes = {f.stem: read_mesh(f, units="m") for f in files}
    rng = np.random.default_rng(3)
    poses = {}
    for name in meshes:
        T = np.eye(4)
        T[:3, :3] = Rotation.random(random_state=rng).as_matrix()
        T[:3, 3] = rng.uniform(-1000, 1000, 3)
        poses[name] = T
    path = tmp_path / "opensim.glb"
    write_static_glb(path, meshes, poses)
    report = run_validator(path)
    assert_clean(report)
    assert report["info"]["drawCallCount"] == len(files)


# --------------------------------------------------------------------------- #
# Geometry and animation content
# --------------------------------------------------------------------------- #

def test_root_node_carries_units_and_up_axis(animated):
    gltf, _ = load(animated[0])
    root = gltf.nodes[gltf.scenes[gltf.scene].nodes[0]]
    assert root.name == "lab"
    np.testing.assert_allclose(root.scale, [0.001] * 3)
    R = Rotation.from_quat(root.rotation).as_matrix()
    np.testing.assert_allclose(R @ [0, 0, 1], [0, 1, 0], atol=1e-12)  # lab up -> glTF up
    assert sorted(gltf.nodes[c].name for c in root.children) == sorted(NAMES)


def test_bone_world_position_matches_lab_data(animated):
    path, motion = animated
    gltf, blob = load(path)
    root = gltf.nodes[gltf.scenes[gltf.scene].nodes[0]]
    root_R = Rotation.from_quat(root.rotation).as_matrix()
    root_s = np.asarray(root.scale)

    for name, frame in [("tibia_r", 17), ("femur_r", 33), ("pelvis", 49)]:
        node = gltf.nodes[node_index(gltf, name)]
        prim = gltf.meshes[node.mesh].primitives[0]
        vertices = accessor(gltf, blob, prim.attributes.POSITION)
        ch = channels(gltf, blob, name)
        times, t_out, _ = ch["translation"]
        q = ch["rotation"][1][frame]
        assert times[frame] == pytest.approx(frame / RATE)
        # glTF: world = root_T @ node_T(TRS at this keyframe) @ vertex
        v = vertices[5].astype(float)
        local = Rotation.from_quat(q).as_matrix() @ v + t_out[frame]
        world = root_R @ (root_s * local)

        b = NAMES.index(name)
        lab = motion.transforms[frame, b] @ np.r_[bone_meshes()[name].vertices[5], 1.0]
        np.testing.assert_allclose(world, lab_to_gltf(lab[:3]), atol=2e-6)


def test_trimesh_sees_frame_zero_in_metres_y_up(animated):
    path, motion = animated
    scene = trimesh.load(path, force="scene")
    meshes = bone_meshes()
    for b, name in enumerate(NAMES):
        node_names = [n for n in scene.graph.nodes_geometry if scene.graph[n][1] == name]
        assert len(node_names) == 1, scene.graph.nodes_geometry
        T_world, geom = scene.graph[node_names[0]]
        shown = trimesh.transform_points(scene.geometry[geom].vertices, T_world)
        expected = lab_to_gltf(meshes[name].transformed(motion.transforms[0, b]).vertices)
        np.testing.assert_allclose(shown, expected, atol=2e-6)


def test_quaternions_unit_continuous_and_correct(animated):
    path, motion = animated
    gltf, blob = load(path)
    raw = Rotation.from_matrix(motion.transforms[:, 1, :3, :3]).as_quat()
    # Precondition: converting each frame on its own does flip sign somewhere
    # on a 720-degree spin, so continuity is the writer's doing.
    assert (np.sum(raw[1:] * raw[:-1], axis=1) < 0).any()
    for b, name in enumerate(NAMES):
        times, q, interpolation = channels(gltf, blob, name)["rotation"]
        assert interpolation == "LINEAR"
        assert q.shape == (F, 4) and q.dtype == np.float32
        np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-6)
        assert (np.sum(q[1:] * q[:-1], axis=1) >= 0).all(), name
        assert q[0, 3] >= 0
        np.testing.assert_allclose(Rotation.from_quat(q).as_matrix(), motion.transforms[:, b, :3, :3], atol=1e-6)
        _, t, _ = channels(gltf, blob, name)["translation"]
        np.testing.assert_allclose(t, motion.transforms[:, b, :3, 3], rtol=1e-6, atol=1e-4)


def test_times_start_at_zero_and_increase(gappy):
    path, motion = gappy  # motion.times start at 12.5 s
    gltf, blob = load(path)
    samplers = gltf.animations[0].samplers
    assert len({s.input for s in samplers}) == 1  # one shared time accessor
    acc = gltf.accessors[samplers[0].input]
    times = accessor(gltf, blob, samplers[0].input)
    assert times[0] == 0.0
    assert (np.diff(times) > 0).all()
    np.testing.assert_allclose(times, motion.times - 12.5, atol=1e-6)
    assert acc.min == [float(times.min())] and acc.max == [float(times.max())]
    assert gltf.asset.extras["time_offset_s"] == pytest.approx(12.5)
    assert gltf.asset.extras["first_frame"] == 1251


def test_invalid_frames_hidden_and_pose_held(gappy):
    path, motion = gappy
    gltf, blob = load(path)
    T = motion.transforms

    # The always-valid femur has no scale channel; the others have a STEP one.
    assert "scale" not in channels(gltf, blob, "femur_r")
    tibia = channels(gltf, blob, "tibia_r")
    _, scale, interpolation = tibia["scale"]
    assert interpolation == "STEP"
    hidden = np.zeros(F, bool)
    hidden[10:20] = hidden[30] = True
    np.testing.assert_array_equal(scale, np.where(hidden, 0.0, 1.0)[:, None].repeat(3, axis=1))
    # While hidden, the last valid pose (frame 9, frame 29) is held.
    _, t, _ = tibia["translation"]
    _, q, _ = tibia["rotation"]
    np.testing.assert_array_equal(t[10:20], np.repeat(t[9:10], 10, axis=0))
    np.testing.assert_array_equal(q[10:20], np.repeat(q[9:10], 10, axis=0))
    np.testing.assert_array_equal(t[30], t[29])
    np.testing.assert_allclose(t[20], T[20, 2, :3, 3], rtol=1e-6)  # back on its own data
    assert np.isfinite(t).all() and np.isfinite(q).all()

    # Missing at the start: first valid pose (frame 5) is used, node hidden at rest.
    pelvis = channels(gltf, blob, "pelvis")
    np.testing.assert_array_equal(pelvis["scale"][1][:, 0], (np.arange(F) >= 5).astype(np.float32))
    np.testing.assert_array_equal(pelvis["translation"][1][:5], np.repeat(pelvis["translation"][1][5:6], 5, axis=0))
    node = gltf.nodes[node_index(gltf, "pelvis")]
    assert node.scale == [0.0, 0.0, 0.0]
    np.testing.assert_allclose(node.translation, T[5, 0, :3, 3])
    assert gltf.nodes[node_index(gltf, "femur_r")].scale in (None, [1.0, 1.0, 1.0])


def test_bone_never_valid_stays_hidden_at_identity(tmp_path):
    T = make_transforms()
    T[:, 1] = np.nan
    path = tmp_path / "never.glb"
    write_animated_glb(path, bone_meshes(), Motion(NAMES, np.arange(F) / RATE, T))
    gltf, blob = load(path)
    ch = channels(gltf, blob, "femur_r")
    assert (ch["scale"][1] == 0).all()
    assert (ch["translation"][1] == 0).all()
    np.testing.assert_array_equal(ch["rotation"][1], np.tile([0, 0, 0, 1], (F, 1)))


def test_normals_unit_nonzero_outward(animated):
    gltf, blob = load(animated[0])
    for name in NAMES:
        prim = gltf.meshes[gltf.nodes[node_index(gltf, name)].mesh].primitives[0]
        v = accessor(gltf, blob, prim.attributes.POSITION).astype(float)
        n = accessor(gltf, blob, prim.attributes.NORMAL).astype(float)
        np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-6)
        outward = np.einsum("ij,ij->i", n, v - v.mean(axis=0))
        assert outward.sum() > 0, name
        assert (outward > 0).all(), name  # convex shapes: every normal points out
        acc = gltf.accessors[prim.attributes.POSITION]
        np.testing.assert_array_equal(acc.min, v.min(axis=0))
        np.testing.assert_array_equal(acc.max, v.max(axis=0))


def test_normals_follow_winding_and_never_zero(tmp_path):
    box = trimesh.creation.box(extents=(10.0, 20.0, 30.0))
    # Inside-out winding gives inward normals (the winding is the contract);
    # an unused vertex and an index-degenerate triangle are tolerated.
    vertices = np.vstack([box.vertices, [[100.0, 0.0, 0.0]]])
    faces = np.vstack([box.faces[:, ::-1], [[0, 0, 1]]])
    path = tmp_path / "inside_out.glb"
    write_static_glb(path, {"b": Mesh(vertices, faces)}, {"b": np.eye(4)})
    gltf, blob = load(path)
    prim = gltf.meshes[0].primitives[0]
    n = accessor(gltf, blob, prim.attributes.NORMAL).astype(float)
    assert len(n) == 9
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-6)
    inward = np.einsum("ij,ij->i", n[:8], box.vertices - box.vertices.mean(axis=0))
    assert (inward < 0).all()
    assert gltf.accessors[prim.indices].count == 36  # the degenerate triangle is dropped
    assert gltf.accessors[prim.indices].componentType == 5123


def test_materials_and_colors(tmp_path):
    motion = Motion(NAMES, np.arange(F) / RATE, make_transforms())
    path = tmp_path / "colored.glb"
    write_animated_glb(path, bone_meshes(), motion, colors={"femur_r": (1.0, 0.0, 0.0)}, lab_up="y")
    gltf, _ = load(path)
    colour = {n.name: gltf.materials[gltf.meshes[n.mesh].primitives[0].material].pbrMetallicRoughness.baseColorFactor
              for n in gltf.nodes if n.mesh is not None}
    assert colour == {"pelvis": list(BONE_COLOR), "femur_r": [1.0, 0.0, 0.0, 1.0], "tibia_r": list(BONE_COLOR)}
    assert len(gltf.materials) == 2
    assert all(m.pbrMetallicRoughness.metallicFactor == 0.0 for m in gltf.materials)
    assert gltf.nodes[0].rotation == [0.0, 0.0, 0.0, 1.0]  # lab already Y up
    with pytest.raises(ValueError, match="colour"):
        write_animated_glb(tmp_path / "x.glb", bone_meshes(), motion, colors=(2.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="lab_up"):
        write_animated_glb(tmp_path / "x.glb", bone_meshes(), motion, lab_up="x")


def test_bone_without_mesh_is_an_animated_empty_node(tmp_path):
    motion = Motion(NAMES, np.arange(F) / RATE, make_transforms())
    meshes = bone_meshes()
    del meshes["femur_r"]
    path = tmp_path / "partial.glb"
    write_animated_glb(path, meshes, motion)
    gltf, blob = load(path)
    femur = gltf.nodes[node_index(gltf, "femur_r")]
    assert femur.mesh is None
    assert set(channels(gltf, blob, "femur_r")) == {"translation", "rotation"}
    assert len(gltf.meshes) == 2


def test_static_pose_nodes(tmp_path):
    T = make_transforms()[21]
    poses = dict(zip(NAMES, T))
    poses["tibia_r"] = np.full((4, 4), np.nan)  # unsolved at this pose: hidden
    path = tmp_path / "pose.glb"
    write_static_glb(path, bone_meshes(), poses)
    gltf, _ = load(path)
    assert not gltf.animations
    femur = gltf.nodes[node_index(gltf, "femur_r")]
    np.testing.assert_allclose(femur.translation, T[1, :3, 3])
    np.testing.assert_allclose(Rotation.from_quat(femur.rotation).as_matrix(), T[1, :3, :3], atol=1e-12)
    assert gltf.nodes[node_index(gltf, "tibia_r")].scale == [0.0, 0.0, 0.0]


# --------------------------------------------------------------------------- #
# Rejected input (and nothing left behind)
# --------------------------------------------------------------------------- #

def test_non_increasing_times_raise(tmp_path):
    motion = Motion(NAMES, np.arange(F) / RATE, make_transforms())
    motion.times = motion.times.copy()
    motion.times[20] = motion.times[19]  # Motion checks only at construction
    with pytest.raises(ValueError, match="increase strictly"):
        write_animated_glb(tmp_path / "t.glb", bone_meshes(), motion)
    # Distinct in float64, equal once stored as float32 keyframe times.
    times = np.arange(F) / RATE
    times[-1] = 1000.0
    times[-2] = 1000.0 - 1e-5
    with pytest.raises(ValueError, match="float32"):
        write_animated_glb(tmp_path / "t.glb", bone_meshes(), Motion(NAMES, times, make_transforms()))
    motion.times[20] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        write_animated_glb(tmp_path / "t.glb", bone_meshes(), motion)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("defect", ["scaled", "sheared", "mirrored", "bottom_row"])
def test_non_rigid_transform_raises_and_keeps_old_file(tmp_path, animated, defect):
    path, motion = animated
    before = path.read_bytes()
    T = motion.transforms.copy()
    if defect == "scaled":
        T[12, 2, :3, :3] *= 1.02
    elif defect == "sheared":
        T[12, 2, 0, 1] += 0.05
    elif defect == "mirrored":
        T[12, 2, :3, :3] = T[12, 2, :3, :3] @ np.diag([1.0, 1.0, -1.0])
    else:
        T[12, 2, 3, 0] = 0.5
    with pytest.raises(ValueError, match=r"'tibia_r' at frame 12 is not rigid"):
        write_animated_glb(path, bone_meshes(), Motion(NAMES, motion.times, T))
    assert path.read_bytes() == before
    assert [p.name for p in path.parent.iterdir()] == [path.name]


def test_mesh_mismatches_raise(tmp_path):
    motion = Motion(NAMES, np.arange(F) / RATE, make_transforms())
    meshes = bone_meshes()
    with pytest.raises(ValueError, match="'humerus'"):
        write_animated_glb(tmp_path / "m.glb", {**meshes, "humerus": meshes["pelvis"]}, motion)
    meshes["femur_r"].frame = "lab"
    with pytest.raises(ValueError, match="frame 'lab'"):
        write_animated_glb(tmp_path / "m.glb", meshes, motion)


# --------------------------------------------------------------------------- #
# Summary
# --------------------------------------------------------------------------- #

def test_summarize(gappy):
    path, motion = gappy
    summary = summarize_gltf(path)
    json.dumps(summary)  # JSON-able
    assert summary["format"] == "gltf" and summary["container"] == "glb"
    assert summary["path"] == str(path)
    assert summary["generator"].startswith("bonecap ")
    assert summary["nodes"] == 4 and summary["node_names"] == ["lab", *NAMES]
    assert summary["meshes"] == 3
    assert summary["triangles"] == sum(len(m.faces) for m in bone_meshes().values())
    assert summary["animations"] == 1
    assert summary["animation_channels"] == [3 * 2 + 2]  # T+R per bone, scale for pelvis and tibia
    assert summary["duration"] == pytest.approx((F - 1) / RATE, abs=1e-6)
    assert summary["frames"] == F


def test_summarize_single_frame_and_json(tmp_path):
    path = tmp_path / "one.glb"
    write_animated_glb(path, bone_meshes(), Motion(NAMES, [3.0], make_transforms()[:1]))
    summary = summarize_gltf(path)
    assert (summary["frames"], summary["duration"]) == (1, 0.0)
    doc = tmp_path / "tiny.gltf"
    doc.write_text(json.dumps({"asset": {"version": "2.0", "generator": "hand"}, "nodes": [{"name": "a"}]}))
    summary = summarize_gltf(doc)
    assert (summary["container"], summary["nodes"], summary["animations"], summary["frames"]) == ("json", 1, 0, 0)


def test_summarize_bad_files(tmp_path, animated):
    garbage = tmp_path / "garbage.glb"
    garbage.write_bytes(b"\x00\x01 definitely not glTF")
    truncated = tmp_path / "cut.glb"
    truncated.write_bytes(animated[0].read_bytes()[:100])
    no_asset = tmp_path / "no_asset.gltf"
    no_asset.write_text('{"nodes": []}')
    broken = tmp_path / "broken.gltf"
    broken.write_text('{"asset": {"version": "2.0"}, "meshes": [{"primitives": [{"indices": 7}]}]}')
    for path in (garbage, truncated, no_asset, broken):
        with pytest.raises(FormatError) as info:
            summarize_gltf(path)
        assert str(info.value).startswith(str(path))
    with pytest.raises(InputError):
        summarize_gltf(tmp_path / "missing.glb")
