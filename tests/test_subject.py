"""The subject folder format and the bone-by-bone scaling of the no-MRI path."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bonecap.errors import FormatError, InputError
from bonecap.model import Bone, Mesh, Skeleton
from bonecap.scaling import fit_scale_factors, scale_skeleton, similarity_fit
from bonecap.subject import MarkerBinding, Subject, read_subject, write_subject


def _box(size=(40.0, 200.0, 30.0)) -> Mesh:
    import trimesh

    tm = trimesh.creation.box(extents=size)
    tm.apply_translation([0, -size[1] / 2, 0])
    return Mesh(np.asarray(tm.vertices), np.asarray(tm.faces))


def chain() -> Skeleton:
    """pelvis -> thigh -> shank, frames turned arbitrarily, joints at the segment ends."""
    rng = np.random.default_rng(4)
    bones = {}
    T0 = np.eye(4)
    T0[:3, :3] = Rotation.from_rotvec(rng.normal(size=3) * 0.3).as_matrix()
    T0[:3, 3] = [10, 900, -20]
    bones["pelvis"] = Bone("pelvis", None, _box((200, 100, 150)), T0,
                           joint_centres={"hip": [0, -80, 80]}, landmarks={"asis": [60, 0, 110]})
    # thigh hangs from the hip, 400 mm long
    T1 = np.eye(4)
    T1[:3, :3] = T0[:3, :3] @ Rotation.from_rotvec([0.1, 0, 0.2]).as_matrix()
    T1[:3, 3] = T0[:3, :3] @ np.array([0, -80, 80]) + T0[:3, 3]
    bones["thigh"] = Bone("thigh", "pelvis", _box((50, 400, 50)), T1,
                          joint_centres={"hip": [0, 0, 0], "knee": [0, -400, 0]},
                          joint_axes={"knee": [0, 0, 1]}, landmarks={"epicondyle": [0, -390, 45]})
    T2 = T1 @ np.array([[1, 0, 0, 0], [0, 1, 0, -400], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    bones["shank"] = Bone("shank", "thigh", _box((40, 380, 40)), T2,
                          joint_centres={"knee": [0, 0, 0]}, landmarks={"malleolus": [0, -370, 30]})
    return Skeleton(bones, world="lps")


def test_subject_round_trip(tmp_path):
    sk = chain()
    markers = {"RKNE": MarkerBinding("RKNE", "thigh", [5, -390, 60], "static", 1.0),
               "RASI": MarkerBinding("RASI", "pelvis", [60, 5, 120], "capsule", 2.0)}
    subj = Subject(sk, markers, skin=_box((300, 1000, 200)), forearm={"r": {"unit": "quarter_turn"}},
                   marker_set="plug_in_gait_full_body", provenance={"mode": "test"})
    write_subject(subj, tmp_path / "s")
    back = read_subject(tmp_path / "s")
    assert back.skeleton.world == "lps"
    assert back.skeleton.names == sk.names
    for n, b in sk.bones.items():
        c = back.skeleton.bones[n]
        assert c.parent == b.parent
        np.testing.assert_allclose(c.bone_to_world, b.bone_to_world, atol=1e-7)
        for k in b.joint_centres:
            np.testing.assert_allclose(c.joint_centres[k], b.joint_centres[k], atol=1e-3)
        for k in b.landmarks:
            np.testing.assert_allclose(c.landmarks[k], b.landmarks[k], atol=1e-3)
        # meshes are stored in world and come back in the bone frame
        np.testing.assert_allclose(c.mesh.vertices, b.mesh.vertices, atol=1e-3)
    for n, m in markers.items():
        np.testing.assert_allclose(back.markers[n].local, m.local, atol=1e-3)
        assert back.markers[n].source == m.source and back.markers[n].weight == m.weight
    assert back.forearm == {"r": {"unit": "quarter_turn"}}
    assert back.skin is not None and len(back.skin.faces) == 12
    # the stored meshes are in world: the thigh's lowest vertex is near its knee
    from bonecap.io.mesh import read_mesh

    world = read_mesh(tmp_path / "s" / "meshes" / "thigh.ply")
    knee = sk.bones["thigh"].landmark_in_world("knee")
    assert np.min(np.linalg.norm(world.vertices - knee, axis=1)) < 40


def test_the_rhythm_follows_the_build_mode_unless_the_subject_says():
    sk = chain()
    assert Subject(sk, provenance={"mode": "mri"}).follows_rhythm()
    assert not Subject(sk, provenance={"mode": "static"}).follows_rhythm()
    assert Subject(sk, provenance={"mode": "static", "girdle_rhythm": True}).follows_rhythm()
    assert not Subject(sk, provenance={"mode": "mri", "girdle_rhythm": False}).follows_rhythm()


def test_read_subject_errors(tmp_path):
    with pytest.raises(InputError, match="no subject.yaml"):
        read_subject(tmp_path)
    (tmp_path / "subject.yaml").write_text("format: something else\n")
    with pytest.raises(FormatError, match="not a bonecap subject"):
        read_subject(tmp_path)
    (tmp_path / "subject.yaml").write_text("format: bonecap subject\nbones: {a: {parent: null}}\n")
    with pytest.raises(FormatError, match="malformed"):
        read_subject(tmp_path)


def test_scale_skeleton_keeps_joints_together():
    sk = chain()
    scaled = scale_skeleton(sk, {"thigh": 1.1, "shank": 0.9}, default=1.0)
    # the thigh is 10 % longer, the knee centres of thigh and shank still meet
    th, sh = scaled.bones["thigh"], scaled.bones["shank"]
    np.testing.assert_allclose(th.landmark_in_world("knee"), sh.landmark_in_world("knee"), atol=1e-9)
    np.testing.assert_allclose(th.landmark_in_world("hip"), scaled.bones["pelvis"].landmark_in_world("hip"),
                               atol=1e-9)
    L = np.linalg.norm(th.landmark_in_world("knee") - th.landmark_in_world("hip"))
    assert L == pytest.approx(440.0)
    # orientations unchanged; the shank mesh is 0.9 x as long
    np.testing.assert_allclose(sh.bone_to_world[:3, :3], sk.bones["shank"].bone_to_world[:3, :3])
    ext = np.ptp(sh.mesh.vertices[:, 1])
    assert ext == pytest.approx(0.9 * 380)
    with pytest.raises(ValueError, match="positive"):
        scale_skeleton(sk, {"thigh": -1})
    with pytest.raises(ValueError, match="not in the skeleton"):
        scale_skeleton(sk, {"femur": 1.0})


def test_similarity_fit_recovers_transform():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(20, 3)) * 100
    R = Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix()
    dst = 1.07 * src @ R.T + [5, -30, 800]
    s, T = similarity_fit(src, dst)
    assert s == pytest.approx(1.07)
    np.testing.assert_allclose(src @ T[:3, :3].T + T[:3, 3], dst, atol=1e-8)
    src[3] = np.nan
    assert similarity_fit(src, dst)[0] == pytest.approx(1.07)
    with pytest.raises(ValueError, match="at least 3"):
        similarity_fit(src[:2], dst[:2])


def test_fit_scale_factors_recovers_lengths():
    sk = chain()
    truth = {"thigh": 1.08, "shank": 0.93}
    # markers on each bone along its length, offsets from the proximal joint
    bones = ["thigh", "thigh", "thigh", "shank", "shank", "pelvis"]
    placed = np.array([[40, -150, 0], [45, -390, 10], [-40, -300, 5], [35, -200, 0], [30, -370, 25],
                       [60, 5, 120]], float)
    measured = placed.copy()
    for i, b in enumerate(bones):
        if b in truth:  # the proximal joint is the bone origin here
            measured[i] = placed[i] * truth[b]
    s = fit_scale_factors(sk, bones, placed, measured)
    assert s["thigh"] == pytest.approx(1.08)
    assert s["shank"] == pytest.approx(0.93)
    # the pelvis has one marker: it takes the factor of its child (no parent)
    assert s["pelvis"] == pytest.approx(1.08)
    # a wild marker is clipped to the limits
    measured[3:5] *= 3
    assert fit_scale_factors(sk, bones, placed, measured)["shank"] == pytest.approx(1.4)


def test_fit_scale_factors_reads_length_not_soft_tissue():
    """Markers 30 mm farther from the bone than the template put them (thicker soft tissue) do not
    lengthen it: only the offsets along the bone's length (hip -> knee) count, and the pelvis (the
    root) is measured across, along its markers' widest spread. Whole offsets read the same case as
    a longer thigh, the measure that scaled an OpenSim model's femora 30 % up."""
    sk = chain()
    bones = ["thigh", "thigh", "thigh", "pelvis", "pelvis", "pelvis", "pelvis"]
    placed = np.array([[40, -150, 0], [45, -390, 10], [-40, -300, 5],
                       [60, 5, 120], [60, 5, -120], [-80, 20, 40], [-80, 20, -40]], float)
    measured = placed.copy()
    measured[:3, 1] *= 1.05                       # the thigh 5 % longer ...
    measured[:3, 0] += 30 * np.sign(placed[:3, 0])  # ... under 30 mm more soft tissue
    measured[3:, 0] += 30 * np.sign(placed[3:, 0])  # the pelvis as wide, its markers 30 mm out in front/back
    s = fit_scale_factors(sk, bones, placed, measured)
    assert s["thigh"] == pytest.approx(1.05, abs=0.005)
    assert s["pelvis"] == pytest.approx(1.0, abs=0.005)
    whole = fit_scale_factors(sk, bones, placed, measured, along_length=False)
    assert whole["thigh"] > 1.06 and whole["pelvis"] > 1.1


def test_location_markers_scale_with_their_bone():
    """An OpenSim marker (a location in its body) moves with the scaled body, also when scaled twice."""
    from bonecap.markers import MarkerDef, MarkerSet, place_markers

    sk = chain()
    mset = MarkerSet("osim", {"KNEE": MarkerDef(name="KNEE", bone="thigh", location=np.array([20.0, -380.0, 45.0]),
                                                tracks=["thigh"])})
    twice = scale_skeleton(scale_skeleton(sk, {"thigh": 1.1}), {"thigh": 0.9})
    for skel, f in ((sk, 1.0), (scale_skeleton(sk, {"thigh": 1.1}), 1.1), (twice, 0.99)):
        T = skel.bones["thigh"].bone_to_world
        local = (place_markers(mset, skel)["KNEE"] - T[:3, 3]) @ T[:3, :3]
        np.testing.assert_allclose(local, f * np.array([20.0, -380.0, 45.0]), atol=1e-9)
