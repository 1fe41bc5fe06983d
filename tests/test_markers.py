"""Marker sets: loading, inheritance, label matching, errors, placement."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from bonecap.errors import DataError, FormatError, InputError
from bonecap.markers import (available_marker_sets, check_marker_set, load_marker_set, match_labels,
                             place_markers)
from bonecap.model import Bone, Mesh, Skeleton

PIG_39 = """LFHD RFHD LBHD RBHD C7 T10 CLAV STRN RBAK LSHO LUPA LELB LFRM LWRA LWRB LFIN RSHO RUPA RELB
RFRM RWRA RWRB RFIN LASI RASI LPSI RPSI LTHI LKNE LTIB LANK LHEE LTOE RTHI RKNE RTIB RANK RHEE RTOE""".split()


def test_shipped_sets():
    assert {"plug_in_gait_full_body", "kojima_paper"} <= set(available_marker_sets())


def test_plug_in_gait_has_the_39_markers():
    pig = load_marker_set("plug_in_gait_full_body")
    assert sorted(pig.physical) == sorted(PIG_39)
    assert pig.markers["SACR"].optional
    for m in pig.markers.values():
        assert m.bone and m.landmark and m.tracks and m.offset_mm > 0


def test_paper_set_extends_pig_with_distinct_names():
    paper = load_marker_set("kojima_paper")
    assert set(PIG_39) <= set(paper.physical)
    added = set(paper.physical) - set(PIG_39)
    assert {"RSHA", "RSHP", "RELA", "RELP", "RMEP", "LMEP", "RIPIP", "RIDIP", "RRPIP", "RRDIP"} <= added
    # PiG's RSHO stays the acromion marker, RELB the lateral epicondyle.
    assert paper.markers["RSHO"].landmark == "acromion"
    assert paper.markers["RELB"].landmark == "lateral_epicondyle"
    rule = paper.paper_solver["humerus_r"]
    assert rule["proximal"]["pair"] == ["RSHA", "RSHP"] and rule["twist"] == ["RELP", "RELA"]
    # Every marker named by the solver table exists in the set.
    for bone, r in paper.paper_solver.items():
        named = list(r["twist"])
        for end in ("proximal", "distal"):
            named += r[end].get("pair", []) + ([r[end]["marker"]] if "marker" in r[end] else [])
        assert set(named) <= set(paper.markers), bone


def test_match_labels_uses_aliases_and_ignores_case():
    pig = load_marker_set("plug_in_gait_full_body")
    found = match_labels(pig, ["lasi", "R.ASIS", "RKNEE", "Unrelated"])
    assert found == {"LASI": "lasi", "RASI": "R.ASIS", "RKNE": "RKNEE"}


def test_unknown_set_and_bad_yaml(tmp_path):
    with pytest.raises(InputError, match="unknown marker set"):
        load_marker_set("no_such_set")
    bad = tmp_path / "bad.yaml"
    bad.write_text("markers:\n  X: {landmark: foo}\n")
    with pytest.raises(FormatError, match="bone"):
        load_marker_set(bad)
    loop = tmp_path / "loop.yaml"
    loop.write_text("name: loop\nextends: " + str(loop) + "\nmarkers: {}\n")
    with pytest.raises(FormatError, match="loop"):
        load_marker_set(loop)


def _box_skeleton() -> Skeleton:
    box = trimesh.creation.box(extents=[20.0, 20.0, 20.0])
    mesh = Mesh(box.vertices, box.faces)
    T = np.eye(4)
    T[:3, 3] = [100.0, 0.0, 0.0]
    bone = Bone("block", mesh=mesh, bone_to_world=T, landmarks={"top": [0.0, 0.0, 10.0], "side": [10.0, 0, 0]})
    return Skeleton({"block": bone})


def test_place_markers_pushes_along_the_surface_normal(tmp_path):
    ms = tmp_path / "ms.yaml"
    ms.write_text("name: t\nmarkers:\n  TOP: {bone: block, landmark: top, offset_mm: 7}\n"
                  "  SIDE: {bone: block, landmark: side, offset_mm: 3}\n")
    placed = place_markers(load_marker_set(ms), _box_skeleton())
    assert np.allclose(placed["TOP"], [100.0, 0.0, 17.0])
    assert np.allclose(placed["SIDE"], [113.0, 0.0, 0.0])


def test_missing_landmark_is_a_clear_error(tmp_path):
    ms = tmp_path / "ms.yaml"
    ms.write_text("name: t\nmarkers:\n  A: {bone: block, landmark: nowhere}\n  B: {bone: femur_r, landmark: x}\n")
    with pytest.raises(DataError) as exc:
        check_marker_set(load_marker_set(ms), _box_skeleton())
    msg = str(exc.value)
    assert "A: bone 'block' has no landmark 'nowhere'" in msg and "B: no bone 'femur_r'" in msg


def test_opensim_marker_set_places_like_opensim(shared_data):
    """Rajagopal2016's MarkerSet as a marker set: 66 markers, 12 virtual, placed where
    the independently derived ground coordinates put them."""
    import csv

    from bonecap.skeleton.opensim import read_osim

    osim = shared_data / "bones/opensim/models/Rajagopal2016.osim"
    ms = load_marker_set(osim)
    assert len(ms.markers) == 66
    virtual = {n for n, m in ms.markers.items() if m.virtual}
    assert len(virtual) == 12 and "RKJC" in virtual and "RASI" not in virtual
    assert set(ms.physical) == set(ms.markers) - virtual
    placed = place_markers(ms, read_osim(osim, load_meshes=False), names=list(ms.markers))
    rows = list(csv.DictReader(open(shared_data / "bones/opensim/rajagopal2016_default_pose_ply/markers_in_ground.csv")))
    assert len(rows) == 66
    cols = [c for c in rows[0] if "ground" in c.lower()]
    assert len(cols) == 3, rows[0].keys()
    for r in rows:
        ref = np.array([float(r[c]) for c in cols]) * 1000.0  # metres -> mm
        assert np.allclose(placed[r[next(iter(r))]], ref, atol=0.1), r


def test_limb_markers_sit_beside_the_shaft_not_over_the_bone_end():
    """On a limb's long bone the push is away from the shaft axis: a landmark at the bone's tip
    (a styloid) moves sideways, not along the limb; one on the shaft moves radially even where
    the surface normal leans (a ridge)."""
    from bonecap.markers import limb_side_directions

    # a 300 mm cylinder of radius 12 mm along y, as a point cloud (its principal axis is y)
    t = np.linspace(0, 2 * np.pi, 48, endpoint=False)
    y = np.linspace(-150, 150, 61)
    V = np.array([[12 * np.cos(a), yy, 12 * np.sin(a)] for yy in y for a in t])
    tip = np.array([[8.0, 150.0, 0.0]])            # near the end, 8 mm off the axis
    ridge = np.array([[0.0, 20.0, 12.0]])          # on the shaft, +z side
    leaning = np.array([[0.0, 1.0, 0.0], [-0.7, 0.0, 0.714]])  # normals: along the limb; leaning posteriorly
    d = limb_side_directions(V, np.vstack([tip, ridge]), leaning)
    assert np.allclose(d[0], [1.0, 0.0, 0.0], atol=1e-6)
    assert np.allclose(d[1], [0.0, 0.0, 1.0], atol=1e-6)
    # on the axis: the normal without its axial part
    d = limb_side_directions(V, np.array([[0.0, 150.0, 0.0]]), np.array([[0.6, 0.8, 0.0]]))
    assert np.allclose(d[0], [1.0, 0.0, 0.0], atol=1e-6)


def test_pig_limb_markers_on_the_generic_skeleton_point_sideways():
    """Thigh, knee, shank and wrist markers of Plug-in Gait leave their bone perpendicular to its
    long axis (within 35 deg), on the anatomical side: thigh and knee lateral, wrist markers
    beside the styloids (the wrist markers once sat 9 cm up the forearm, pushed along it)."""
    from bonecap.skeleton.generic import build_generic_skeleton

    sk = build_generic_skeleton()
    ms = load_marker_set("plug_in_gait_full_body")
    names = ["RTHI", "LTHI", "RKNE", "LKNE", "RWRA", "RWRB", "LWRA", "LWRB", "RUPA", "RTIB"]
    placed = place_markers(ms, sk, names)
    for n in names:
        b = sk.bones[ms.markers[n].bone]
        lm = b.landmark_in_world(ms.markers[n].landmark)
        d = placed[n] - lm
        d /= np.linalg.norm(d)
        y_axis = b.bone_to_world[:3, 1]
        assert abs(d @ y_axis) < np.sin(np.radians(35)), n
        if n[1:] in ("THI", "KNE", "UPA"):
            lateral = b.bone_to_world[:3, 2] * (1 if n[0] == "R" else -1)   # ISB Z points right on both sides
            assert d @ lateral > 0.7, n


def test_midline_landmarks_push_within_the_sagittal_plane():
    """On a midline bone a landmark on the sagittal plane (|Z| < 5 mm) leaves it within that plane:
    the left-right part of a leaning normal is removed; off the plane, or a normal pointing
    sideways, stays as it is."""
    from bonecap.markers import midline_directions

    pts = np.array([[0.0, 0.0, 0.5], [0.0, 0.0, 30.0], [0.0, 0.0, 0.0]])
    normals = np.array([[0.38, 0.9, -0.23], [0.38, 0.9, -0.23], [0.0, 0.1, 0.995]])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    d = midline_directions(pts, normals)
    assert np.allclose(d[0], np.array([0.38, 0.9, 0.0]) / np.hypot(0.38, 0.9))
    assert np.allclose(d[1:], normals[1:])


def test_pig_midline_markers_on_the_generic_skeleton_stay_on_the_midline():
    """C7, T10, CLAV, STRN and SACR leave their bones in the sagittal plane: the decimated
    template's C7 normal leaned 22 deg to one side (a ray along it met the skin 20-30 mm off the
    midline on the phantoms)."""
    from bonecap.skeleton.generic import build_generic_skeleton

    sk = build_generic_skeleton()
    ms = load_marker_set("plug_in_gait_full_body")
    names = ["C7", "T10", "CLAV", "STRN", "SACR"]
    placed = place_markers(ms, sk, names)
    for n in names:
        b = sk.bones[ms.markers[n].bone]
        lm = b.landmark_in_world(ms.markers[n].landmark)
        d = b.bone_to_world[:3, :3].T @ (placed[n] - lm)
        assert np.linalg.norm(d) == pytest.approx(ms.markers[n].offset_mm), n
        assert abs(d[2]) < 1e-6 * ms.markers[n].offset_mm, (n, d)


def test_pig_trunk_markers_leave_tips_and_notches_straight_back_or_forward():
    """The trunk's markers over a process tip or a notch leave it straight back (C7, T10, SACR, PSIS)
    or straight forward (CLAV, STRN, ASIS) in the bone frame, as the manual places them over the
    landmark: the surface normal there is ill-conditioned -- on the template the xiphoid's points
    down the abdomen and the jugular notch's up into the neck, and on phantom subjects these
    normals lay 7-66 deg from the template's."""
    from bonecap.skeleton.generic import build_generic_skeleton

    sk = build_generic_skeleton()                  # the meshes come from the in-process cache
    ms = load_marker_set("plug_in_gait_full_body")
    back, front = ["C7", "T10", "SACR", "LPSI", "RPSI"], ["CLAV", "STRN", "LASI", "RASI"]
    placed = place_markers(ms, sk, back + front)
    for n in back + front:
        b = sk.bones[ms.markers[n].bone]
        d = b.bone_to_world[:3, :3].T @ (placed[n] - b.landmark_in_world(ms.markers[n].landmark))
        assert np.allclose(d / np.linalg.norm(d), [-1.0 if n in back else 1.0, 0.0, 0.0], atol=1e-9), (n, d)
    from bonecap.markers import _nearest_surface_normals

    st = sk.bones["sternum"]
    n_px, n_ij = _nearest_surface_normals(st.mesh.vertices, st.mesh.faces,
                                          np.array([st.landmarks["xiphoid"], st.landmarks["jugular_notch"]]))
    assert n_px[1] < -0.7 and n_ij[1] > 0.7, (n_px, n_ij)


