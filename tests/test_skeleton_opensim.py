"""OpenSim .osim models -> Skeleton: checked against the independently derived
default-pose files in ``../shared/data/bones/opensim``, against poses computed
by OpenSim 4.6 itself, and on small synthetic models written here."""

from __future__ import annotations

import csv
import math
import warnings
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from bonecap.errors import FormatError, InputError
from bonecap.skeleton.opensim import (OsimMarker, SimmSpline, UnsupportedModelError, markers_in_world,
                                      read_osim, read_osim_markers)

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
OSIM = DATA / "bones" / "opensim"
MODELS = OSIM / "models"
RAJAGOPAL = MODELS / "Rajagopal2016.osim"
GAIT2392 = MODELS / "gait2392_thelen2003muscle.osim"
ARM26 = MODELS / "arm26.osim"
HAMNER = MODELS / "FullBodyModel_Hamner2010_v2_0.osim"

TOL_MM = 0.1


def _need_data():
    if not DATA.is_dir():
        pytest.skip(f"shared data not found at {DATA}")


@pytest.fixture(scope="module")
def rajagopal():
    _need_data()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # every mesh of this model is in Geometry/
        return read_osim(RAJAGOPAL)


@pytest.fixture(scope="module")
def gait2392():
    _need_data()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return read_osim(GAIT2392)


def _frames_in_ground(path: Path) -> dict[str, np.ndarray]:
    """``body m00 m01 ... m33`` lines (row-major 4x4 body->ground, metres) -> mm."""
    out = {}
    for line in path.read_text().splitlines():
        if not line.strip() or line.startswith("#"):
            continue
        name, *vals = line.split()
        T = np.array([float(v) for v in vals]).reshape(4, 4)
        T[:3, 3] *= 1000.0
        out[name] = T
    return out


def _body_names(path: Path) -> list[str]:
    model = ET.parse(path).getroot().find("Model")
    return [b.get("name") for b in model.find("BodySet").find("objects")]


def _read_ply_mm(path: Path) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    tm = trimesh.load(path, process=False)
    return np.asarray(tm.vertices) * 1000.0, np.asarray(tm.faces)


def _check_frames(skel, ref_dir: Path) -> tuple[float, float]:
    ref = _frames_in_ground(ref_dir / "body_frames_in_ground.txt")
    assert ref.pop("ground").tolist() == np.eye(4).tolist()
    assert set(ref) == set(skel.bones)
    dt = max(np.abs(skel.bones[n].bone_to_world[:3, 3] - T[:3, 3]).max() for n, T in ref.items())
    dr = max(np.abs(skel.bones[n].bone_to_world[:3, :3] - T[:3, :3]).max() for n, T in ref.items())
    return dt, dr


def _check_meshes(skel, ref_dir: Path) -> float:
    """Every ``body__file.ply`` (metres, ground) against the merged bone mesh placed in ground."""
    from scipy.spatial import cKDTree

    by_body: dict[str, list[Path]] = {}
    for ply in sorted(ref_dir.glob("*__*.ply")):
        by_body.setdefault(ply.stem.split("__")[0], []).append(ply)
    assert by_body
    worst = 0.0
    for body, plys in by_body.items():
        world = skel.world_mesh(body)
        assert world.frame == "opensim_ground"
        refs = [_read_ply_mm(p)[0] for p in plys]
        # The bone mesh is exactly the union of its reference parts...
        assert sum(len(v) for v in refs) == len(world.vertices), body
        # ...and every reference vertex has its twin within tolerance.
        d, _ = cKDTree(world.vertices).query(np.concatenate(refs))
        worst = max(worst, float(d.max()))
    return worst


# --------------------------------------------------------------------------- #
# Rajagopal2016 against the derived default pose
# --------------------------------------------------------------------------- #
def test_rajagopal_bones_are_the_model_bodies(rajagopal):
    _need_data()
    assert list(rajagopal.bones) != []
    assert set(rajagopal.bones) == set(_body_names(RAJAGOPAL))
    assert len(rajagopal.bones) == len(_body_names(RAJAGOPAL)) == 22
    assert rajagopal.world == "opensim_ground"
    assert rajagopal.bones["pelvis"].parent is None
    assert rajagopal.bones["femur_r"].parent == "pelvis"
    assert rajagopal.bones["patella_r"].parent == "femur_r"
    assert rajagopal.bones["hand_r"].parent == "radius_r"
    # parent before child
    names = list(rajagopal.bones)
    for n, b in rajagopal.bones.items():
        if b.parent:
            assert names.index(b.parent) < names.index(n)
    meta = rajagopal.metadata
    assert meta["opensim_version"] == 40000 and meta["layout"] == "opensim4"
    assert meta["joints"]["radius_hand_r"]["type"] == "UniversalJoint"
    assert meta["missing_meshes"] == []


