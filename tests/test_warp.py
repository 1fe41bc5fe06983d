"""The affine + Gaussian RBF warp of a template skeleton (bonecap.skeleton.warp).

Checked against (1) a known smooth non-affine map (an affine plus a Gaussian
bump) applied to a small analytic two-bone skeleton, (2)-(3) the residual and
Jacobian checks on analytic maps, and (4) a phantom: the default template
warped onto the true bone meshes of a seeded tiny phantom, whose skeleton is a
non-affine variant of the template, scored against its truth.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from bonecap.meshing import surface_distance
from bonecap.model import Bone, Mesh, Skeleton
from bonecap.skeleton.warp import (affine_icp, feature_points, fit_warp, initial_transform, rigid_icp,
                                   warp_skeleton)


def mean_surface_distance(a: Mesh, b: Mesh) -> float:
    """Symmetric mean point-to-surface distance (mm)."""
    return 0.5 * (surface_distance(a.vertices, b).mean() + surface_distance(b.vertices, a).mean())


# --------------------------------------------------------------------------- #
# an analytic two-bone skeleton and a known smooth non-affine map
# --------------------------------------------------------------------------- #
def bent_ellipsoid(subdivisions: int, radii, bend: float, centre) -> np.ndarray:
    """Vertices and faces of an ellipsoid bent into a banana (no symmetry left for ICP to slide along)."""
    s = trimesh.creation.icosphere(subdivisions=subdivisions)
    v = np.asarray(s.vertices) * radii
    v[:, 0] += bend * v[:, 1] ** 2 + 0.03 * v[:, 2] * (v[:, 1] > 0)
    return v + centre, np.asarray(s.faces)


AFF = np.eye(4)
AFF[:3, :3] = Rotation.from_euler("xyz", [8, -5, 12], degrees=True).as_matrix() @ np.array(
    [[1.06, 0.04, 0.0], [0.0, 0.95, 0.03], [0.02, 0.0, 1.08]])
AFF[:3, 3] = [12.0, -7.0, 20.0]
BUMP_C, BUMP_S, BUMP_A = np.array([0.0, -110.0, 0.0]), 35.0, np.array([4.0, 0.0, -3.0])


def true_map(p: np.ndarray) -> np.ndarray:
    """Template world -> target world: an affine plus a Gaussian bump (5 mm peak) on the upper bone's shaft."""
    p = np.asarray(p, dtype=float)
    bump = np.exp(-((p - BUMP_C) ** 2).sum(1) / BUMP_S ** 2)[:, None] * BUMP_A
    return (p + bump) @ AFF[:3, :3].T + AFF[:3, 3]


def true_jacobian(p: np.ndarray) -> np.ndarray:
    g = np.exp(-((p - BUMP_C) ** 2).sum(1) / BUMP_S ** 2)
    Jb = np.eye(3)[None] + BUMP_A[None, :, None] * (-2.0 * (p - BUMP_C) / BUMP_S ** 2 * g[:, None])[:, None, :]
    return AFF[:3, :3][None] @ Jb


def two_bone_template(subdivisions: int = 4) -> Skeleton:
    """Upper bone (frame origin at its proximal joint, mesh from y=-205 to -15) and lower bone below it."""
    vu, fu = bent_ellipsoid(subdivisions, (18, 95, 25), 0.002, (0, -110, 0))
    vl, fl = bent_ellipsoid(subdivisions, (15, 85, 20), -0.002, (0, -100, 0))
    upper_T = np.eye(4)
    upper_T[:3, 3] = [0, 400, 0]
    lower_T = np.eye(4)
    lower_T[:3, :3] = Rotation.from_euler("z", 6, degrees=True).as_matrix()
    lower_T[:3, 3] = upper_T[:3, 3] + [0, -220, 0]
    upper = Bone("upper", None, Mesh(vu, fu, "upper"), upper_T,
                 joint_centres={"proximal": [0, 0, 0], "knee": [0, -220, 0]},
                 joint_axes={"knee": [0, 0, 1]}, landmarks={"bump": [0, -110, 25]})
    lower = Bone("lower", "upper", Mesh(vl, fl, "lower"), lower_T, joint_centres={"knee": [0, 0, 0]},
                 joint_axes={"knee": [0, 0, 1]}, landmarks={"tip": [-14.45, -185, 0]})  # the bent pole
    return Skeleton({"upper": upper, "lower": lower}, world="model")


@pytest.fixture(scope="module")
def analytic_case():
    template = two_bone_template(4)
    # the targets: the same shapes on another triangulation (the warp must not rely on vertex order)
    fine = two_bone_template(5)
    targets = {n: Mesh(true_map(fine.world_mesh(n).vertices), fine.bones[n].mesh.faces, "lps") for n in fine.bones}
    rough = np.eye(4)                      # a rough start: rotation 6 deg and 15 mm off the truth's
    rough[:3, :3] = Rotation.from_euler("xyz", [5, 0, 8], degrees=True).as_matrix()
    rough[:3, 3] = AFF[:3, 3] + [10.0, 5.0, -8.0]
    sk, report = warp_skeleton(template, targets, init=rough)
    return template, targets, sk, report


def test_analytic_warp_recovers_surface_and_joints(analytic_case):
    template, targets, sk, report = analytic_case
    assert sk.world == "lps"
    for name in ("upper", "lower"):
        assert report["bones"][name]["source"] == "own target"
        assert 50 <= report["bones"][name]["n_features"] <= 1000
        assert mean_surface_distance(sk.world_mesh(name), targets[name]) <= 0.5
        # the affine alone cannot follow the bump on the upper bone
    aff_upper = template.world_mesh("upper").transformed(np.array(report["transforms"]["upper"]))
    assert mean_surface_distance(aff_upper, targets["upper"]) > 2 * mean_surface_distance(
        sk.world_mesh("upper"), targets["upper"])
    # joint centres and landmarks where the true map puts them
    for name, bone in template.bones.items():
        for k in bone.joint_centres:
            truth = true_map(bone.landmark_in_world(k)[None])[0]
            assert np.linalg.norm(sk.bones[name].landmark_in_world(k) - truth) <= 1.0, (name, k)
        for k in bone.landmarks:
            truth = true_map(bone.landmark_in_world(k)[None])[0]
            assert np.linalg.norm(sk.bones[name].landmark_in_world(k) - truth) <= 1.0, (name, k)


def test_shared_joint_is_one_point(analytic_case):
    _, _, sk, _ = analytic_case
    a = sk.bones["upper"].landmark_in_world("knee")
    b = sk.bones["lower"].landmark_in_world("knee")
    np.testing.assert_allclose(a, b, atol=1e-9)


def test_personal_frames_stay_rigid_and_oriented(analytic_case):
    template, _, sk, _ = analytic_case
    R_true = np.linalg.svd(AFF[:3, :3])
    R_true = R_true[0] @ R_true[2]                 # polar rotation of the true affine
    for name, bone in sk.bones.items():
        R = bone.bone_to_world[:3, :3]
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-9)
        assert np.linalg.det(R) == pytest.approx(1.0)
        expect = R_true @ template.bones[name].bone_to_world[:3, :3]
        angle = np.degrees(np.arccos(np.clip((np.trace(expect.T @ R) - 1) / 2, -1, 1)))
        assert angle < 3.0, (name, angle)
        # the mesh is stored in the bone's own frame
        assert bone.mesh.frame == name


def test_warp_jacobian_positive_and_true(analytic_case):
    template, _, sk, report = analytic_case
    for name in ("upper", "lower"):
        assert report["bones"][name]["min_jacobian_det"] > 0.5
    # the fitted warp's Jacobian matches the true map's where the bump bends it
    tpl = template.world_mesh("upper").vertices
    src = tpl[::3]
    w = fit_warp(src, true_map(src), kernel_width_mm=25.0, smoothing=0.0)
    pts = tpl[np.linalg.norm(tpl - BUMP_C, axis=1) < 40][:50]
    np.testing.assert_allclose(w.jacobian(pts), true_jacobian(pts), atol=0.03)
    assert w.min_jacobian_det(tpl) > 0