def test_surface_extreme_with_the_seed_inside_a_thick_bone():
    """A seed on a shaft's axis with no vertex within the radius: the most lateral point at the
    seed's level, not the nearest vertex (which may be on the medial side)."""
    from bonecap.skeleton.shapes import surface_extreme

    t = np.linspace(0, 2 * np.pi, 36, endpoint=False)
    V = np.array([[14 * np.cos(a), yy, 14 * np.sin(a)] for yy in np.linspace(-100, 100, 21) for a in t])
    V[5] += [0.0, 0.0, -0.01]                       # nudge: a nearest vertex that is not lateral
    p = surface_extreme(V, [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], radius=10.0)
    assert p[2] == pytest.approx(14.0) and abs(p[1]) <= 10.0


def test_direction_words_place_the_marker_that_way(tmp_path):
    """``direction:`` in a set (bone frame: X anterior, Y up, Z right) beats the surface normal;
    lateral/medial follow the bone's side suffix; bad words and side-less lateral are clear errors."""
    ms = tmp_path / "ms.yaml"
    ms.write_text("name: t\nmarkers:\n  TOP: {bone: block, landmark: top, offset_mm: 7, direction: anterior}\n"
                  "  SIDE: {bone: block, landmark: side, offset_mm: 3, direction: [0, 0, -2]}\n")
    placed = place_markers(load_marker_set(ms), _box_skeleton())
    # top landmark (100, 0, 10) pushed along +X, not along its +Z normal
    assert np.allclose(placed["TOP"], [107.0, 0.0, 10.0])
    assert np.allclose(placed["SIDE"], [110.0, 0.0, -3.0])
    m = load_marker_set("plug_in_gait_full_body").markers
    assert np.allclose(m["RTHI"].direction, [0, 0, 1]) and np.allclose(m["LTHI"].direction, [0, 0, -1])
    assert np.allclose(m["RWRB"].direction, [0, 0, -1]) and np.allclose(m["LHEE"].direction, [-1, 0, 0])
    for bad, msg in (("direction: sideways", "unknown direction word"), ("direction: lateral", "needs a side"),
                     ("direction: [0, 0, 0]", "zero")):
        ms.write_text("name: t\nmarkers:\n  TOP: {bone: block, landmark: top, offset_mm: 7, " + bad + "}\n")
        with pytest.raises(FormatError, match=msg):
            load_marker_set(ms)