def test_rajagopal_body_frames_match_reference(rajagopal):
    dt, dr = _check_frames(rajagopal, OSIM / "rajagopal2016_default_pose_ply")
    assert dt < TOL_MM
    assert dr < 1e-6
    # pelvis_ty default 0.94 m: the model stands on its feet
    assert rajagopal.bones["pelvis"].bone_to_world[1, 3] == pytest.approx(940.0)


def test_rajagopal_patella_follows_the_coupler(rajagopal):
    # knee_angle_r_beta = knee_angle_r (LinearFunction 1 0) = 0 -> patella tilt = spline(0)
    assert rajagopal.metadata["coordinates"]["knee_angle_r_beta"] == 0.0
    assert rajagopal.metadata["coupled_coordinates"]["knee_angle_r_beta"] == \
        "patellofemoral_knee_angle_r_con"
    R = rajagopal.bones["patella_r"].bone_to_world[:3, :3]
    assert math.atan2(R[1, 0], R[0, 0]) == pytest.approx(0.00113686, abs=1e-9)
    # a knee angle given by the caller moves the patella through the constraint
    bent = read_osim(RAJAGOPAL, load_meshes=False, coordinates={"knee_angle_r": 1.0})
    assert bent.metadata["coordinates"]["knee_angle_r_beta"] == pytest.approx(1.0)


def test_rajagopal_markers_match_reference(rajagopal):
    rows = list(csv.DictReader((OSIM / "rajagopal2016_default_pose_ply" / "markers_in_ground.csv").open()))
    markers = rajagopal.metadata["markers"]
    assert len(markers) == len(rows) == 66
    assert all(isinstance(m, OsimMarker) for m in markers)
    by_name = {m.name: m for m in markers}
    world = markers_in_world(rajagopal)
    worst = 0.0
    for r in rows:
        m = by_name[r["marker"]]
        assert m.body == r["body"]
        body = 1000.0 * np.array([float(r[k]) for k in ("x_body", "y_body", "z_body")])
        ground = 1000.0 * np.array([float(r[k]) for k in ("x_ground", "y_ground", "z_ground")])
        worst = max(worst, np.abs(m.location - body).max(), np.abs(world[m.name] - ground).max())
    assert worst < TOL_MM
    # the stand-alone accessor gives the same list
    alone = read_osim_markers(RAJAGOPAL)
    assert [m.name for m in alone] == [m.name for m in markers]
    assert np.allclose([m.location for m in alone], [m.location for m in markers])


def test_rajagopal_meshes_match_reference_ply(rajagopal):
    ref_dir = OSIM / "rajagopal2016_default_pose_ply"
    assert _check_meshes(rajagopal, ref_dir) < TOL_MM
    # a single-file bone vertex by vertex (the .ply is in metres)
    ref, _ = _read_ply_mm(ref_dir / "femur_r__r_femur.ply")
    world = rajagopal.world_mesh("femur_r")
    assert world.vertices.shape == ref.shape
    assert np.abs(world.vertices - ref).max() < TOL_MM
    # the hand's 27 bones carry scale_factors 0.85: a wrong scale would be cm off
    mesh = rajagopal.bones["hand_r"].mesh
    assert mesh.frame == "hand_r" and len(rajagopal.bones["hand_r"].metadata["mesh_files"]) == 27


def test_rajagopal_joint_centres_agree_between_child_and_parent(rajagopal):
    femur = rajagopal.bones["femur_r"]
    pelvis = rajagopal.bones["pelvis"]
    assert set(femur.joint_centres) == {"hip_r", "walker_knee_r", "patellofemoral_r"}
    assert np.allclose(femur.joint_centres["hip_r"], 0.0)
    assert np.allclose(pelvis.joint_centres["hip_r"], [-56.276, -78.49, 77.26])
    for name, bone in rajagopal.bones.items():
        if bone.parent is None:
            continue
        parent = rajagopal.bones[bone.parent]
        (joint,) = [j for j, info in rajagopal.metadata["joints"].items() if info["child"] == name]
        assert np.allclose(bone.landmark_in_world(joint), parent.landmark_in_world(joint), atol=1e-9)
    # pin joints carry their axis in both frames
    talus = rajagopal.bones["talus_r"]
    tibia = rajagopal.bones["tibia_r"]
    a_child = talus.bone_to_world[:3, :3] @ talus.joint_axes["ankle_r"]
    a_parent = tibia.bone_to_world[:3, :3] @ tibia.joint_axes["ankle_r"]
    assert np.allclose(a_child, a_parent)


