"""The patella's pose from the knee's flexion (bonecap.motion.patella): analytic knee bends."""

from __future__ import annotations

import numpy as np
import pytest

from bonecap.motion.patella import PATELLA_FLEXION_RATIO, knee_patellae, patella_from_knee
from bonecap.skeleton.generic import build_generic_skeleton
from bonecap.skeleton.kinematics import proximal_joint


@pytest.fixture(scope="module")
def sk():
    return build_generic_skeleton()


def _about(axis_world, centre_world, deg):
    from scipy.spatial.transform import Rotation

    M = np.eye(4)
    M[:3, :3] = Rotation.from_rotvec(np.radians(deg) * np.asarray(axis_world)).as_matrix()
    M[:3, 3] = centre_world - M[:3, :3] @ centre_world
    return M


def _bent(sk, side, degs, lab=np.eye(4)):
    """Poses (F, B, 4, 4): the whole skeleton moved by ``lab``, the shank (tibia and below) turned about
    the femur's Z through the knee centre by each of ``degs``; the patella left on the femur."""
    names = sk.names
    femur, tibia = "femur" + side, "tibia" + side
    Tf = sk.bones[femur].bone_to_world
    _, c_f, _ = proximal_joint(sk, tibia)
    centre, axis = Tf[:3, :3] @ c_f + Tf[:3, 3], Tf[:3, :3] @ [0.0, 0.0, 1.0]
    shank = {tibia}
    for n in names:
        if sk.bones[n].parent in shank:
            shank.add(n)
    out = np.zeros((len(degs), len(names), 4, 4))
    for f, d in enumerate(degs):
        M = _about(axis, centre, d)
        for i, n in enumerate(names):
            out[f, i] = lab @ (M if n in shank else np.eye(4)) @ sk.bones[n].bone_to_world
    return out, axis, centre


def test_the_patella_turns_by_the_ratio_of_the_knee_flexion(sk):
    assert ("patella_r", "femur_r", "tibia_r") in knee_patellae(sk)
    assert "patella_r" not in [p for p, _, _ in knee_patellae(sk, ["patella_r"])]
    lab = _about([1.0, 0.0, 0.0], np.array([100.0, 0.0, 900.0]), 30.0)      # any lab pose of the body
    degs = [0.0, -20.0, -60.0, 10.0]
    T, axis, centre = _bent(sk, "_r", degs, lab)
    names = sk.names
    ip, il = names.index("patella_r"), names.index("patella_l")
    out = patella_from_knee(sk, names, T)
    for f, d in enumerate(degs):
        want = lab @ _about(axis, centre, PATELLA_FLEXION_RATIO * d) @ sk.bones["patella_r"].bone_to_world
        np.testing.assert_allclose(out[f, ip], want, atol=1e-6)
        np.testing.assert_allclose(out[f, il], T[f, il], atol=1e-9)          # the straight knee's stays
    # every other bone untouched; a patella with markers of its own keeps its solved pose
    others = [i for i, n in enumerate(names) if not n.startswith("patella")]
    np.testing.assert_array_equal(out[:, others], T[:, others])
    np.testing.assert_array_equal(patella_from_knee(sk, names, T, ["patella_r"])[:, ip], T[:, ip])
    # a lost tibia: the knee's angle is unknown, and so is the patella's pose
    T2 = T.copy()
    T2[1, names.index("tibia_r")] = np.nan
    out2 = patella_from_knee(sk, names, T2)
    assert np.isnan(out2[1, ip]).all() and np.isfinite(out2[[0, 2, 3], ip]).all()


def test_patella_from_knee_checks_its_inputs(sk):
    T, _, _ = _bent(sk, "_l", [0.0])
    with pytest.raises(ValueError, match="frames"):
        patella_from_knee(sk, sk.names[:-1], T)
    with pytest.raises(ValueError, match="ratio"):
        patella_from_knee(sk, sk.names, T, ratio=1.5)