def test_folding_is_detected():
    # two feature points 2 mm apart asked to swap places: any interpolant folds between them
    rng = np.random.default_rng(0)
    src = rng.uniform(-50, 50, (200, 3))
    src[:2] = [[0, 0, 0], [2.0, 0, 0]]
    dst = src.copy()
    dst[:2] = [[2.0, 0, 0], [0, 0, 0]]
    w = fit_warp(src, dst, kernel_width_mm=10.0, smoothing=0.0)
    assert w.min_jacobian_det(np.array([[1.0, 0, 0]])) < 0
    ok = fit_warp(src, src * 1.1 + 2.0, kernel_width_mm=10.0, smoothing=0.0)
    assert ok.min_jacobian_det(np.array([[1.0, 0, 0]])) == pytest.approx(1.1 ** 3, rel=1e-6)


def test_too_wide_kernel_is_caught():
    rng = np.random.default_rng(1)
    src = rng.uniform(-100, 100, (500, 3))                     # 200 mm across
    dst = src + 5.0 * np.sin(src / 30.0)                       # a smooth non-affine map
    good = fit_warp(src, dst, kernel_width_mm=30.0, smoothing=0.0)
    assert np.percentile(good.residual_mm, 95) < 0.05
    with pytest.raises(ValueError, match="too wide"):
        fit_warp(src, dst, kernel_width_mm=1000.0, smoothing=0.0)
    # unchecked, the residual shows the failure: the fit silently misses its points
    bad = fit_warp(src, dst, kernel_width_mm=1000.0, smoothing=0.0, max_residual_mm=None)
    assert np.percentile(bad.residual_mm, 95) > 1.0


def test_icps_and_feature_points_on_an_analytic_map():
    template = two_bone_template(4)
    m = template.world_mesh("upper")
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [4, -6, 3], degrees=True).as_matrix()
    T[:3, 3] = [5, -3, 7]
    target = m.transformed(T, "lps")
    T_r, res = rigid_icp(m.vertices, target)
    np.testing.assert_allclose(T_r, T, atol=0.05)
    assert res.mean() < 0.05
    A = T.copy()
    A[:3, :3] = A[:3, :3] @ np.diag([1.1, 0.9, 1.05])
    T_a, res_a = affine_icp(m.vertices, m.transformed(A, "lps"), init=T_r)
    assert res_a.mean() < 0.1
    src, dst = feature_points(m.transformed(T_a), m.transformed(A, "lps"), n=600)
    assert 100 <= len(src) <= 600 and src.shape == dst.shape
    assert np.linalg.norm(src - dst, axis=1).mean() < 0.2


def test_bad_input():
    template = two_bone_template(2)
    with pytest.raises(ValueError, match="not in the template"):
        warp_skeleton(template, {"femur": template.world_mesh("upper")})
    with pytest.raises(ValueError, match="nothing to warp"):
        warp_skeleton(template, {})
    with pytest.raises(ValueError, match="same shape"):
        fit_warp(np.zeros((5, 3)), np.zeros((6, 3)))
    with pytest.raises(ValueError, match="at least 4"):
        fit_warp(np.zeros((3, 3)), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="kernel_width_mm"):
        fit_warp(np.random.rand(10, 3), np.random.rand(10, 3), kernel_width_mm=0)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        rigid_icp(np.zeros((4, 2)), template.world_mesh("upper"))


# --------------------------------------------------------------------------- #
# the phantom
# --------------------------------------------------------------------------- #
PHANTOM_BONES = ["sacrum", "hip_r", "hip_l", "femur_r", "femur_l", "patella_r", "tibia_r", "fibula_r", "talus_l",
                 "l3", "sternum", "rib5_r", "clavicle_r", "scapula_r", "humerus_r", "skull"]


@pytest.fixture(scope="module")
def phantom_case(tmp_path_factory):
    from bonecap.io.mesh import read_mesh
    from bonecap.phantom import make_phantom
    from bonecap.skeleton.template import load_template

    out = tmp_path_factory.mktemp("phantom")
    make_phantom(out, seed=3, preset="tiny")
    truth_meshes = {n: read_mesh(out / "truth" / "meshes" / f"{n}.ply") for n in PHANTOM_BONES + ["tibia_l"]}
    truth = json.loads((out / "truth" / "skeleton.json").read_text())["bones"]
    template = load_template("default")
    targets = {n: truth_meshes[n] for n in PHANTOM_BONES}
    # the rough start the pipeline has: a similarity from the targets' centroids, no truth pose
    init = initial_transform(template, targets)
    sk, report = warp_skeleton(template, targets, init=init)
    return template, targets, truth_meshes, truth, sk, report


def test_phantom_personal_beats_affine(phantom_case):
    template, targets, _, _, sk, report = phantom_case
    personal, affine = [], []
    for n in targets:
        assert report["bones"][n]["source"] == "own target"
        assert report["bones"][n]["min_jacobian_det"] > 0
        assert report["bones"][n]["n_features"] <= 2000
        personal.append(mean_surface_distance(sk.world_mesh(n), targets[n]))
        aff = template.world_mesh(n).transformed(np.array(report["transforms"][n]), "lps")
        affine.append(mean_surface_distance(aff, targets[n]))
    personal, affine = np.array(personal), np.array(affine)
    assert personal.mean() <= 1.5                                # issue #5 target
    assert personal.mean() * 2 <= affine.mean()
    assert personal.max() <= 1.5


def truth_spread(truth: dict, bone: str, joint: str) -> float:
    """How far apart the truth puts one joint in the bones that list it (same name, or with a side suffix).

    The phantom gives every bone its own non-affine shape, which also moves a joint centre lying far from
    that bone (a sacrum's pubic symphysis): the truth then has several positions for one joint, and one
    personal position cannot meet them all.
    """
    p0 = np.array(truth[bone]["joint_centres_lps"][joint])
    spread = 0.0
    for b, t in truth.items():
        for k, p in t["joint_centres_lps"].items():
            if b != bone and (k == joint or k.startswith(joint + "_") or joint.startswith(k + "_")):
                d = float(np.linalg.norm(np.array(p) - p0))
                if d < 10.0:
                    spread = max(spread, d)
    return spread


def test_phantom_joint_centres_and_frames(phantom_case):
    _, targets, _, truth, sk, _ = phantom_case
    errs = []
    for n in targets:
        for k, p in truth[n]["joint_centres_lps"].items():
            err = np.linalg.norm(sk.bones[n].landmark_in_world(k) - np.array(p))
            errs.append(err)
            # a joint known from one bone alone (femur_l here: tibia_l has no target) is an extrapolation
            assert err <= 3.0 + truth_spread(truth, n, k), (n, k, err)
        # ISB orientation kept: the personal frame turns like the true one, within a few degrees
        R_true = np.array(truth[n]["bone_to_lps"])[:3, :3]
        R = sk.bones[n].bone_to_world[:3, :3]
        angle = np.degrees(np.arccos(np.clip((np.trace(R_true.T @ R) - 1) / 2, -1, 1)))
        assert angle < 8.0, (n, angle)
    # 1.0 until the landmark rule's seed-inside-the-bone fallback changed the phantom's landmarks
    # (median 1.006 mm after it, with or without the frame origins rebuilt)
    assert np.median(errs) <= 1.1
    # every joint between a bone and its parent is one point
    for n, b in sk.bones.items():
        if b.parent is None:
            continue
        for k in set(b.joint_centres) & set(sk.bones[b.parent].joint_centres):
            np.testing.assert_allclose(b.landmark_in_world(k), sk.bones[b.parent].landmark_in_world(k), atol=1e-6)


def test_phantom_bone_without_target_is_carried(phantom_case):
    _, _, truth_meshes, truth, sk, report = phantom_case
    assert report["bones"]["tibia_l"]["source"] == "neighbours"
    # its knee comes from the warped femur_l, its ankle from the warped talus_l
    for k in ("knee", "ankle"):
        true_k = np.array(truth["tibia_l"]["joint_centres_lps"][k])
        err = np.linalg.norm(sk.bones["tibia_l"].landmark_in_world(k) - true_k)
        assert err <= 3.0, (k, err)
    assert mean_surface_distance(sk.world_mesh("tibia_l"), truth_meshes["tibia_l"]) <= 2.5