def test_virtual_markers_are_flagged(rajagopal):
    flags = {m.name: m.virtual for m in rajagopal.metadata["markers"]}
    for name in ("RHJC", "LHJC", "RKJC", "RAJC", "RSJC", "REJC", "R_tibial_plateau",
                 "L_tibial_plateau"):
        assert flags[name], name
    for name in ("RASI", "LPSI", "RLFC", "RMMAL", "RCAL", "RTOE", "C7", "RACR", "RFAradius"):
        assert not flags[name], name
    assert sum(flags.values()) == 12
    hamner = {m.name: m.virtual for m in read_osim_markers(HAMNER)}
    assert hamner["RWJC"] and hamner["LKJC"]
    assert not hamner["R.ASIS"] and not hamner["V.Sacral"] and not hamner["R.Knee.Lat"]


# --------------------------------------------------------------------------- #
# gait2392, arm26, Hamner2010
# --------------------------------------------------------------------------- #
def test_gait2392_matches_reference(gait2392):
    ref_dir = OSIM / "gait2392_default_pose_ply"
    dt, dr = _check_frames(gait2392, ref_dir)
    assert dt < TOL_MM and dr < 1e-6
    assert _check_meshes(gait2392, ref_dir) < TOL_MM
    assert len(gait2392.bones) == len(_body_names(GAIT2392)) == 12
    assert gait2392.metadata["markers"] == []


def test_arm26_loads_and_reports_missing_meshes():
    _need_data()
    with pytest.warns(UserWarning, match=r"31 mesh file\(s\) not found") as rec:
        skel = read_osim(ARM26)
    assert len([w for w in rec if "not found" in str(w.message)]) == 1  # one warning per model
    assert list(skel.bones) == ["base", "r_humerus", "r_ulna_radius_hand"]
    assert skel.bones["base"].parent is None
    assert skel.metadata["joints"]["offset"]["type"] == "WeldJoint"
    assert skel.bones["base"].bone_to_world[:3, 3] == pytest.approx([0, 800, 0])
    assert "arm_r_1mc.vtp" in skel.metadata["missing_meshes"]
    assert len(skel.metadata["missing_meshes"]) == 31
    # what exists is loaded: the humerus, the ulna and radius (hand bones missing)
    assert skel.bones["r_humerus"].mesh is not None
    assert len(skel.bones["r_ulna_radius_hand"].mesh.vertices) > 100
    # base: clavicle and scapula are there, ground_ribs/spine/skull/jaw.vtp are not
    assert skel.bones["base"].mesh is not None
    assert {"ground_ribs.vtp", "ground_jaw.vtp"} <= set(skel.metadata["missing_meshes"])
    assert [m.name for m in skel.metadata["markers"]] == ["r_acromion", "r_humerus_epicondyle",
                                                          "r_radius_styloid"]
    assert not any(m.virtual for m in skel.metadata["markers"])


def test_hamner_loads():
    _need_data()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        skel = read_osim(HAMNER)
    assert len(skel.bones) == len(_body_names(HAMNER)) == 20
    _assert_tree(skel)
    assert sum(b.mesh is not None for b in skel.bones.values()) == 20
    assert len(skel.metadata["markers"]) == 83


def _assert_tree(skel):
    roots = [n for n, b in skel.bones.items() if b.parent is None]
    assert len(roots) == 1
    for name in skel.bones:  # every bone reaches the root
        seen = set()
        while skel.bones[name].parent is not None:
            assert name not in seen
            seen.add(name)
            name = skel.bones[name].parent
        assert name == roots[0]


@pytest.mark.parametrize("path", [RAJAGOPAL, GAIT2392, HAMNER], ids=lambda p: p.stem)
def test_full_body_femur_length_is_plausible(path):
    _need_data()
    skel = read_osim(path, load_meshes=False)
    _assert_tree(skel)
    for side in "rl":
        femur = skel.bones[f"femur_{side}"]
        (hip,) = [j for j, i in skel.metadata["joints"].items() if i["child"] == f"femur_{side}"]
        (knee,) = [j for j, i in skel.metadata["joints"].items() if i["child"] == f"tibia_{side}"]
        length = np.linalg.norm(femur.joint_centres[hip] - femur.joint_centres[knee])
        assert 350 < length < 500, (path.stem, side, length)
        # the knee is below the hip in the standing default pose
        assert femur.landmark_in_world(knee)[1] < femur.landmark_in_world(hip)[1] - 350