def test_a_measured_joint_width_sets_the_markers_depth_along_the_joint_axis(tmp_path):
    """Plug-in Gait's chord rule: the marker ends ``width / 2 + marker radius`` from the joint centre along
    the joint axis (whichever sign the template gave the axis), keeps its place around the axis, and stays
    where it was without the measurement; names match as Nexus (LKneeWidth) or a VSK (LeftKneeWidth) write them."""
    from bonecap.markers import joint_centre_axis, joint_width_placement, subject_parameter

    R = Rotation.from_euler("xyz", [20, -35, 50], degrees=True).as_matrix()
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, [10.0, 400.0, -30.0]
    thigh = Bone("thigh", bone_to_world=T, joint_centres={"knee": [0.0, -400.0, 0.0]},
                 landmarks={"lat": [3.0, -398.0, 45.0]})
    T2 = T.copy()
    T2[:3, 3] = T[:3, :3] @ [0.0, -400.0, 0.0] + T[:3, 3]
    shank = Bone("shank", parent="thigh", bone_to_world=T2, joint_centres={"knee": [0.0, 0.0, 0.0]},
                 joint_axes={"knee": [0.0, 0.0, -1.0]})        # pointing medially: the marker's side wins
    sk = Skeleton({"thigh": thigh, "shank": shank})
    ms = tmp_path / "ms.yaml"
    ms.write_text("name: t\nmarkers:\n  LKNE: {bone: thigh, landmark: lat, offset_mm: 5, direction: [0, 0, 1], "
                  "width: {parameter: LKneeWidth, joint: knee}}\n  OTHER: {bone: thigh, landmark: lat}\n")
    mset = load_marker_set(ms)
    assert mset.markers["LKNE"].width == ("LKneeWidth", "knee")
    placed = place_markers(mset, sk)
    centre, axis = joint_centre_axis(sk, "thigh", "knee")
    assert np.allclose(centre, T[:3, :3] @ [0.0, -400.0, 0.0] + T[:3, 3])
    assert abs(abs(axis @ (R @ [0, 0, 1.0])) - 1) < 1e-12
    for params, diameter in (({"LKNEEWIDTH": 130.0}, 14.0), ({"LeftKneeWidth": 130.0, "MARKERDIAMETER": 25.0}, 25.0)):
        new, report = joint_width_placement(mset, sk, placed, params)
        local = R.T @ (new["LKNE"] - centre)
        assert local[2] == pytest.approx(65.0 + diameter / 2)            # along the axis, laterally
        assert np.allclose(local[:2], (R.T @ (placed["LKNE"] - centre))[:2])     # around the axis: unchanged
        assert np.array_equal(new["OTHER"], placed["OTHER"])
        assert report["LKNE"]["depth_mm"] == pytest.approx(65.0 + diameter / 2)
    same, report = joint_width_placement(mset, sk, placed, {"RKNEEWIDTH": 130.0, "LKNEEWIDTH": 0.0})
    assert report == {} and all(np.array_equal(same[n], placed[n]) for n in placed)
    assert subject_parameter({"LEFTKNEEWIDTH": 101.0}, "LKneeWidth") == 101.0
    assert subject_parameter({"RKNEEWIDTH": 99.0}, "RightKneeWidth") == 99.0
    with pytest.raises(ValueError, match="LKneeWidth = 1300 mm is not a joint width"):
        joint_width_placement(mset, sk, placed, {"LKNEEWIDTH": 1300.0})
    with pytest.raises(ValueError, match="no centre and axis of joint 'ankle'"):
        joint_centre_axis(sk, "thigh", "ankle")
    ms.write_text("name: t\nmarkers:\n  LKNE: {bone: thigh, landmark: lat, width: LKneeWidth}\n")
    with pytest.raises(FormatError, match="'width' needs"):
        load_marker_set(ms)