# --------------------------------------------------------------------------- #
# a rigid body of several bones without targets (a pelvis) is carried as one
# --------------------------------------------------------------------------- #
def pelvis_template(subdivisions: int = 3) -> Skeleton:
    """A sacrum with two hip bones (one rigid body, no targets) and two femora hanging from the hips."""
    def ell(radii, centre):
        s = trimesh.creation.icosphere(subdivisions=subdivisions)
        return Mesh(np.asarray(s.vertices) * radii + centre, np.asarray(s.faces), "bone")

    T0 = np.eye(4)
    T0[:3, 3] = [0.0, 900.0, 0.0]
    bones = {"sacrum": Bone("sacrum", None, ell((30, 50, 40), (-60, 20, 0)), T0.copy(),
                            joint_centres={"sacroiliac_r": [-50, 30, 40], "sacroiliac_l": [-50, 30, -40]})}
    for side, z in (("r", 1.0), ("l", -1.0)):
        bones[f"hip_{side}"] = Bone(f"hip_{side}", "sacrum", ell((40, 60, 20), (-20, 0, 70 * z)), T0.copy(),
                                    joint_centres={"sacroiliac": [-50, 30, 40 * z], "hip": [0, -60, 85 * z]})
        Tf = T0.copy()
        Tf[:3, 3] += [0.0, -60.0, 85.0 * z]
        v, f = bent_ellipsoid(subdivisions + 1, (18, 180, 25), 0.002, (0, -200, 0))
        v[:, 2] *= z
        bones[f"femur_{side}"] = Bone(f"femur_{side}", f"hip_{side}", Mesh(v, f, "femur"), Tf,
                                      joint_centres={"hip": [0, 0, 0]})
    return Skeleton(bones, world="model", metadata={"rigid_bodies": [["sacrum", "hip_r", "hip_l"]]})


def femur_with_foot(radii, centre, joints) -> tuple[dict, np.ndarray, trimesh.Trimesh]:
    """:func:`pelvis_template`'s bones with a knee at the right femur's distal end (380 mm down its axis) and a
    target-less foot hanging there: an ellipsoid of ``radii`` about ``centre`` in its frame, ``joints`` its
    joint centres. Returns the bones, the foot's frame and the sphere it was made from."""
    template = pelvis_template()
    bones = dict(template.bones)
    Tf = template.bones["femur_r"].bone_to_world
    end = np.array([0.0, -380.0, 0.0])                    # the femur's distal end, in its frame
    Tc = Tf.copy()
    Tc[:3, 3] = Tf[:3, :3] @ end + Tf[:3, 3]
    s = trimesh.creation.icosphere(subdivisions=2)
    bones["femur_r"] = Bone("femur_r", "hip_r", template.bones["femur_r"].mesh, Tf.copy(),
                            joint_centres={"hip": [0, 0, 0], "knee": end})
    bones["foot_r"] = Bone("foot_r", "femur_r", Mesh(np.asarray(s.vertices) * radii + centre, np.asarray(s.faces),
                                                     "foot"), Tc, joint_centres=joints)
    return bones, Tc, s


def test_a_rigid_body_without_targets_is_carried_as_one():
    template = pelvis_template()
    # the person: the femora (and so the hip centres) 12 mm off the placed template, and 6 mm further apart
    # (a wider pelvis); nothing of the pelvis itself was segmented
    shift = np.array([6.0, -4.0, 9.0])
    targets = {}
    for side, z in (("r", 1.0), ("l", -1.0)):
        n = f"femur_{side}"
        targets[n] = Mesh(template.world_mesh(n).vertices + shift + [0.0, 0.0, 3.0 * z],
                          template.bones[n].mesh.faces, "lps")
    sk, report = warp_skeleton(template, targets, init=np.eye(4), start_from="placed")
    for n in ("sacrum", "hip_r", "hip_l"):
        assert report["bones"][n]["source"] == "neighbours"
        # one rigid body: the same motion for the three, the placed orientation kept (two hip centres
        # do not say how the pelvis is turned better than its placement did), moved onto the hip centres
        move = sk.bones[n].bone_to_world @ np.linalg.inv(template.bones[n].bone_to_world)
        np.testing.assert_allclose(move[:3, :3], np.eye(3), atol=1e-3)
        np.testing.assert_allclose(move[:3, 3], shift, atol=0.5)
    for side in ("r", "l"):
        # each hip bone meets its femur's warped hip centre, and the pelvis stayed joined
        np.testing.assert_allclose(sk.bones[f"hip_{side}"].landmark_in_world("hip"),
                                   sk.bones[f"femur_{side}"].landmark_in_world("hip"), atol=1e-6)
        np.testing.assert_allclose(sk.bones[f"hip_{side}"].landmark_in_world("sacroiliac"),
                                   sk.bones["sacrum"].landmark_in_world(f"sacroiliac_{side}"), atol=1e-6)
    width = np.linalg.norm(sk.bones["hip_r"].landmark_in_world("hip") - sk.bones["hip_l"].landmark_in_world("hip"))
    assert abs(width - (170.0 + 6.0)) < 0.5
    # without the rigid body, bone by bone: the unmoved sacrum pins each hip bone's sacroiliac joint and the
    # hip bones turn toward their femora (what this guards against)
    sk2, _ = warp_skeleton(template, targets, init=np.eye(4), start_from="placed", rigid_bodies=[])
    turned = sk2.bones["hip_r"].bone_to_world[:3, :3]
    assert np.degrees(np.arccos(np.clip((np.trace(turned) - 1) / 2, -1, 1))) > 2.0