# --------------------------------------------------------------------------- #
# Poses other than the default, against OpenSim 4.6
# --------------------------------------------------------------------------- #
# Body->ground (rotation, translation in metres) computed with the opensim 4.6
# Python package (locked coordinates unlocked, Model.initSystem,
# Coordinate.setValue, Model.assemble; the assembled values differ from these
# by < 3e-10) for these coordinate values. They check what the default pose cannot: the
# composition order of a CustomJoint's three rotations, SimmSpline
# interpolation between knots, the UniversalJoint and the patella coupler.
RAJAGOPAL_POSE = {"pelvis_tilt": 0.1, "pelvis_list": 0.2, "pelvis_rotation": 0.3, "pelvis_tx": 0.05,
                  "hip_flexion_r": 0.5, "hip_adduction_r": -0.3, "hip_rotation_r": 0.4,
                  "knee_angle_r": 1.0, "ankle_angle_r": 0.2, "subtalar_angle_r": -0.1,
                  "arm_flex_r": 0.5, "arm_add_r": -0.4, "arm_rot_r": 0.3, "elbow_flex_r": 1.0,
                  "pro_sup_r": 0.5, "wrist_flex_r": 0.3, "wrist_dev_r": 0.2}
RAJAGOPAL_OPENSIM = {
    "tibia_r": ([[0.7853358843, 0.2557590598, 0.5637684384], [-0.4340852657, 0.8767854118, 0.2069234732],
                 [-0.4413813895, -0.4072280012, 0.7995922861]], [0.2796309052, 0.5171051703, 0.0595812493]),
    "patella_r": ([[0.9005868119, -0.0340695896, 0.4333389635], [-0.1121050273, 0.9449932549, 0.3072787189],
                   [-0.4199712575, -0.3253106382, 0.8472290904]], [0.3061772744, 0.4902494063, 0.0588729263]),
    "calcn_r": ([[0.86995069, 0.0337089097, 0.4919852704], [-0.2196267821, 0.9197390032, 0.3253371214],
                 [-0.4415312826, -0.3910803951, 0.8075309599]], [0.1293205291, 0.145312618, 0.2709613024]),
    "hand_r": ([[-0.5477927522, -0.6228069241, 0.558600605], [0.7216213377, -0.0139120937, 0.6921481768],
                [-0.423303373, 0.7822518706, 0.4570517098]], [0.3841847471, 1.1050834114, 0.1924051584]),
}
GAIT2392_POSE = {"knee_angle_r": -1.0, "hip_flexion_r": 0.3, "hip_adduction_r": 0.2, "hip_rotation_r": -0.25}
GAIT2392_OPENSIM = {
    "tibia_r": ([[0.7516868635, 0.6346321383, -0.1794684048], [-0.6585278065, 0.7073101809, -0.2570086302],
                 [-0.0361661067, 0.3113749461, 0.9495986814]], [0.0502324151, 0.5058280276, 0.004030416]),
}


@pytest.mark.parametrize("path,pose,expected", [(RAJAGOPAL, RAJAGOPAL_POSE, RAJAGOPAL_OPENSIM),
                                                (GAIT2392, GAIT2392_POSE, GAIT2392_OPENSIM)],
                         ids=["Rajagopal2016", "gait2392"])
def test_pose_matches_opensim(path, pose, expected):
    _need_data()
    skel = read_osim(path, load_meshes=False, coordinates=pose)
    for body, (R, p) in expected.items():
        T = skel.bones[body].bone_to_world
        assert np.abs(T[:3, :3] - np.array(R)).max() < 1e-8, body
        assert np.abs(T[:3, 3] - 1000.0 * np.array(p)).max() < 1e-5, body


def test_unknown_coordinate_override_is_refused():
    _need_data()
    with pytest.raises(KeyError, match="no_such_coordinate"):
        read_osim(GAIT2392, load_meshes=False, coordinates={"no_such_coordinate": 1.0})


