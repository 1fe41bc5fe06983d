"""ISB frames from landmarks (bonecap.skeleton.isb): definitions match the template, refresh restores them."""

from __future__ import annotations

import numpy as np
import pytest

from bonecap.skeleton.generic import build_generic_skeleton
from bonecap.skeleton.isb import (_reframe, distal_fibula_bearing, distal_torsion, isb_frame, malleolar_frames,
                                  malleolar_turns, reframe_bone, refresh_isb_frames)


@pytest.fixture(scope="module")
def generic():
    return build_generic_skeleton()


def _angle(A, B):
    return np.degrees(np.arccos(np.clip((np.trace(A[:3, :3].T @ B[:3, :3]) - 1) / 2, -1, 1)))


@pytest.mark.parametrize("side", ["_r", "_l"])
def test_definitions_reproduce_the_generic_frames(generic, side):
    """The same definitions the template was built with, on either side (left frames: Z to the right)."""
    for base in ("femur", "tibia", "fibula", "talus", "calcaneus", "foot", "humerus", "ulna", "radius"):
        T = isb_frame(generic, base + side)
        T0 = generic.bones[base + side].bone_to_world
        assert T is not None, base
        assert _angle(T, T0) < 1e-6 and np.linalg.norm(T[:3, 3] - T0[:3, 3]) < 1e-6, base
    # a bone without a definition, or a missing landmark: None, not a guess
    assert isb_frame(generic, "sacrum") is None
    sk = build_generic_skeleton()
    del sk.bones["tibia" + side].landmarks["medial_malleolus"]
    assert isb_frame(sk, "tibia" + side) is None


def test_refresh_moves_a_drifted_origin_back_and_keeps_the_geometry(generic):
    sk = build_generic_skeleton()
    bad = sk.bones["tibia_r"].bone_to_world.copy()
    bad[:3, 3] += [20.0, -5.0, 10.0]                  # the frame drifted; the bone did not move
    sk.bones["tibia_r"] = _reframe(sk.bones["tibia_r"], bad)
    world_before = sk.world_mesh("tibia_r").vertices
    fixed, moved = refresh_isb_frames(sk, generic)
    assert moved["tibia_r"]["mm"] == pytest.approx(np.linalg.norm([20.0, -5.0, 10.0]), abs=1e-6)
    T = fixed.bones["tibia_r"].bone_to_world
    np.testing.assert_allclose(T[:3, 3], generic.bones["tibia_r"].bone_to_world[:3, 3], atol=1e-6)
    np.testing.assert_allclose(fixed.world_mesh("tibia_r").vertices, world_before, atol=1e-6)
    for k in ("knee", "ankle"):
        np.testing.assert_allclose(fixed.bones["tibia_r"].landmark_in_world(k),
                                   generic.bones["tibia_r"].landmark_in_world(k), atol=1e-6)
    # orientation kept by default, rebuilt on request
    turned = generic.bones["femur_r"].bone_to_world.copy()
    c, s = np.cos(np.radians(10)), np.sin(np.radians(10))
    turned[:3, :3] = turned[:3, :3] @ np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    sk.bones["femur_r"] = _reframe(sk.bones["femur_r"], turned)
    kept, _ = refresh_isb_frames(sk, generic)
    assert _angle(kept.bones["femur_r"].bone_to_world, turned) < 1e-6
    rebuilt, _ = refresh_isb_frames(sk, generic, rotation=True)
    assert _angle(rebuilt.bones["femur_r"].bone_to_world, generic.bones["femur_r"].bone_to_world) < 1e-6


def test_frames_of_another_template_are_left_alone(generic):
    """A template whose frames are not these definitions (an OpenSim model's bodies) is not re-framed."""
    sk = build_generic_skeleton()
    T = sk.bones["humerus_r"].bone_to_world.copy()
    T[:3, 3] += [0.0, -40.0, 0.0]                     # the template's own frame is elsewhere
    sk.bones["humerus_r"] = _reframe(sk.bones["humerus_r"], T)
    out, moved = refresh_isb_frames(sk, sk)
    assert "humerus_r" not in moved and "tibia_r" in moved and moved["tibia_r"]["mm"] < 1e-6
    np.testing.assert_allclose(out.bones["humerus_r"].bone_to_world, T)