def test_a_chain_between_the_pelvis_and_a_fixed_skull_meets_both():
    """Vertebrae without targets between the pelvis (carried onto the femora) and a skull placed by
    other means (``fixed``: build-subject fits it to the head's skin) are spread to meet both: a spine
    3 % longer than the template's ends at the skull, each vertebra keeps its placed orientation and
    moves in proportion to its height; without ``fixed`` the chain ends short of the skull. With
    ``refine_chain`` the inner joints go where it says, the ends stay; refused, the spread is kept."""
    template = pelvis_template()
    T0 = template.bones["sacrum"].bone_to_world
    bones = dict(template.bones)
    parent, prev_joint = "sacrum", "l5_s1"
    bones["sacrum"] = Bone("sacrum", None, template.bones["sacrum"].mesh, T0.copy(),
                           joint_centres={**template.bones["sacrum"].joint_centres, "l5_s1": [-40, 80, 0]})
    names = [f"v{i}" for i in range(6)]                 # bottom to top, 40 mm apart
    for i, n in enumerate(names):
        s = trimesh.creation.icosphere(subdivisions=2)
        T = T0.copy()
        T[:3, 3] += [-40.0, 100.0 + 40.0 * i, 0.0]
        top = f"{n}_top"
        bones[n] = Bone(n, parent, Mesh(np.asarray(s.vertices) * [15, 12, 15], np.asarray(s.faces), n), T,
                        joint_centres={prev_joint: [0, -20, 0], top: [0, 20, 0]})
        parent, prev_joint = n, top
    T = T0.copy()
    T[:3, 3] += [-40.0, 100.0 + 40.0 * 6 + 60.0, 0.0]
    s = trimesh.creation.icosphere(subdivisions=2)
    bones["skull"] = Bone("skull", parent, Mesh(np.asarray(s.vertices) * 70, np.asarray(s.faces), "skull"), T,
                          joint_centres={prev_joint: [0, -80, 0]})
    # the chain's bones are children of the sacrum: list them after it, the skull last
    order = ["sacrum", "hip_r", "hip_l", "femur_r", "femur_l", *names, "skull"]
    template = Skeleton({n: bones[n] for n in order}, world="model", metadata=template.metadata)
    shift = np.array([2.0, -3.0, 1.0])
    targets = {n: Mesh(template.world_mesh(n).vertices + shift, template.bones[n].mesh.faces, "lps")
               for n in ("femur_r", "femur_l")}
    bottom = template.bones["sacrum"].landmark_in_world("l5_s1") + shift
    top0 = template.bones["skull"].landmark_in_world(prev_joint)
    longer = 0.03 * (top0[1] - bottom[1])               # the person's spine, 3 % longer
    skull_map = np.eye(4)
    skull_map[:3, 3] = shift + [1.5, longer, -2.0]
    sk, report = warp_skeleton(template, targets, init=np.eye(4), start_from="placed", fixed={"skull": skull_map})
    assert report["bones"]["skull"]["source"].startswith("fixed")
    np.testing.assert_allclose(sk.bones["skull"].bone_to_world, skull_map @ template.bones["skull"].bone_to_world,
                               atol=1e-9)
    # joined at both ends
    np.testing.assert_allclose(sk.bones[names[-1]].landmark_in_world(prev_joint),
                               sk.bones["skull"].landmark_in_world(prev_joint), atol=1e-6)
    np.testing.assert_allclose(sk.bones[names[0]].landmark_in_world("l5_s1"),
                               sk.bones["sacrum"].landmark_in_world("l5_s1"), atol=1e-6)
    top = _apply_map(skull_map, top0)
    for i, n in enumerate(names):
        move = sk.bones[n].bone_to_world @ np.linalg.inv(template.bones[n].bone_to_world)
        np.testing.assert_allclose(move[:3, :3] @ move[:3, :3].T, np.eye(3), atol=1e-9)   # rigid frame
        np.testing.assert_allclose(move[:3, :3], np.eye(3), atol=1e-9)                   # placed orientation
        f = (template.bones[n].bone_to_world[1, 3] - bottom[1] + shift[1]) / (top0[1] - bottom[1] + shift[1])
        expected = shift + f * (top - top0 - shift)
        np.testing.assert_allclose(move[:3, 3], expected, atol=0.3)
    # without the fixed skull the chain is carried up from the pelvis alone: its top misses the skull
    sk2, _ = warp_skeleton(template, targets, init=np.eye(4), start_from="placed")
    gap = np.linalg.norm(sk2.bones[names[-1]].landmark_in_world(prev_joint) - top)
    assert gap > 0.9 * longer


    # the image's word on the joints between the ends (build-subject: the discs the MRI shows): the chain's
    # inner joints go where ``refine_chain`` puts them, its ends stay with the pelvis and the skull, and the
    # vertebrae stay joined and keep their placed orientation
    seen = {}

    def refine(joint_bones, points):
        seen["bones"], seen["points"] = joint_bones, np.array(points)
        return np.asarray(points) + [0.0, 6.0, 0.0], {"used": True}
    sk3, report3 = warp_skeleton(template, targets, init=np.eye(4), start_from="placed",
                                 fixed={"skull": skull_map}, refine_chain=refine)
    assert seen["bones"][0] == ["sacrum", "v0"] and seen["bones"][-1] == ["skull", names[-1]]
    assert report3["chains"][0]["used"] and report3["chains"][0]["joints"][0] == "l5_s1"
    for i, n in enumerate(names[1:], start=1):
        np.testing.assert_allclose(sk3.bones[n].landmark_in_world(f"v{i - 1}_top"), seen["points"][i] + [0, 6, 0],
                                   atol=1e-6)
        np.testing.assert_allclose(sk3.bones[n].landmark_in_world(f"v{i - 1}_top"),
                                   sk3.bones[names[i - 1]].landmark_in_world(f"v{i - 1}_top"), atol=1e-6)
        move = sk3.bones[n].bone_to_world @ np.linalg.inv(template.bones[n].bone_to_world)
        np.testing.assert_allclose(move[:3, :3], np.eye(3), atol=1e-9)
    np.testing.assert_allclose(sk3.bones[names[0]].landmark_in_world("l5_s1"),
                               sk.bones[names[0]].landmark_in_world("l5_s1"), atol=1e-9)
    np.testing.assert_allclose(sk3.bones[names[-1]].landmark_in_world(prev_joint),
                               sk.bones[names[-1]].landmark_in_world(prev_joint), atol=1e-9)
    # refused (None): the linear spread, exactly
    sk4, report4 = warp_skeleton(template, targets, init=np.eye(4), start_from="placed", fixed={"skull": skull_map},
                                 refine_chain=lambda b, p: (None, {"used": False}))
    for n in names:
        np.testing.assert_array_equal(sk4.bones[n].bone_to_world, sk.bones[n].bone_to_world)
    # the chain's joints far from where the template was placed (a phantom's lumbar spine 26 mm shorter
    # than the spread, its discs all matched): trusted as own targets' joints are, so the middle vertebrae,
    # moved beyond the bound from their placed pose, follow them (up to twice the bound) instead of
    # staying placed -- here a 20 mm bound and a smooth 30 mm sag
    sag = -30.0 * np.sin(np.pi * np.arange(len(seen["points"])) / (len(seen["points"]) - 1))
    sk5, report5 = warp_skeleton(template, targets, init=np.eye(4), start_from="placed", max_shift_mm=20.0,
                                 fixed={"skull": skull_map},
                                 refine_chain=lambda b, p: (np.asarray(p) + sag[:, None] * [0, 1, 0], {"used": True}))
    for i in (3, 4):                                    # v2 and v3, between the sag's deepest joints
        n = names[i - 1]
        moved = np.linalg.norm(sk5.bones[n].bone_to_world[:3, 3] - template.bones[n].bone_to_world[:3, 3])
        assert moved > 25.0 and report5["bones"][n]["source"] == "neighbours", (n, moved, report5["bones"][n])
        np.testing.assert_allclose(sk5.bones[n].landmark_in_world(f"v{i - 2}_top"),
                                   seen["points"][i - 1] + [0, sag[i - 1], 0], atol=1e-6)
        np.testing.assert_allclose(sk5.bones[n].landmark_in_world(f"v{i - 1}_top"),
                                   seen["points"][i] + [0, sag[i], 0], atol=1e-6)