# --------------------------------------------------------------------------- #
# SimmSpline
# --------------------------------------------------------------------------- #
def test_simmspline_reproduces_a_cubic_unlike_a_natural_spline():
    from scipy.interpolate import CubicSpline

    x = np.array([-1.0, -0.2, 0.5, 1.0, 2.2, 3.0])
    f = lambda t: 0.3 * t**3 - t**2 + 0.5 * t + 2.0  # noqa: E731
    s = SimmSpline(x, f(x))
    t = np.linspace(-1.0, 3.0, 57)
    assert np.allclose([s(v) for v in t], f(t), atol=1e-12)
    natural = CubicSpline(x, f(x), bc_type="natural")
    assert np.abs(natural(t) - f(t)).max() > 1e-2  # the end conditions matter
    # knots are interpolated exactly; outside, straight along the end tangents
    assert [s(v) for v in x] == pytest.approx(f(x), abs=1e-14)
    slope0 = 0.9 * 1.0 + 2.0 + 0.5  # f'(-1)
    assert s(-2.0) == pytest.approx(f(-1.0) - slope0, abs=1e-9)
    slope1 = 0.9 * 9.0 - 6.0 + 0.5  # f'(3)
    assert s(4.0) == pytest.approx(f(3.0) + slope1, abs=1e-9)
    assert SimmSpline(np.array([0.0, 2.0]), np.array([1.0, 5.0]))(3.0) == pytest.approx(7.0)


# --------------------------------------------------------------------------- #
# Synthetic models: both XML layouts, offset frames, errors
# --------------------------------------------------------------------------- #
def _rot(axis, a):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(a) * K + (1 - math.cos(a)) * K @ K


def _T(R=np.eye(3), t=(0, 0, 0)):
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def _euler(a, b, c, t=(0, 0, 0)):
    return _T(_rot([1, 0, 0], a) @ _rot([0, 1, 0], b) @ _rot([0, 0, 1], c), t)


SPATIAL = """
<TransformAxis name="rotation1"><coordinates>q1</coordinates><axis>0 0 1</axis>{lin}</TransformAxis>
<TransformAxis name="rotation2"><coordinates>q2</coordinates><axis>2 0 0</axis>{mult}</TransformAxis>
<TransformAxis name="rotation3"><coordinates></coordinates><axis>0 1 0</axis>{const}</TransformAxis>
<TransformAxis name="translation1"><coordinates>q1</coordinates><axis>1 0 0</axis>{poly}</TransformAxis>
<TransformAxis name="translation2"><coordinates>q2</coordinates><axis>0 1 0</axis>{spline}</TransformAxis>
<TransformAxis name="translation3"><coordinates></coordinates><axis>0 0 1</axis>{zero}</TransformAxis>
"""


def _spatial(v4: bool) -> str:
    def fn(body):  # OpenSim 4 names the function "function"; OpenSim 3 wraps it in <function>
        tag = body.split(">", 1)[0][1:]
        if v4:
            return body.replace(f"<{tag}>", f'<{tag} name="function">', 1)
        return f"<function>{body}</function>"

    return SPATIAL.format(
        lin=fn("<LinearFunction><coefficients>1 0</coefficients></LinearFunction>"),
        mult=fn("<MultiplierFunction><function><LinearFunction><coefficients>1 0</coefficients>"
                "</LinearFunction></function><scale>2</scale></MultiplierFunction>"),
        const=fn("<Constant><value>0.25</value></Constant>"),
        poly=fn("<PolynomialFunction><coefficients>1 0 0.01</coefficients></PolynomialFunction>"),
        # 0.1 x^3 sampled at 4 points: a SimmSpline gives back the cubic exactly
        spline=fn("<SimmSpline><x>-1 0 1 2</x><y>-0.1 0 0.1 0.8</y></SimmSpline>"),
        zero=fn("<Constant><value>0</value></Constant>"))


