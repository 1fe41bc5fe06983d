"""The paper's rule-based solver: pinned angle rules, twist, exact recovery of rigid motion."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bonecap.motion.paper import (axis_angles, joint_centre_from_markers, joint_centre_offset, marker_frame,
                                  minimal_rotation, paper_rotation, solve_bone, to_paper_frame, twist_angle)


@pytest.mark.parametrize("a,theta_z", [
    ([1, 1, 0], 45.0), ([1, 0, 0], 90.0), ([0, -1, 0], 180.0), ([-1, 0, 0], 270.0), ([-1, 1, 0], 315.0),
    ([0, 1, 0], 0.0), ([1, -1, 0], 135.0), ([-1, -1, 0], 225.0),
])
def test_theta_z_quadrants(a, theta_z):
    tz, tx = axis_angles(np.array([a], dtype=float))
    assert tz[0] == pytest.approx(theta_z)
    assert tx[0] == pytest.approx(0.0)


@pytest.mark.parametrize("r,theta_x", [(1, 45.0), (-1, -45.0)])
def test_theta_x(r, theta_x):
    tz, tx = axis_angles(np.array([[0.0, 1.0, r]]))
    assert tx[0] == pytest.approx(theta_x) and tz[0] == pytest.approx(0.0)


def test_rotation_takes_rest_axis_to_the_bone():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(500, 3))
    tz, tx = axis_angles(a)
    R = paper_rotation(tz, tx, rng.uniform(-180, 180, size=500))
    assert np.allclose(R @ [0.0, 1.0, 0.0], a / np.linalg.norm(a, axis=1, keepdims=True), atol=1e-12)


def test_vertical_bone_holds_the_previous_theta_z():
    a = np.array([[1.0, 1.0, 0.2], [0.0, 0.0, 1.0], [0.0, 1e-12, -1.0], [0.0, -1.0, 0.0]])
    tz, tx = axis_angles(a)
    assert tz[1] == pytest.approx(45.0) and tz[2] == pytest.approx(45.0) and tz[3] == pytest.approx(180.0)
    assert tx[1] == pytest.approx(90.0) and tx[2] == pytest.approx(-90.0)


def test_lab_to_paper_frame():
    assert np.allclose(to_paper_frame([1.0, 2.0, 3.0]), [1.0, 3.0, -2.0])
    assert np.allclose(to_paper_frame([1.0, 2.0, 3.0], lab_up="y"), [1.0, 2.0, 3.0])


def test_minimal_rotation_is_minimal_and_handles_opposites():
    rng = np.random.default_rng(1)
    u, v = rng.normal(size=(100, 3)), rng.normal(size=(100, 3))
    R = minimal_rotation(u, v)
    un, vn = u / np.linalg.norm(u, axis=1, keepdims=True), v / np.linalg.norm(v, axis=1, keepdims=True)
    assert np.allclose(np.einsum("fij,fj->fi", R, un), vn, atol=1e-12)
    angle = Rotation.from_matrix(R).magnitude()
    assert np.allclose(angle, np.arccos(np.clip(np.sum(un * vn, axis=1), -1, 1)), atol=1e-9)
    Rop = minimal_rotation(np.array([[0.0, 0.0, 1.0]]), np.array([[0.0, 0.0, -1.0]]))
    assert np.allclose(Rop[0] @ [0, 0, 1.0], [0, 0, -1.0]) and np.isclose(np.linalg.det(Rop[0]), 1.0)


def test_twist_angle_recovers_a_known_axial_rotation():
    rng = np.random.default_rng(2)
    axis_s, tw_s = np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.3])
    twists = rng.uniform(-170, 170, size=50)
    # swing the bone anywhere, then twist it about its new axis by a known angle
    swing = Rotation.from_rotvec(rng.normal(scale=0.8, size=(50, 3)))
    axis = swing.apply(axis_s)
    M = minimal_rotation(np.broadcast_to(axis_s, axis.shape), axis)
    carried = M @ tw_s
    tw = Rotation.from_rotvec(axis * np.radians(twists)[:, None]).apply(carried)
    assert np.allclose(twist_angle(axis_s, tw_s, axis, tw), twists, atol=1e-9)


def test_solve_bone_recovers_any_rigid_motion_exactly():
    rng = np.random.default_rng(3)
    F = 200
    # A humerus-like bone in its own frame: proximal (0,0,0), distal 300 mm down its -Y... any geometry works.
    prox_l, dist_l = np.array([0.0, 0.0, 0.0]), np.array([5.0, -300.0, 8.0])
    tw_from_l, tw_to_l = np.array([0.0, -280.0, -40.0]), np.array([0.0, -280.0, 40.0])
    bone_static = np.eye(4)
    bone_static[:3, :3] = Rotation.from_rotvec([0.2, 1.0, -0.4]).as_matrix()
    bone_static[:3, 3] = [100.0, 200.0, 1400.0]
    motion = np.tile(np.eye(4), (F, 1, 1))
    motion[:, :3, :3] = Rotation.from_rotvec(rng.normal(scale=1.0, size=(F, 3))).as_matrix()
    motion[:, :3, 3] = rng.normal(scale=300.0, size=(F, 3))
    motion[0] = np.eye(4)  # frame 0 is the static pose
    truth = motion @ bone_static

    def lab(p):
        return truth[:, :3, :3] @ p + truth[:, :3, 3]

    out = solve_bone(lab(prox_l), lab(dist_l), lab(tw_from_l), lab(tw_to_l), 0, bone_static)
    assert np.allclose(out["transforms"], truth, atol=1e-8)
    # the paper's decomposition reproduces the same orientation
    R = paper_rotation(out["theta_z"], out["theta_x"], out["theta_y"])
    a = to_paper_frame(lab(dist_l) - lab(prox_l))
    assert np.allclose(R @ [0.0, 1.0, 0.0], a / np.linalg.norm(a, axis=1, keepdims=True), atol=1e-9)


def test_joint_centre_offset_is_preserved_in_the_marker_frame():
    rng = np.random.default_rng(4)
    A, B, axis = np.array([10.0, 0, 0]), np.array([-10.0, 5, 0]), np.array([0.0, 0, 1])
    centre = np.array([3.0, 20.0, -15.0])
    frame_s = marker_frame((A + B) / 2, A, axis)[0]
    off = joint_centre_offset(frame_s, centre)
    G = Rotation.from_rotvec(rng.normal(size=(20, 3)))
    t = rng.normal(scale=100, size=(20, 3))
    frames = marker_frame(G.apply((A + B) / 2) + t, G.apply(A) + t, G.apply(axis))
    assert np.allclose(joint_centre_from_markers(frames, off), G.apply(centre) + t, atol=1e-9)