def _apply_map(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    return T[:3, :3] @ p + T[:3, 3]


def test_a_target_cut_short_is_not_taken_for_the_bone_end():
    """A segmentation whose search ended 35 mm short of the lower bone's end gives a target cut there
    (capped, closed). Taken as it is, the warp shrinks the bone to the cut (its distal tip moves up by
    ~ the missing length); with the cut declared ``unseen`` the bone's end is extrapolated by the affine
    fitted on the rest (the map is affine there) and lands near the truth. The seen part fits both ways."""
    template = two_bone_template(4)
    fine = two_bone_template(5)
    targets = {n: Mesh(true_map(fine.world_mesh(n).vertices), fine.bones[n].mesh.faces, "lps") for n in fine.bones}
    low = template.bones["lower"]
    tip_true = true_map(low.landmark_in_world("tip")[None])[0]
    axis = true_map(low.landmark_in_world("tip")[None])[0] - true_map(low.bone_to_world[:3, 3][None])[0]
    axis /= np.linalg.norm(axis)
    cut_at = tip_true - 35.0 * axis
    import pyvista as pv

    m = targets["lower"]
    poly = pv.PolyData(m.vertices, np.hstack([np.full((len(m.faces), 1), 3), m.faces]).ravel())
    short = poly.clip_closed_surface(normal=tuple(-axis), origin=tuple(cut_at)).triangulate()  # keeps the -axis side
    faces = np.asarray(short.faces).reshape(-1, 4)[:, 1:]
    short = trimesh.Trimesh(np.asarray(short.points), faces, process=True)
    assert short.is_watertight and (short.vertices @ axis).max() < cut_at @ axis + 1e-6
    targets["lower"] = Mesh(np.asarray(short.vertices), np.asarray(short.faces), "lps")
    rough = np.eye(4)
    rough[:3, 3] = AFF[:3, 3]
    tips, fits = {}, {}
    for name, unseen in (("plain", None), ("cut", {"lower": [(axis, float(cut_at @ axis) - 5.0)]})):
        sk, report = warp_skeleton(template, targets, init=rough, unseen=unseen)
        tips[name] = np.linalg.norm(sk.bones["lower"].landmark_in_world("tip") - tip_true)
        seen = sk.world_mesh("lower").vertices
        seen = seen[seen @ axis < cut_at @ axis - 10.0]
        fits[name] = surface_distance(seen, targets["lower"]).mean()
        assert ("unseen" in report["bones"]["lower"]) == (unseen is not None)
    assert tips["plain"] > 10.0, tips          # shrunk towards the cut (15.6 mm)
    assert tips["cut"] < 3.0, tips            # 0.7 mm
    assert fits["cut"] < 0.6 and fits["plain"] < 0.6, fits
    with pytest.raises(ValueError, match="unseen"):
        warp_skeleton(template, targets, init=rough, unseen={"nosuchbone": [(axis, 0.0)]})
    with pytest.raises(ValueError, match="half-space"):
        warp_skeleton(template, targets, init=rough, unseen={"lower": [((0.0, 0.0, 0.0), 1.0)]})



def _flared_shaft() -> trimesh.Trimesh:
    """A long bone of revolution along z: a shaft of radius 8 mm, 240 mm long, flaring to 14 mm over its
    last 40 mm at the -z end (a distal radius or tibia), rounded caps."""
    z = np.linspace(-120.0, 120.0, 97)
    r = 8.0 + 6.0 * np.clip((-80.0 - z) / 35.0, 0, 1) ** 1.5
    r = r * np.sqrt(np.clip(1 - ((np.abs(z) - 112.0).clip(0) / 8.0) ** 2, 0, 1))
    prof = np.column_stack([r, z])
    prof[0, 0] = prof[-1, 0] = 0.0
    return trimesh.creation.revolve(prof, sections=48)


def test_a_bone_placed_off_along_its_axis_slides_back():
    """The subject's bone 8 % longer than the template's, their proximal ends together: the template's
    flared end lies 18 mm short of the target's. Along a shaft only the ends hold the slide, and their
    pairs are the farthest: a trimmed rigid ICP (the nearest 90 % of the pairs each way) drops them and
    does not move (the affine ICP after it then leaves the end 18 mm short); keeping every pair, the
    rigid fit centres the bone and the affine stretches it onto the target. The warp's rigid stage keeps
    every pair: its personal bone ends within 3 mm of the target's end."""
    m = _flared_shaft()
    V, F = np.asarray(m.vertices), np.asarray(m.faces)
    tV = V * [1.0, 1.0, 1.08]
    tV[:, 2] += V[:, 2].max() - tV[:, 2].max()
    target = Mesh(tV, F, "lps")
    tip0, tip_true = np.array([0.0, 0.0, V[:, 2].min()]), np.array([0.0, 0.0, tV[:, 2].min()])
    err = {}
    for trim in (0.9, 1.0):
        T_r, _ = rigid_icp(V, target, np.eye(4), trim=trim)
        T_a, _ = affine_icp(V, target, T_r)
        err[trim] = np.linalg.norm(_apply_map(T_a, tip0) - tip_true)
    assert err[0.9] > 12.0 and err[1.0] < 4.0, err
    sk = Skeleton({"bone": Bone("bone", None, Mesh(V, F, "bone"), np.eye(4), joint_centres={"top": [0, 0, 120.0]},
                                landmarks={"tip": tip0})}, world="model")
    personal, _ = warp_skeleton(sk, {"bone": target}, init=np.eye(4))
    assert np.linalg.norm(personal.bones["bone"].landmark_in_world("tip") - tip_true) < 3.0


def test_an_extraction_run_on_past_the_bone_does_not_stretch_it():
    """The same shaft's extraction runs on into a neighbour past its flared end (a radius's into the
    carpals: a 14 mm ball 1 mm beyond its tip). Keeping every pair, the rigid fit slides the bone toward
    the ball and the affine then stretches it over it (the tip 20 mm out); a trimmed rigid start finds
    the other minimum, where the template lies on its extraction (affine residual 0.2 against 0.5 mm),
    and the warp keeps that one: the personal tip within 6 mm of the true one, and the report says so."""
    m = _flared_shaft()
    V, F = np.asarray(m.vertices), np.asarray(m.faces)
    ball = trimesh.creation.icosphere(subdivisions=3)
    bV = np.asarray(ball.vertices) * [14.0, 14.0, 11.2]
    bV[:, 2] += V[:, 2].min() - 1.0 - 11.2
    target = Mesh(np.concatenate([V, bV]), np.concatenate([F, np.asarray(ball.faces) + len(V)]), "lps")
    tip = np.array([0.0, 0.0, V[:, 2].min()])
    T_r, _ = rigid_icp(V, target, np.eye(4), trim=1.0)
    T_a, res_untrimmed = affine_icp(V, target, T_r)
    assert np.linalg.norm(_apply_map(T_a, tip) - tip) > 15.0          # the one start alone: stretched on
    sk = Skeleton({"bone": Bone("bone", None, Mesh(V, F, "bone"), np.eye(4), joint_centres={"top": [0, 0, 120.0]},
                                landmarks={"tip": tip})}, world="model")
    personal, report = warp_skeleton(sk, {"bone": target}, init=np.eye(4))
    assert np.linalg.norm(personal.bones["bone"].landmark_in_world("tip") - tip) < 6.0
    assert any("trimmed rigid start kept" in f for f in report["bones"]["bone"]["flags"])
    assert report["bones"]["bone"]["affine_residual_mean_mm"] < 0.8 * res_untrimmed.mean()


def test_a_bone_carried_onto_an_own_targets_joint_follows_it_past_the_shift_bound():
    """A bone without a target hanging from a long bone that is longer than placed (a foot below a
    tibia 12 % longer: its end 45 mm beyond the placed one, its centre half that) is carried onto the
    warped joint, not kept where it was placed: joints placed by own targets, and by bones carried onto
    them (the toes below the foot), are trusted to twice ``max_shift_mm``."""
    bones, Tc, s = femur_with_foot([20, 30, 20], [0, -35, 0], {"knee": [0, 0, 0], "mtp": [0, -70, 0]})
    # and one more down the chain, carried onto the foot's joint (placed by a carried bone)
    Tt = Tc.copy()
    Tt[:3, 3] = Tc[:3, :3] @ [0.0, -70.0, 0.0] + Tc[:3, 3]
    bones["toes_r"] = Bone("toes_r", "foot_r", Mesh(np.asarray(s.vertices) * [15, 20, 15] + [0, -20, 0],
                                                    np.asarray(s.faces), "toes"), Tt, joint_centres={"mtp": [0, 0, 0]})
    template = Skeleton(bones, world="model", metadata=pelvis_template().metadata)
    # the person's femora: 12 % longer along their axis, about the hip
    targets = {}
    for side in ("r", "l"):
        b = template.bones[f"femur_{side}"]
        S = np.eye(4)
        S[1, 1] = 1.12
        v = b.mesh.vertices @ S[:3, :3].T
        targets[f"femur_{side}"] = Mesh(v @ b.bone_to_world[:3, :3].T + b.bone_to_world[:3, 3], b.mesh.faces, "lps")
    # the bounds build-subject uses
    sk, report = warp_skeleton(template, targets, init=np.eye(4), start_from="placed", max_shift_mm=40.0,
                               max_turn_deg=35.0)
    assert report["bones"]["femur_r"]["source"] == "own target"
    knee = sk.bones["femur_r"].landmark_in_world("knee")
    assert np.linalg.norm(knee - template.bones["femur_r"].landmark_in_world("knee")) > 40.0   # past the bound
    assert report["bones"]["foot_r"]["source"] == "neighbours"
    np.testing.assert_allclose(sk.bones["foot_r"].landmark_in_world("knee"), knee, atol=1e-6)
    # the foot's own surface went with it (it was not left where it was placed), and the toes with it
    shift = sk.world_mesh("foot_r").vertices.mean(0) - template.world_mesh("foot_r").vertices.mean(0)
    assert np.linalg.norm(shift) > 40.0
    assert report["bones"]["toes_r"]["source"] == "neighbours"
    np.testing.assert_allclose(sk.bones["toes_r"].landmark_in_world("mtp"), sk.bones["foot_r"].landmark_in_world("mtp"),
                               atol=1e-6)


def test_a_bone_below_an_own_target_turns_with_it():
    """A foot (no target) below a femur whose warp turns it 6 deg about the hip from where it was placed:
    the foot was placed with it and shares the placement's error, so it turns with the femur's rigid
    correction and keeps the template's joint angle (its frame relative to the femur's as the template
    has it), instead of keeping its placed orientation and only moving onto the knee. The pelvis, above
    the femur, is not turned."""
    bones, _, _ = femur_with_foot([60, 20, 25], [40, -20, 0], {"knee": [0, 0, 0]})
    template = Skeleton(bones, world="model", metadata=pelvis_template().metadata)
    hip = template.bones["femur_r"].landmark_in_world("hip")
    R = Rotation.from_rotvec(np.radians(6.0) * np.array([0.0, 0.6, 0.8])).as_matrix()
    targets = {}
    for side in ("r", "l"):
        w = template.world_mesh(f"femur_{side}").vertices
        if side == "r":
            w = (w - hip) @ R.T + hip
        targets[f"femur_{side}"] = Mesh(w, template.bones[f"femur_{side}"].mesh.faces, "lps")
    sk, report = warp_skeleton(template, targets, init=np.eye(4), start_from="placed", max_shift_mm=40.0,
                               max_turn_deg=35.0)
    assert report["bones"]["femur_r"]["source"] == "own target" and report["bones"]["foot_r"]["source"] == "neighbours"

    def turn(a, b):
        return np.degrees(Rotation.from_matrix(a[:3, :3].T @ b[:3, :3]).magnitude())

    # (its rigid ICP finds 5.2 of the 6 deg: the part about its long axis is weakly held by its shape)
    assert turn(template.bones["femur_r"].bone_to_world, sk.bones["femur_r"].bone_to_world) > 4.5
    rel_t = np.linalg.solve(template.bones["femur_r"].bone_to_world, template.bones["foot_r"].bone_to_world)
    rel_p = np.linalg.solve(sk.bones["femur_r"].bone_to_world, sk.bones["foot_r"].bone_to_world)
    assert turn(rel_t, rel_p) < 0.3                        # 5.2 deg when the foot kept its placed orientation
    np.testing.assert_allclose(sk.bones["foot_r"].landmark_in_world("knee"),
                               sk.bones["femur_r"].landmark_in_world("knee"), atol=1e-6)
    # the foot's surface went round with the femur's frame
    move = sk.bones["femur_r"].bone_to_world @ np.linalg.inv(template.bones["femur_r"].bone_to_world)
    foot = template.world_mesh("foot_r").vertices
    np.testing.assert_allclose(sk.world_mesh("foot_r").vertices, foot @ move[:3, :3].T + move[:3, 3], atol=1.0)
    for n in ("sacrum", "hip_r"):
        assert turn(template.bones[n].bone_to_world, sk.bones[n].bone_to_world) < 0.3


def test_two_close_joints_move_a_carried_bone_without_turning_it():
    """Two joints 30 mm apart, one warped 5 mm across their line: over a short baseline that is a 9.5 deg
    turn (and a stretch) of the whole bone; below ``min_baseline_mm`` the bone is only moved, onto their
    midpoint or onto the pinned one."""
    from bonecap.skeleton.warp import _carry

    M = np.eye(4)
    M[:3, 3] = [10.0, -4.0, 2.0]
    A = np.array([[0.0, 0.0, 0.0], [0.0, 30.0, 0.0]])
    B = A + M[:3, 3] + np.array([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0]])
    turned = _carry(M, A, B)
    angle = np.degrees(np.arccos(np.clip((np.trace(turned[:3, :3] / np.cbrt(np.linalg.det(turned[:3, :3]))) - 1) / 2,
                                         -1, 1)))
    assert angle > 8.0
    moved = _carry(M, A, B, min_baseline_mm=50.0)
    np.testing.assert_allclose(moved[:3, :3], np.eye(3), atol=1e-12)
    # the joints' midpoint lands on theirs
    np.testing.assert_allclose((moved[:3, :3] @ A.T).T.mean(0) + moved[:3, 3], B.mean(0), atol=1e-9)
    # a long baseline still turns it
    assert not np.allclose(_carry(M, A, B, min_baseline_mm=20.0)[:3, :3], np.eye(3))
    # pinned to the joint an own target placed (the glenohumeral centre on its humerus): that one lands
    pinned = _carry(M, A, B, min_baseline_mm=50.0, pin=np.array([False, True]))
    np.testing.assert_allclose(pinned[:3, :3], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(pinned[:3, :3] @ A[1] + pinned[:3, 3], B[1], atol=1e-9)


def _tapered_rod(length: float, radius: float = 6.0, taper: float = 30.0) -> trimesh.Trimesh:
    """A thin long bone of revolution along z from 0 (its distal tip) to ``length``: a shaft of ``radius``
    narrowing to a point over its last ``taper`` mm at z = 0 (a fibula's malleolus), a rounded top."""
    z = np.linspace(0.0, length, 121)
    r = radius * np.sqrt(np.clip(z / taper, 0, 1)) * np.sqrt(np.clip(1 - ((z - (length - 8.0)).clip(0) / 8.0) ** 2,
                                                                    0, 1))
    prof = np.column_stack([r, z])
    prof[0, 0] = prof[-1, 0] = 0.0
    return trimesh.creation.revolve(prof, sections=32)


def _cut_end_warps(sk, bone, target, unseen, landmark, truth, option):
    """The one-bone warp onto a target cut at one end, plain and with ``option`` (``cover`` or
    ``cover_marrow``) naming the bone: the landmark's error (mm) and the report, keyed False / True."""
    err, reps = {}, {}
    for on in (False, True):
        personal, rep = warp_skeleton(sk, {bone: target}, init=np.eye(4), start_from="placed", unseen=unseen,
                                      **{option: (bone,) if on else ()})
        err[on] = np.linalg.norm(personal.bones[bone].landmark_in_world(landmark) - truth)
        reps[on] = rep
    return err, reps


def _kept_above(V: np.ndarray, F: np.ndarray, z: float) -> Mesh:
    """The closed surface (V, F) cut at height ``z``, its part above kept and capped (a search's cut end)."""
    import pyvista as pv

    poly = pv.PolyData(V, np.hstack([np.full((len(F), 1), 3), F]).ravel())
    kept = poly.clip_closed_surface(normal=(0, 0, 1.0), origin=(0, 0, z)).triangulate()   # keeps z > cut
    kept = trimesh.Trimesh(np.asarray(kept.points), np.asarray(kept.faces).reshape(-1, 4)[:, 1:], process=True)
    assert kept.is_watertight and np.isclose(kept.vertices[:, 2].min(), z)
    return Mesh(np.asarray(kept.vertices), np.asarray(kept.faces), "lps")


def test_cover_extent_stretches_a_short_template_to_its_target():
    """cover_extent on analytic rods: a template 8 % short of its target at one end is stretched along its
    axis (anchored at the end that covers) to reach it, the section unchanged; a shortfall within the
    tolerance, a target shorter than the template, or a bone that is not elongated are left alone; a target
    far longer than the bone (something else) is refused."""
    from bonecap.skeleton.warp import cover_extent

    rod = _tapered_rod(300.0)
    V = np.asarray(rod.vertices)
    T0 = np.eye(4)
    T0[:3, :3] = Rotation.from_euler("xz", [20, -35], degrees=True).as_matrix()
    T0[:3, 3] = [5.0, -40.0, 300.0]
    longer = (V * [1, 1, 1.08] - [0, 0, 24.0]) @ T0[:3, :3].T + T0[:3, 3]   # 24 mm past the tip, top together
    T, rep = cover_extent(T0, V, longer)
    axis = T0[:3, :3] @ [0, 0, 1.0]
    got = V @ T[:3, :3].T + T[:3, 3]
    assert rep["stretch"] == pytest.approx(1.08, abs=1e-3) and rep["lo_mm"] == pytest.approx(24.0, abs=0.05)
    assert rep["hi_mm"] == 0.0
    assert np.isclose((got @ axis).min(), (longer @ axis).min(), atol=0.05)        # reaches the target's end
    assert np.isclose((got @ axis).max(), ((V @ T0[:3, :3].T + T0[:3, 3]) @ axis).max(), atol=0.05)  # anchored
    radial = got - np.outer(got @ axis, axis)
    radial0 = (V @ T0[:3, :3].T) - np.outer((V @ T0[:3, :3].T) @ axis, axis)
    assert np.allclose(np.linalg.norm(radial - radial.mean(0), axis=1),
                       np.linalg.norm(radial0 - radial0.mean(0), axis=1), atol=1e-6)   # the section as it was
    placed = V @ T0[:3, :3].T + T0[:3, 3]
    for tgt in (placed - 1.5 * axis, (V * [1, 1, 0.9]) @ T0[:3, :3].T + T0[:3, 3]):
        T1, rep1 = cover_extent(T0, V, tgt)
        assert rep1 is None and np.array_equal(T1, T0)
    blob = trimesh.creation.icosphere(3).vertices * [40, 30, 25]
    assert cover_extent(np.eye(4), blob, blob * 1.3)[1] is None
    T2, rep2 = cover_extent(T0, V, (V * [1, 1, 1.5]) @ T0[:3, :3].T + T0[:3, 3])
    assert "skipped" in rep2 and np.array_equal(T2, T0)
    with pytest.raises(ValueError, match="target_vertices"):
        cover_extent(T0, V, np.zeros((3, 2)))


def test_a_thin_bone_short_at_a_cut_end_is_covered():
    """A fibula-like rod 7 % longer than the template's, their tops together; the segmentation's search
    ended 14 mm above the true tip, and the extraction's last 15 mm slice pitch is declared unseen (a cut).
    The template's landmark 25 mm above its tip (the lateral malleolus) should follow the subject's.
    Plain, nothing holds the affine's length at the cut end: it stays short, and the narrow RBF kernels
    of a thin bone do not reach the landmark. With ``cover`` the affine is first stretched to the
    extraction's end, which halves the landmark's error (what is left is the part the search never saw)."""
    L = 380.0
    rod = _tapered_rod(L)
    V, F = np.asarray(rod.vertices), np.asarray(rod.faces)
    s = 1.07
    tV = V * [1.0, 1.0, s] - [0, 0, (s - 1.0) * L]          # tops together: the tip 26.6 mm lower
    lm0 = np.array([6.0 * np.sqrt(25.0 / 30.0), 0.0, 25.0])  # on the surface, 25 mm above the tip
    lm_true = lm0 * [1, 1, s] - [0, 0, (s - 1.0) * L]
    tip_true_z = tV[:, 2].min()
    cut_z = tip_true_z + 14.0
    target = _kept_above(tV, F, cut_z)
    sk = Skeleton({"fibula": Bone("fibula", None, Mesh(V, F, "fibula"), np.eye(4),
                                  joint_centres={"top": [0, 0, L]}, landmarks={"malleolus": lm0})}, world="model")
    unseen = {"fibula": [((0, 0, -1.0), -(cut_z + 15.0))]}     # z < cut + 15: the extraction's last pitch
    err, reps = _cut_end_warps(sk, "fibula", target, unseen, "malleolus", lm_true, "cover")
    assert "covered" in reps[True]["bones"]["fibula"] and "covered" not in reps[False]["bones"]["fibula"]
    assert reps[True]["bones"]["fibula"]["covered"]["lo_mm"] > 8.0
    # the affine-only baseline stays the plain affine ICP
    assert np.allclose(reps[True]["transforms"]["fibula"], reps[False]["transforms"]["fibula"])
    assert err[False] > 20.0, err                                    # 24.6 mm: up the shaft
    # the extraction itself ends 14 mm short of the tip: covered, the landmark is about that far off (13.3)
    assert err[True] < 0.6 * err[False] and err[True] < 15.0, err


def test_cover_extent_covers_only_the_ends_toward_the_given_directions():
    """A target longer than the template at both ends: ``directions`` limits the stretch to the ends lying
    toward them (a cut end), a direction across the bone to neither."""
    from bonecap.skeleton.warp import cover_extent

    V = np.asarray(_tapered_rod(300.0).vertices)
    both = V * [1, 1, 1.1] - [0, 0, 15.0]                    # 15 mm past each end
    T, rep = cover_extent(np.eye(4), V, both)
    assert rep["lo_mm"] == pytest.approx(15.0, abs=0.05) and rep["hi_mm"] == pytest.approx(15.0, abs=0.05)
    T, rep = cover_extent(np.eye(4), V, both, directions=[np.array([0.0, 0.1, -1.0])])
    assert rep["lo_mm"] == pytest.approx(15.0, abs=0.05) and rep["hi_mm"] == 0.0
    T, rep = cover_extent(np.eye(4), V, both, directions=[np.array([0.0, 0.0, 2.0])])
    assert rep["lo_mm"] == 0.0 and rep["hi_mm"] == pytest.approx(15.0, abs=0.05)
    T, rep = cover_extent(np.eye(4), V, both, directions=[np.array([1.0, 0.0, 0.0])])
    assert rep is None and np.array_equal(T, np.eye(4))


def test_a_bone_whose_extraction_ends_with_its_marrow_gets_its_tip_back():
    """A radius-like rod whose marrow ends 14 mm short of its tip (the styloid holds none), the subject's
    8 % longer, tops together. The cortical rule's extraction ends where the subject's marrow does, and
    that end is a cut (unseen). Plain, the warp leaves the tip where the template's shorter bone put it;
    with ``cover_marrow`` the template's marrow is stretched to the extraction's end, and the tip, 14 mm
    past it in the template, lands within a few mm of the subject's."""
    L, s, gap = 260.0, 1.08, 14.0
    rod = _tapered_rod(L, radius=7.0, taper=20.0)
    V, F = np.asarray(rod.vertices), np.asarray(rod.faces)
    inner = trimesh.creation.cylinder(radius=3.5, segment=[[0, 0, gap], [0, 0, L - 20.0]])
    tV = V * [1.0, 1.0, s] - [0, 0, (s - 1.0) * L]          # the subject: its tip (s - 1) L = 20.8 mm lower
    marrow_end = gap * s - (s - 1.0) * L
    target = _kept_above(tV, F, marrow_end)
    sk = Skeleton({"radius": Bone("radius", None, Mesh(V, F, "radius"), np.eye(4), joint_centres={"top": [0, 0, L]},
                                  landmarks={"styloid": [0.0, 0.0, 0.5]},
                                  inner_mesh=Mesh(np.asarray(inner.vertices), np.asarray(inner.faces), "radius"))},
                  world="model")
    unseen = {"radius": [((0, 0, -1.0), -(marrow_end + 5.0))]}
    tip_true = np.array([0.0, 0.0, 0.5 * s - (s - 1.0) * L])
    err, reps = _cut_end_warps(sk, "radius", target, unseen, "styloid", tip_true, "cover_marrow")
    assert "covered" not in reps[False]["bones"]["radius"]
    assert reps[True]["bones"]["radius"]["covered"]["marrow"]["lo_mm"] > 5.0
    assert err[False] > 10.0, err
    assert err[True] < 4.0, err


def test_a_bone_short_of_its_neighbour_s_length_is_warped_again_to_it():
    """A radius-like rod beside an ulna-like one, the subject's both 8 % longer, tops together. The ulna's
    extraction is whole; the radius's ends 20 mm short of its tip (where its marrow stopped showing), but the
    search went on past it, so nothing declares that end unseen. Plain, the warp takes the extraction's end
    for the bone's and the tip comes out short; with ``length_from`` the warp is found short of the length
    the ulna's warp gives the template radius, and is done again with that end cut and the affine stretched
    to that length: the tip within a few mm. A radius whose extraction is whole is left as the plain warp
    makes it; a neighbour without a target, or one that is not plausibly itself, lends nothing; names
    outside the template are refused."""
    from bonecap.skeleton.warp import LENGTH_FROM_MARGIN_MM

    L, s, gap = 260.0, 1.08, 20.0
    rod = _tapered_rod(L, radius=7.0, taper=20.0)
    V, F = np.asarray(rod.vertices), np.asarray(rod.faces)
    off = np.array([28.0, 0.0, 0.0])                         # the radius beside the ulna
    T_r = np.eye(4)
    T_r[:3, 3] = off
    sk = Skeleton({"ulna": Bone("ulna", None, Mesh(V, F, "ulna"), np.eye(4), joint_centres={"elbow_u": [0, 0, L]}),
                   "radius": Bone("radius", "ulna", Mesh(V, F, "radius"), T_r, joint_centres={"elbow_r": [0, 0, L]},
                                  landmarks={"styloid": [0.0, 0.0, 0.5]})}, world="model")
    tV = V * [1.0, 1.0, s] - [0, 0, (s - 1.0) * L]          # the subject: tips (s - 1) L = 20.8 mm lower
    tip_z = float(tV[:, 2].min())
    targets = {"ulna": Mesh(tV, F, "lps"), "radius": _kept_above(tV + off, F, tip_z + gap)}
    end = [((0, 0, -1.0), -(tip_z + gap + 5.0))]             # the extraction's last pitch, toward its distal end
    tip_true = off + [0.0, 0.0, 0.5 * s - (s - 1.0) * L]
    err, reps = {}, {}
    for on in (False, True):
        personal, rep = warp_skeleton(sk, targets, init=np.eye(4), start_from="placed",
                                      length_from={"radius": ("ulna", end)} if on else None)
        err[on] = float(np.linalg.norm(personal.bones["radius"].landmark_in_world("styloid") - tip_true))
        reps[on] = rep
    bone = reps[True]["bones"]["radius"]
    assert "length_from" not in reps[False]["bones"]["radius"] and "covered" not in reps[False]["bones"]["radius"]
    assert bone["length_from"]["used"] and bone["length_from"]["short_mm"] > LENGTH_FROM_MARGIN_MM, bone
    cov = bone["covered"]["neighbour"]
    assert max(cov["lo_mm"], cov["hi_mm"]) > 5.0 and min(cov["lo_mm"], cov["hi_mm"]) == 0.0, cov   # the cut end only
    assert cov["held_past_cut"] > 10 and len(bone["unseen"]) == 1
    assert err[False] > 12.0, err                                   # 16.5 mm
    assert err[True] < 4.0, err                                     # 2.6 mm
    # the ulna's own warp is the same either way
    assert np.allclose(reps[True]["transforms"]["ulna"], reps[False]["transforms"]["ulna"])
    # the radius's whole extraction: its warp reaches the ulna's length, and stays the plain one
    whole = {**targets, "radius": Mesh(tV + off, F, "lps")}
    plain, _ = warp_skeleton(sk, whole, init=np.eye(4), start_from="placed")
    checked, rep = warp_skeleton(sk, whole, init=np.eye(4), start_from="placed", length_from={"radius": ("ulna", end)})
    assert not rep["bones"]["radius"]["length_from"]["used"]
    # (the ulna's affine ICP on the tapered rod comes out 2.5 mm short: its RBF fits its own tip)
    assert abs(rep["bones"]["radius"]["length_from"]["short_mm"]) < 3.0, rep["bones"]["radius"]["length_from"]
    assert np.allclose(checked.bones["radius"].mesh.vertices, plain.bones["radius"].mesh.vertices)
    # no target for the neighbour: nothing to take the length from
    _, rep = warp_skeleton(sk, {"radius": targets["radius"]}, init=np.eye(4), start_from="placed",
                           length_from={"radius": ("ulna", end)})
    lf = rep["bones"]["radius"]["length_from"]
    assert lf["short_mm"] is None and not lf["used"] and "no plausible warp of ulna" in lf["why"]
    # a neighbour whose fit is implausible (its target turned 90 deg: another bone) lends nothing
    turned = Rotation.from_euler("x", 90, degrees=True).as_matrix()
    bad = {**targets, "ulna": Mesh(tV @ turned.T, F, "lps")}
    _, rep = warp_skeleton(sk, bad, init=np.eye(4), start_from="placed", max_turn_deg=35.0,
                           length_from={"radius": ("ulna", end)})
    assert rep["bones"]["ulna"]["source"] != "own target"
    assert not rep["bones"]["radius"]["length_from"]["used"]
    with pytest.raises(ValueError, match="length_from"):
        warp_skeleton(sk, targets, init=np.eye(4), length_from={"radius": ("nosuchbone", end)})
    with pytest.raises(ValueError, match="half-space"):
        warp_skeleton(sk, targets, init=np.eye(4), length_from={"radius": ("ulna", [])})
    # the same from the ancestor path (the ulna, its parent, warped first)
    personal, rep = warp_skeleton(sk, targets, init=np.eye(4), start_from="ancestor",
                                  length_from={"radius": ("ulna", end)})
    assert rep["bones"]["radius"]["length_from"]["used"]
    assert np.linalg.norm(personal.bones["radius"].landmark_in_world("styloid") - tip_true) < 4.0
    # another cut on the bone (its search ended past the proximal end too) is no length cut: with an ulna
    # standing 8 mm higher, only the distal end is stretched and held, and the radius's proximal joint stays
    # on the subject's (taken for a length cut, the top had been stretched 8.3 mm up too)
    top = [((0, 0, 1.0), float(tV[:, 2].max()) - 5.0)]
    higher = {**targets, "ulna": Mesh(tV + [0.0, 0.0, 8.0], F, "lps")}
    both, rep = warp_skeleton(sk, higher, init=np.eye(4), start_from="placed", unseen={"radius": top},
                              length_from={"radius": ("ulna", end)})
    bone = rep["bones"]["radius"]
    assert bone["length_from"]["used"] and len(bone["unseen"]) == 2
    cov = bone["covered"]["neighbour"]
    assert max(cov["lo_mm"], cov["hi_mm"]) > 5.0 and min(cov["lo_mm"], cov["hi_mm"]) == 0.0, cov
    assert np.linalg.norm(both.bones["radius"].landmark_in_world("elbow_r") - (off + [0.0, 0.0, L])) < 1.0


def test_a_slender_bone_s_affine_is_a_rigid_motion_with_two_scales():
    """A fibula-like rod (a flattened section with a knob at its tip, so that its turn is held) turned,
    moved, 5 % longer and 8 % thicker: ``axial_icp`` from the rigid fit, untrimmed, recovers the map (its
    scales to 0.005, the surface to 0.1 mm, every vertex within 1 mm). Through ``warp_skeleton`` a slender
    template bone's affine stage is this two-scale fit: onto a target squashed 25 % along a slant across
    it (a blurred or sheared extraction), the transform keeps one scale across the bone where a general
    affine takes the squash (three different stretches). The template's fibula is slender; its ulna,
    radius, femur, tibia and humerus are not."""
    from bonecap.skeleton.template import load_template
    from bonecap.skeleton.warp import SLENDER_RATIO, _slender, axial_icp

    rod = _tapered_rod(340.0)
    V = np.asarray(rod.vertices) * [1.0, 0.7, 1.0]
    knob = (V[:, 2] < 40.0) & (V[:, 0] > 0)
    V[knob, 0] *= 1.6                                        # the malleolus bulges to one side
    F = np.asarray(rod.faces)
    assert _slender(V)
    c = V.mean(axis=0)
    R = Rotation.from_euler("xyz", [3.0, -4.0, 6.0], degrees=True).as_matrix()
    S = np.diag([1.08, 1.08, 1.05])                          # across, across, along (the rod's axis is z)
    T = np.eye(4)
    T[:3, :3] = R @ S
    T[:3, 3] = c + [4.0, -2.0, 5.0] - R @ S @ c
    target = Mesh(V @ T[:3, :3].T + T[:3, 3], F, "lps")
    T_r, _ = rigid_icp(V, target)
    # every pair kept: along a shaft only the ends hold the length, and trimming drops them first
    T_x, res = axial_icp(V, target, init=T_r, trim=1.0)
    assert res.mean() < 0.1
    np.testing.assert_allclose(np.sort(np.linalg.svd(T_x[:3, :3], compute_uv=False)), [1.05, 1.08, 1.08], atol=0.005)
    # (the rings of this mesh lie 2.8 mm apart along the shaft: the fit may slide along it by a fraction of that)
    err = np.linalg.norm(V @ T_x[:3, :3].T + T_x[:3, 3] - target.vertices, axis=1)
    assert err.max() < 1.0, err.max()
    # squashed along a slant across the bone: two scales still (one of them across), the affine three
    u = np.array([1.0, 0.0, 0.35]) / np.linalg.norm([1.0, 0.0, 0.35])
    Q = np.eye(3) - 0.25 * np.outer(u, u)
    squashed = Mesh((V - c) @ Q.T + c, F, "lps")
    sk = Skeleton({"fibula_r": Bone("fibula_r", None, Mesh(V, F, "fibula_r"), np.eye(4),
                                    joint_centres={"top": [0.0, 0.0, 340.0]})}, world="model")
    _, rep = warp_skeleton(sk, {"fibula_r": squashed}, init=np.eye(4), start_from="placed")
    sv = np.sort(np.linalg.svd(np.asarray(rep["transforms"]["fibula_r"])[:3, :3], compute_uv=False))
    T_a, _ = affine_icp(V, squashed, init=np.eye(4))
    sva = np.sort(np.linalg.svd(T_a[:3, :3], compute_uv=False))
    assert min(sv[1] - sv[0], sv[2] - sv[1]) < 1e-6, sv
    assert min(sva[1] - sva[0], sva[2] - sva[1]) > 0.02, sva
    template = load_template("default")
    ratios = {}
    for b in ("fibula_r", "ulna_r", "radius_r", "femur_r", "tibia_r", "humerus_r"):
        v = template.bones[b].mesh.vertices
        s_ = np.linalg.svd(v - v.mean(axis=0), compute_uv=False)
        ratios[b] = s_[1] / s_[0]
    assert [b for b, r in ratios.items() if r < SLENDER_RATIO] == ["fibula_r"], ratios
