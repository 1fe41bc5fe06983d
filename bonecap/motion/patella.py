"""The patella's pose from the knee's flexion: the kneecap lags the tibia as the knee bends.

No marker set places a marker on the patella (it slides under the skin), so a
solver can only carry it. Carried rigidly with the femur at its reference
relative pose, it stays where it sat with the knee straight while the knee
flexes: in a phantom walk it was 13 deg off the truth at the median and 43 deg
at the knee's deepest flexion. The patella rides the femoral trochlea and is
tied to the tibial tuberosity by the patellar tendon; in vivo its flexion
relative to the femur lags the knee's by 30-40 % over the range of gait and
squatting [1]_. :func:`patella_from_knee` turns each patella that no marker
holds about the femur's mediolateral axis through the knee centre by
:data:`PATELLA_FLEXION_RATIO` times the knee's flexion from the reference pose.

The knee's flexion is the twist part of the tibia's rotation relative to the
femur (swing-twist decomposition about the femur frame's Z, the ISB
mediolateral axis of the generic skeleton and of OpenSim's femur bodies),
measured from the reference pose: 0 where the knee is as it was in the MRI (or
the template), whatever its absolute angle there. Both solvers get the same
rule (:func:`bonecap.animate.solve_trial`). An OpenSim model's own
patellofemoral coupling (Rajagopal 2016: a spline of the knee angle, about 0.8
at 90 deg) is not read; the ratio is applied to it too.

References
----------
.. [1] Yu Z, Yao J, Wang X, et al. (2019). Research methods and progress of
   patellofemoral joint kinematics: a review. J Healthc Eng 2019:9159267 --
   "the patellar flexion angle lagged by 30-40 % compared to the tibiofemoral
   joint flexion".
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from bonecap.model import Skeleton

__all__ = ["PATELLA_FLEXION_RATIO", "patella_from_knee", "knee_patellae"]

#: Patellar flexion relative to the femur per degree of knee flexion: the middle of the 30-40 % lag of [1]_.
PATELLA_FLEXION_RATIO = 0.65


def knee_patellae(skeleton: Skeleton, marker_bones: Sequence[str] = ()) -> list[tuple[str, str, str]]:
    """``(patella, femur, tibia)`` for every patella that hangs from a femur and carries no marker.

    A bone is a patella by its name (``patella...``); its parent must be a
    femur (``femur...``) with a tibia (``tibia...``) among its children.
    """
    carried = set(marker_bones)
    out = []
    for name, bone in skeleton.bones.items():
        if not name.startswith("patella") or name in carried or bone.parent is None:
            continue
        if not bone.parent.startswith("femur"):
            continue
        tibiae = [n for n, b in skeleton.bones.items() if b.parent == bone.parent and n.startswith("tibia")]
        if len(tibiae) == 1:
            out.append((name, bone.parent, tibiae[0]))
    return out


def _twist_about_z(R: np.ndarray) -> np.ndarray:
    """Signed angle (rad) of the twist part of rotations ``R`` (F, 3, 3) about Z.

    With the unit quaternion (x, y, z, w) of ``R``, the twist is ``2 atan2(z, w)``;
    ``4 w z = R[1, 0] - R[0, 1]`` and ``4 w^2 = 1 + trace(R)``, so it is
    ``2 atan2(R[1, 0] - R[0, 1], 1 + trace(R))`` without forming the quaternion
    (a few elementwise operations on every frame instead of scipy's conversion).
    """
    return 2.0 * np.arctan2(R[:, 1, 0] - R[:, 0, 1], 1.0 + np.trace(R, axis1=1, axis2=2))


def patella_from_knee(skeleton: Skeleton, bones: Sequence[str], transforms: np.ndarray,
                      marker_bones: Sequence[str] = (), ratio: float = PATELLA_FLEXION_RATIO) -> np.ndarray:
    """Turn marker-less patellae with their knee's flexion.

    Parameters
    ----------
    skeleton : Skeleton
        The subject at its reference pose (any world frame; frames ISB).
    bones : sequence of str
        Bone names of the second axis of ``transforms``.
    transforms : ndarray (F, B, 4, 4)
        Solved poses, bone frame -> lab (mm), NaN where invalid; each patella
        as the solver carried it (on its femur at the reference relative pose).
    marker_bones : sequence of str
        Bones that carry markers: a patella among them keeps its solved pose.
    ratio : float
        Patellar flexion per unit of knee flexion (:data:`PATELLA_FLEXION_RATIO`).

    Returns
    -------
    ndarray (F, B, 4, 4)
        A copy with each marker-less patella on its femur turned about the
        femur frame's Z through the knee centre by ``ratio`` x the knee's
        flexion from the reference pose. Where the femur is valid but the
        tibia is not (NaN), the knee's angle is unknown and so is the
        patella's pose: NaN.

    Raises
    ------
    ValueError
        On a ``transforms`` shape that does not match ``bones``, or a ratio
        outside [0, 1].

    References
    ----------
    .. [1] Yu et al. (2019), see the module.
    """
    from bonecap.skeleton.kinematics import proximal_joint

    T = np.asarray(transforms, float)
    names = list(bones)
    if T.ndim != 4 or T.shape[1:] != (len(names), 4, 4):
        raise ValueError(f"transforms must be (frames, {len(names)}, 4, 4) for {len(names)} bones, got {T.shape}")
    if not (np.isfinite(ratio) and 0.0 <= ratio <= 1.0):
        raise ValueError(f"ratio must be within [0, 1] (patellar per knee flexion), got {ratio!r}")
    out = T.copy()
    index = {n: i for i, n in enumerate(names)}
    for patella, femur, tibia in knee_patellae(skeleton, marker_bones):
        if not {patella, femur, tibia} <= set(index):
            continue
        Tf0, Tt0 = skeleton.bones[femur].bone_to_world, skeleton.bones[tibia].bone_to_world
        rest = np.linalg.solve(Tf0, skeleton.bones[patella].bone_to_world)      # patella in the femur frame
        R0 = Tf0[:3, :3].T @ Tt0[:3, :3]                                         # tibia in femur, reference
        Tf, Tt = T[:, index[femur]], T[:, index[tibia]]
        ok = np.isfinite(Tf).all(axis=(1, 2)) & np.isfinite(Tt).all(axis=(1, 2))
        out[~ok, index[patella]] = np.nan
        if not ok.any():
            continue
        D = np.swapaxes(Tf[ok, :3, :3], 1, 2) @ Tt[ok, :3, :3] @ R0.T            # knee motion, femur frame
        flex = _twist_about_z(D) * ratio
        _, centre, _ = proximal_joint(skeleton, tibia)                           # knee centre, femur frame
        c, s = np.cos(flex), np.sin(flex)
        M = np.tile(np.eye(4), (len(flex), 1, 1))
        M[:, 0, 0], M[:, 0, 1], M[:, 1, 0], M[:, 1, 1] = c, -s, s, c          # about Z
        M[:, :3, 3] = centre - M[:, :3, :3] @ centre
        out[ok, index[patella]] = Tf[ok] @ M @ rest
    return out