MODEL_V4 = """<?xml version="1.0" encoding="UTF-8" ?>
<OpenSimDocument Version="40000">
<Model name="mini">
 <Ground name="ground"/>
 <length_units>meters</length_units>
 <BodySet name="bodyset"><objects>
  <Body name="a"><mass>2.5</mass>
   <attached_geometry><Mesh name="a_geom"><socket_frame>..</socket_frame>
     <scale_factors>1 2 1</scale_factors><mesh_file>box.ply</mesh_file></Mesh></attached_geometry>
   <components><PhysicalOffsetFrame name="a_deco"><socket_parent>..</socket_parent>
     <translation>0.01 0 0</translation><orientation>0 0 1.5707963267948966</orientation>
     <attached_geometry><Mesh name="a_geom2"><socket_frame>..</socket_frame>
       <scale_factors>1 1 1</scale_factors><mesh_file>box.ply</mesh_file></Mesh></attached_geometry>
   </PhysicalOffsetFrame></components>
  </Body>
  <Body name="b"><attached_geometry><Mesh name="b_geom"><socket_frame>..</socket_frame>
     <mesh_file>absent.vtp</mesh_file></Mesh></attached_geometry></Body>
 </objects></BodySet>
 <JointSet name="jointset"><objects>
  <CustomJoint name="j1">
   <socket_parent_frame>ground_offset</socket_parent_frame>
   <socket_child_frame>a_offset</socket_child_frame>
   <coordinates>
    <Coordinate name="q1"><default_value>0.3</default_value></Coordinate>
    <Coordinate name="q2"><default_value>-0.7</default_value></Coordinate>
   </coordinates>
   <frames>
    <PhysicalOffsetFrame name="ground_offset"><socket_parent>/ground</socket_parent>
     <translation>0.1 0.2 0.3</translation><orientation>0.1 0.2 0.3</orientation></PhysicalOffsetFrame>
    <PhysicalOffsetFrame name="a_offset"><socket_parent>/bodyset/a</socket_parent>
     <translation>0 0.05 0</translation><orientation>-0.2 0 0.4</orientation></PhysicalOffsetFrame>
   </frames>
   <SpatialTransform>{spatial}</SpatialTransform>
  </CustomJoint>
  <{pin} name="j2">
   <socket_parent_frame>a_offset</socket_parent_frame>
   <socket_child_frame>b_offset</socket_child_frame>
   <coordinates><Coordinate name="q3"><default_value>0.5</default_value></Coordinate></coordinates>
   <frames>
    <PhysicalOffsetFrame name="a_offset"><socket_parent>/bodyset/a</socket_parent>
     <translation>0 -0.4 0</translation><orientation>0.3 0 0</orientation></PhysicalOffsetFrame>
    <PhysicalOffsetFrame name="b_offset"><socket_parent>/bodyset/b</socket_parent>
     <translation>0 0.02 0.01</translation><orientation>0.3 0 0</orientation></PhysicalOffsetFrame>
   </frames>
  </{pin}>
 </objects></JointSet>
 <MarkerSet name="markerset"><objects>
  <Marker name="M1"><socket_parent_frame>/bodyset/b</socket_parent_frame>
   <location>0.01 0.02 0.03</location><fixed>true</fixed></Marker>
  <Marker name="KNEE"><socket_parent_frame>/bodyset/b</socket_parent_frame>
   <location>0 0.0202 0.0101</location><fixed>false</fixed></Marker>
 </objects></MarkerSet>
</Model>
</OpenSimDocument>
"""

MODEL_V3 = """<?xml version="1.0" encoding="UTF-8"?>
<OpenSimDocument Version="30000">
<Model name="mini3">
 <length_units>meters</length_units>
 <BodySet><objects>
  <Body name="ground"><mass>0</mass><Joint/></Body>
  <Body name="a"><mass>2.5</mass>
   <Joint><CustomJoint name="j1">
    <parent_body>ground</parent_body>
    <location_in_parent>0.1 0.2 0.3</location_in_parent>
    <orientation_in_parent>0.1 0.2 0.3</orientation_in_parent>
    <location>0 0.05 0</location><orientation>-0.2 0 0.4</orientation>
    <CoordinateSet><objects>
     <Coordinate name="q1"><motion_type>rotational</motion_type><default_value>0.3</default_value></Coordinate>
     <Coordinate name="q2"><motion_type>rotational</motion_type><default_value>-0.7</default_value></Coordinate>
    </objects></CoordinateSet>
    <reverse>false</reverse>
    <SpatialTransform>{spatial}</SpatialTransform>
   </CustomJoint></Joint>
   <VisibleObject><GeometrySet><objects>
     <DisplayGeometry><geometry_file>box.ply</geometry_file><transform>0 0 0 0 0 0</transform>
      <scale_factors>1 2 1</scale_factors></DisplayGeometry>
     <DisplayGeometry><geometry_file>box.ply</geometry_file><transform>0 0 1.5707963267948966 0.01 0 0</transform>
      <scale_factors>1 1 1</scale_factors></DisplayGeometry>
    </objects></GeometrySet>
    <scale_factors>1 1 1</scale_factors><transform>0 0 0 0 0 0</transform></VisibleObject>
  </Body>
  <Body name="b">
   <Joint><PinJoint name="j2">
    <parent_body>a</parent_body>
    <location_in_parent>0 -0.4 0</location_in_parent><orientation_in_parent>0.3 0 0</orientation_in_parent>
    <location>0 0.02 0.01</location><orientation>0.3 0 0</orientation>
    <CoordinateSet><objects><Coordinate name="q3"><default_value>0.5</default_value></Coordinate></objects></CoordinateSet>
   </PinJoint></Joint>
   <VisibleObject><geometry_files>absent.vtp</geometry_files></VisibleObject>
  </Body>
 </objects></BodySet>
 <MarkerSet><objects>
  <Marker name="M1"><body>b</body><location>0.01 0.02 0.03</location><fixed>true</fixed></Marker>
  <Marker name="KNEE"><body>b</body><location>0 0.0202 0.0101</location><fixed>false</fixed></Marker>
 </objects></MarkerSet>
</Model>
</OpenSimDocument>
"""


