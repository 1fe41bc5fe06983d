"""Forward kinematics: reference pose, joint-centre continuity, agreement with OpenSim's chain."""

from __future__ import annotations

import numpy as np
import pytest

from bonecap.skeleton.kinematics import pose_skeleton, proximal_joint
from bonecap.skeleton.opensim import read_osim


@pytest.fixture(scope="module")
def rajagopal(shared_data):
    return shared_data / "bones/opensim/models/Rajagopal2016.osim"


def _rest(skel):
    return np.stack([b.bone_to_world for b in skel.bones.values()])


def test_zero_rotations_give_the_reference_pose(rajagopal):
    skel = read_osim(rajagopal, load_meshes=False)
    root = skel.bones[skel.names[0]].bone_to_world
    poses = pose_skeleton(skel, root)
    assert np.allclose(poses[0], _rest(skel), atol=1e-9)


def test_joint_centres_stay_together_under_random_rotations(rajagopal):
    skel = read_osim(rajagopal, load_meshes=False)
    rng = np.random.default_rng(3)
    F = 7
    rots = {n: rng.normal(scale=0.6, size=(F, 3)) for n in skel.names[1:]}
    root = np.tile(np.eye(4), (F, 1, 1))
    root[:, :3, 3] = rng.normal(scale=500, size=(F, 3))
    poses = pose_skeleton(skel, root, rots)
    idx = {n: i for i, n in enumerate(skel.names)}
    for name in skel.names[1:]:
        joint, c_parent, c_child = proximal_joint(skel, name)
        parent = skel.bones[name].parent
        a = poses[:, idx[parent], :3, :3] @ c_parent + poses[:, idx[parent], :3, 3]
        b = poses[:, idx[name], :3, :3] @ c_child + poses[:, idx[name], :3, 3]
        assert np.allclose(a, b, atol=1e-6), (name, joint)
        # and every pose stays rigid
        R = poses[:, idx[name], :3, :3]
        assert np.allclose(R @ R.transpose(0, 2, 1), np.eye(3), atol=1e-9)


def test_hip_rotation_moves_the_whole_leg_like_opensim(rajagopal):
    """Flex the right hip in OpenSim's own chain; the same rotation at our hip centre
    must put femur, tibia and foot where the OpenSim reader puts them."""
    rest = read_osim(rajagopal, load_meshes=False)
    flexed = read_osim(rajagopal, load_meshes=False, coordinates={"hip_flexion_r": 0.7, "hip_adduction_r": -0.2})
    P = rest.bones["pelvis"].bone_to_world
    F0, Fq = rest.bones["femur_r"].bone_to_world, flexed.bones["femur_r"].bone_to_world
    R = (np.linalg.inv(P) @ Fq @ np.linalg.inv(F0) @ P)[:3, :3]  # femur rotation in the pelvis frame
    poses = pose_skeleton(rest, P, {"femur_r": R[None]})
    idx = {n: i for i, n in enumerate(rest.names)}
    for name in ("femur_r", "tibia_r", "calcn_r", "toes_r", "femur_l"):
        assert np.allclose(poses[0, idx[name]], flexed.bones[name].bone_to_world, atol=1e-6), name
    assert not np.allclose(poses[0, idx["tibia_r"]], rest.bones["tibia_r"].bone_to_world, atol=1.0)


def test_bad_input(rajagopal):
    skel = read_osim(rajagopal, load_meshes=False)
    with pytest.raises(ValueError, match="not in the skeleton"):
        pose_skeleton(skel, np.eye(4), {"wing": np.zeros((1, 3))})
    with pytest.raises(ValueError, match="root"):
        proximal_joint(skel, "pelvis")
    with pytest.raises(ValueError, match="rotation"):
        pose_skeleton(skel, np.eye(4), {"femur_r": np.zeros((1, 4))})


def test_joint_groups_join_names_with_side_suffixes_at_one_place():
    """``joint_groups``: the sacrum's ``sacroiliac_r`` and the right hip bone's ``sacroiliac`` are one
    joint; the left ones another; one name at two places is two joints; a one-bone joint is alone."""
    from bonecap.model import Bone, Skeleton
    from bonecap.skeleton.kinematics import joint_groups

    eye = np.eye(4)
    sk = Skeleton({
        "sacrum": Bone("sacrum", None, None, eye, joint_centres={"sacroiliac_r": [0, 0, 40],
                                                                 "sacroiliac_l": [0, 0, -40], "l5_s1": [0, 50, 0]}),
        "hip_r": Bone("hip_r", "sacrum", None, eye, joint_centres={"sacroiliac": [0, 0, 40.5], "hip": [0, -80, 90]}),
        "hip_l": Bone("hip_l", "sacrum", None, eye, joint_centres={"sacroiliac": [0, 0, -40], "hip": [0, -80, -90]}),
        "femur_r": Bone("femur_r", "hip_r", None, eye, joint_centres={"hip": [0, -80, 90]}),
        "femur_l": Bone("femur_l", "hip_l", None, eye, joint_centres={"hip": [0, -80, -60]}),   # 30 mm off
    }, world="model")
    groups = {frozenset(g) for g in joint_groups(sk)}
    assert frozenset({("sacrum", "sacroiliac_r"), ("hip_r", "sacroiliac")}) in groups
    assert frozenset({("sacrum", "sacroiliac_l"), ("hip_l", "sacroiliac")}) in groups
    assert frozenset({("hip_r", "hip"), ("femur_r", "hip")}) in groups
    assert frozenset({("hip_l", "hip")}) in groups and frozenset({("femur_l", "hip")}) in groups
    assert frozenset({("sacrum", "l5_s1")}) in groups
    assert sum(len(g) for g in groups) == 9
    with pytest.raises(ValueError):
        joint_groups(sk, tol_mm=-1.0)


def test_turn_about_keeps_its_point_and_turns_the_rest():
    """turn_about(point, R): the point stays, every other point turns by R about it."""
    from scipy.spatial.transform import Rotation

    from bonecap.skeleton.kinematics import turn_about

    R = Rotation.from_rotvec([0.3, -0.2, 0.9]).as_matrix()
    p = np.array([10.0, -20.0, 5.0])
    T = turn_about(p, R)
    assert np.allclose(T[:3, :3] @ p + T[:3, 3], p)
    q = np.array([[1.0, 2.0, 3.0], [-40.0, 7.0, 12.0]])
    assert np.allclose(q @ T[:3, :3].T + T[:3, 3], (q - p) @ R.T + p)
    assert np.array_equal(T[3], [0, 0, 0, 1])