def test_the_fibula_takes_its_tibias_frame(generic):
    """The fibula's frame is the tibia's (ISB's one tibia/fibula segment): a fibula whose carried frame
    turned 4 deg about the long axis gets the tibia's back, its geometry kept in world; a template whose
    fibula has a frame of its own is left alone."""
    sk = build_generic_skeleton()
    assert _angle(generic.bones["fibula_l"].bone_to_world, generic.bones["tibia_l"].bone_to_world) < 1e-9
    turned = sk.bones["fibula_l"].bone_to_world.copy()
    c, s = np.cos(np.radians(4)), np.sin(np.radians(4))
    turned[:3, :3] = turned[:3, :3] @ np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    sk.bones["fibula_l"] = _reframe(sk.bones["fibula_l"], turned)
    before = sk.world_mesh("fibula_l").vertices
    out, moved = refresh_isb_frames(sk, generic)
    assert moved["fibula_l"]["deg"] == pytest.approx(4.0, abs=1e-6)
    np.testing.assert_allclose(out.bones["fibula_l"].bone_to_world, out.bones["tibia_l"].bone_to_world, atol=1e-9)
    np.testing.assert_allclose(out.world_mesh("fibula_l").vertices, before, atol=1e-6)
    # a template with a fibula frame of its own (here: the turned one) keeps the fibula's
    own, moved_own = refresh_isb_frames(sk, sk)
    assert _angle(own.bones["fibula_l"].bone_to_world, turned) < 1e-6


def _turned_about_y(T, deg):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    out = T.copy()
    out[:3, :3] = T[:3, :3] @ np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return out


LEG = ("tibia", "fibula", "talus", "calcaneus", "foot")


def test_malleolar_turns_undo_a_carried_twist(generic):
    """A shank whose frames were carried 6 deg (right) and -4 deg (left) about the long axis, the bones
    themselves where they were (the warp's error on a tibia of another torsion), is turned back: the
    tibia's and fibula's frames to the template's, the feet's with them; nothing moves in world."""
    sk = build_generic_skeleton()
    for side, deg in (("_r", 6.0), ("_l", -4.0)):
        T = _turned_about_y(sk.bones["tibia" + side].bone_to_world, deg)
        W = T[:3, :3] @ sk.bones["tibia" + side].bone_to_world[:3, :3].T
        sk.bones["tibia" + side] = reframe_bone(sk.bones["tibia" + side], T)
        sk.bones["fibula" + side] = reframe_bone(sk.bones["fibula" + side], T)
        for b in LEG[2:]:
            Tb = sk.bones[b + side].bone_to_world.copy()
            Tb[:3, :3] = W @ Tb[:3, :3]
            sk.bones[b + side] = reframe_bone(sk.bones[b + side], Tb)
    measured = {b + s for b in ("tibia", "fibula") for s in ("_r", "_l")}
    turns = malleolar_turns(sk, generic, measured)
    assert turns["tibia_r"] == pytest.approx(-6.0, abs=1e-6)
    assert turns["tibia_l"] == pytest.approx(4.0, abs=1e-6)
    frames = malleolar_frames(sk, turns, measured)
    assert set(frames) == {b + s for b in LEG for s in ("_r", "_l")}
    for name, T in frames.items():
        assert _angle(T, generic.bones[name].bone_to_world) < 1e-4, name
        np.testing.assert_allclose(T[:3, 3], sk.bones[name].bone_to_world[:3, 3])
        before = sk.world_mesh(name).vertices
        moved = reframe_bone(sk.bones[name], T)
        np.testing.assert_allclose(moved.bone_to_world[:3, :3] @ moved.mesh.vertices.T + T[:3, 3:4],
                                   before.T, atol=1e-9)
    # a measured talus keeps its own frame
    assert "talus_r" not in malleolar_frames(sk, turns, measured | {"talus_r"})


