"""ISB frames from landmarks (bonecap.skeleton.isb): definitions match the template, refresh restores them."""

from __future__ import annotations

import numpy as np
import pytest

from bonecap.skeleton.generic import build_generic_skeleton
from bonecap.skeleton.isb import _reframe, isb_frame, refresh_isb_frames


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