def _expected_mini():
    """Body->ground of the mini model in mm, composed by hand."""
    q1, q2, q3 = 0.3, -0.7, 0.5
    R = _rot([0, 0, 1], q1) @ _rot([1, 0, 0], 2 * q2) @ _rot([0, 1, 0], 0.25)  # body-fixed 1, 2, 3
    t = [q1**2 + 0.01, 0.1 * q2**3, 0.0]  # in the parent offset frame, not rotated
    a = _euler(0.1, 0.2, 0.3, (0.1, 0.2, 0.3)) @ _T(R, t) @ np.linalg.inv(_euler(-0.2, 0, 0.4, (0, 0.05, 0)))
    b = a @ _euler(0.3, 0, 0, (0, -0.4, 0)) @ _T(_rot([0, 0, 1], q3)) @ np.linalg.inv(
        _euler(0.3, 0, 0, (0, 0.02, 0.01)))
    for T in (a, b):
        T[:3, 3] *= 1000.0
    return a, b


def _write_box(folder: Path) -> None:
    """``box.ply``: a 20 x 40 x 60 mm box centred on the origin, in metres."""
    import trimesh

    folder.mkdir(parents=True, exist_ok=True)
    trimesh.creation.box(extents=(0.02, 0.04, 0.06)).export(folder / "box.ply")


def _write_model(folder: Path, text: str, geometry: str | None = "Geometry") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "mini.osim"
    path.write_text(text)
    if geometry:
        _write_box(folder / geometry)
    return path


def _assert_same_points(a, b, tol=1e-3):
    """Same point sets (any order); the .ply stores float32."""
    d = np.linalg.norm(a[:, None, :] - b[None, :, :], axis=2)
    assert a.shape == b.shape and d.min(axis=0).max() < tol and d.min(axis=1).max() < tol


@pytest.mark.parametrize("layout", ["opensim4", "opensim3"])
def test_synthetic_model_both_layouts(tmp_path, layout):
    text = (MODEL_V4.replace("{spatial}", _spatial(True)).replace("{pin}", "PinJoint")
            if layout == "opensim4" else MODEL_V3.replace("{spatial}", _spatial(False)))
    # the shared layout: models/ beside Geometry/
    path = _write_model(tmp_path / "models", text, geometry=None)
    _write_box(tmp_path / "Geometry")
    with pytest.warns(UserWarning, match="absent.vtp") as rec:
        skel = read_osim(path)
    assert len(rec) == 1
    assert skel.metadata["layout"] == layout
    assert list(skel.bones) == ["a", "b"]
    assert skel.bones["a"].parent is None and skel.bones["b"].parent == "a"
    a, b = _expected_mini()
    assert np.allclose(skel.bones["a"].bone_to_world, a, atol=1e-9)
    assert np.allclose(skel.bones["b"].bone_to_world, b, atol=1e-9)
    assert skel.bones["a"].metadata["mass"] == 2.5
    # meshes: box scaled (1, 2, 1) at the origin + box turned 90 deg about z, 10 mm along x
    mesh = skel.bones["a"].mesh
    assert mesh.frame == "a" and len(mesh.vertices) == 16
    box = np.array([[x, y, z] for x in (-10, 10) for y in (-20, 20) for z in (-30, 30)], float)
    _assert_same_points(mesh.vertices[:8], box * [1, 2, 1])
    _assert_same_points(mesh.vertices[8:], box @ _rot([0, 0, 1], math.pi / 2).T + [10, 0, 0])
    assert skel.bones["b"].mesh is None
    assert skel.metadata["missing_meshes"] == ["absent.vtp"]
    # joint centres: the child offset origin, the same point in the parent
    assert np.allclose(skel.bones["b"].joint_centres["j2"], [0, 20, 10])
    assert np.allclose(skel.bones["a"].landmark_in_world("j2"), skel.bones["b"].landmark_in_world("j2"))
    assert np.allclose(skel.bones["b"].joint_axes["j2"], _rot([1, 0, 0], 0.3)[:, 2])
    # markers: mm in the body frame; KNEE sits 0.22 mm from j2's centre -> virtual
    m1, knee = skel.metadata["markers"]
    assert (m1.name, m1.body, m1.fixed, m1.virtual) == ("M1", "b", True, False)
    assert np.allclose(m1.location, [10, 20, 30])
    assert knee.virtual and not knee.fixed
    w = markers_in_world(skel)
    assert np.allclose(w["M1"], b[:3, :3] @ [10, 20, 30] + b[:3, 3])