def test_malleolar_turns_need_both_bones_measured_and_stay_bounded(generic):
    sk = build_generic_skeleton()
    assert malleolar_turns(sk, generic, {"tibia_r", "fibula_r", "tibia_l", "fibula_l"}) == pytest.approx(
        {"tibia_r": 0.0, "tibia_l": 0.0}, abs=1e-9)
    assert malleolar_turns(sk, generic, {"tibia_r", "fibula_l"}) == {}
    for b in ("tibia_r", "fibula_r"):
        sk.bones[b] = reframe_bone(sk.bones[b], _turned_about_y(generic.bones["tibia_r"].bone_to_world, 25.0))
    assert "tibia_r" not in malleolar_turns(sk, generic, {"tibia_r", "fibula_r"})
    assert malleolar_turns(sk, generic, {"tibia_r", "fibula_r"}, max_deg=30.0)["tibia_r"] == pytest.approx(
        -25.0, abs=1e-6)
    # the bearing itself, atan2(anterior, rightward): the fibula lies lateral and a little posterior of
    # the tibia above the ankle (right: Z lateral, a small negative angle; left: -Z, near -180)
    a_r, a_l = distal_fibula_bearing(generic, "_r"), distal_fibula_bearing(generic, "_l")
    assert -30.0 < a_r < 0.0 and 150.0 < abs(a_l), (a_r, a_l)
    with pytest.raises(ValueError, match="side"):
        distal_fibula_bearing(generic, "r")
    with pytest.raises(ValueError, match="window"):
        distal_fibula_bearing(generic, "_r", window=(0.3, 0.2))
    with pytest.raises(ValueError, match="max_deg"):
        malleolar_turns(sk, generic, set(), max_deg=0.0)
    with pytest.raises(ValueError, match="4x4"):
        reframe_bone(sk.bones["tibia_r"], np.eye(3))


def _shank_reshaped(side, deg, scale, fibula_shift_mm=0.0):
    """The generic skeleton with one shank's tibia and fibula turned ``deg`` about the tibia's long axis in its
    frame and scaled by ``scale`` about its origin (frames unchanged), the fibula moved ``fibula_shift_mm``
    anteriorly besides."""
    import dataclasses

    from bonecap.model import Mesh

    sk = build_generic_skeleton()
    c, s_ = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    R = np.array([[c, 0, s_], [0, 1, 0], [-s_, 0, c]])
    tib, fib = sk.bones["tibia" + side], sk.bones["fibula" + side]
    M = np.linalg.solve(tib.bone_to_world, fib.bone_to_world)           # fibula frame -> tibia frame
    w = fib.mesh.vertices @ M[:3, :3].T + M[:3, 3]
    w = scale * w @ R.T + [fibula_shift_mm, 0.0, 0.0]
    sk.bones["tibia" + side] = dataclasses.replace(tib, mesh=Mesh(scale * tib.mesh.vertices @ R.T, tib.mesh.faces,
                                                                  tib.mesh.frame))
    sk.bones["fibula" + side] = dataclasses.replace(fib, mesh=Mesh((w - M[:3, 3]) @ M[:3, :3], fib.mesh.faces,
                                                                   fib.mesh.frame))
    return sk


def test_distal_torsion_reads_the_shank_s_turn_whatever_its_size(generic):
    """A shank turned 7 deg (right) and -5 deg (left) about its long axis, 6 % larger or smaller than the
    template's: the registration of both bones' distal surfaces reads the turns exactly; a fibula lying 1.5 mm
    more anterior beside an unturned tibia (a person's, not a torsion) reads 0.6 of what its centroid's bearing
    does (the bones weighted alike); nothing to read without both bones."""
    for side, deg, scale in (("_r", 7.0, 1.06), ("_l", -5.0, 0.94)):
        sk = _shank_reshaped(side, deg, scale)
        assert distal_torsion(sk, generic, side) == pytest.approx(deg, abs=0.01)
        assert distal_torsion(generic, generic, side) == pytest.approx(0.0, abs=1e-9)
    sk = _shank_reshaped("_r", 0.0, 1.0, fibula_shift_mm=1.5)
    bearing = distal_fibula_bearing(sk, "_r") - distal_fibula_bearing(generic, "_r")
    assert bearing > 2.0                                      # 2.7 deg
    assert abs(distal_torsion(sk, generic, "_r")) < 0.65 * bearing  # 1.6 deg
    # the turn applied puts the shank's frame where the template's distal bones say
    assert malleolar_turns(_shank_reshaped("_r", 7.0, 1.06), generic, {"tibia_r", "fibula_r"})["tibia_r"] \
        == pytest.approx(7.0, abs=0.01)
    import dataclasses
    bare = build_generic_skeleton()
    bare.bones["fibula_r"] = dataclasses.replace(bare.bones["fibula_r"], mesh=None)
    assert distal_torsion(bare, generic, "_r") is None
    with pytest.raises(ValueError, match="side"):
        distal_torsion(generic, generic, "r")
    with pytest.raises(ValueError, match="keep"):
        distal_torsion(generic, generic, "_r", keep=0.0)