def test_geometry_dir_argument_and_no_meshes(tmp_path):
    text = MODEL_V4.replace("{spatial}", _spatial(True)).replace("{pin}", "PinJoint")
    path = _write_model(tmp_path / "m", text, geometry="meshes_here")
    with pytest.warns(UserWarning, match=r"2 mesh file\(s\) not found"):  # box.ply and absent.vtp
        assert read_osim(path).bones["a"].mesh is None  # no Geometry/ next to the model
    with pytest.warns(UserWarning, match="absent.vtp"):
        skel = read_osim(path, tmp_path / "m" / "meshes_here")
    assert len(skel.bones["a"].mesh.vertices) == 16
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        bare = read_osim(path, load_meshes=False)
    assert all(b.mesh is None for b in bare.bones.values())
    assert bare.bones["a"].metadata["mesh_files"] == ["box.ply", "box.ply"]
    with pytest.raises(InputError, match="geometry folder"):
        read_osim(path, tmp_path / "nowhere")


def test_unsupported_joint_type_is_named(tmp_path):
    text = MODEL_V4.replace("{spatial}", _spatial(True)).replace("{pin}", "EllipsoidJoint")
    path = _write_model(tmp_path, text, geometry=None)
    with pytest.raises(UnsupportedModelError, match=r"EllipsoidJoint.*'j2'") as exc:
        read_osim(path, load_meshes=False)
    assert str(path) in str(exc.value)
    assert isinstance(exc.value, InputError)


def test_unsupported_function_type_is_named(tmp_path):
    text = MODEL_V4.replace("{spatial}", _spatial(True)).replace("{pin}", "PinJoint")
    text = text.replace('<SimmSpline name="function">', '<GCVSpline name="function">').replace(
        "</SimmSpline>", "</GCVSpline>")
    path = _write_model(tmp_path, text, geometry=None)
    with pytest.raises(UnsupportedModelError, match=r"GCVSpline.*j1|j1.*GCVSpline"):
        read_osim(path, load_meshes=False)


def test_truncated_xml_is_a_format_error(tmp_path):
    _need_data()
    bad = tmp_path / "truncated.osim"
    bad.write_bytes(RAJAGOPAL.read_bytes()[:20000])
    with pytest.raises(FormatError, match="not well-formed XML") as exc:
        read_osim(bad)
    assert str(bad) in str(exc.value)


def test_xml_that_is_not_a_model_is_a_format_error(tmp_path):
    bad = tmp_path / "setup.osim"
    bad.write_text('<?xml version="1.0"?><OpenSimDocument Version="40000"><IKTool name="ik"/>'
                   "</OpenSimDocument>")
    with pytest.raises(FormatError, match="not an OpenSim model") as exc:
        read_osim(bad)
    assert str(bad) in str(exc.value)
    other = tmp_path / "doc.osim"
    other.write_text("<html><body/></html>")
    with pytest.raises(FormatError, match="not an OpenSim model"):
        read_osim_markers(other)
    with pytest.raises(InputError, match="no such file"):
        read_osim(tmp_path / "missing.osim")


def test_dangling_frame_reference_is_a_format_error(tmp_path):
    text = MODEL_V4.replace("{spatial}", _spatial(True)).replace("{pin}", "PinJoint")
    text = text.replace("<socket_child_frame>b_offset</socket_child_frame>",
                        "<socket_child_frame>nowhere_offset</socket_child_frame>")
    path = _write_model(tmp_path, text, geometry=None)
    with pytest.raises(FormatError, match="nowhere_offset"):
        read_osim(path, load_meshes=False)


def test_mirroring_scale_keeps_faces_outward(tmp_path):
    text = MODEL_V4.replace("{spatial}", _spatial(True)).replace("{pin}", "PinJoint")
    text = text.replace("<scale_factors>1 2 1</scale_factors>", "<scale_factors>-1 2 1</scale_factors>")
    path = _write_model(tmp_path, text)
    with pytest.warns(UserWarning, match="absent.vtp"):
        mesh = read_osim(path).bones["a"].mesh
    # signed volumes of the two boxes: 20 x 80 x 60 (mirrored) + 20 x 40 x 60 mm
    assert mesh.to_trimesh().volume == pytest.approx(96000 + 48000, rel=1e-6)
