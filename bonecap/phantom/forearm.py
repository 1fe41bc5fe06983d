"""The phantom's forearm set: the subject's forearm posed at given pronation twists.

The paper fitted its pronation model from three forearm MRI stacks at measured
twists of 0, 99.5 and 172.1 degrees. This module poses the phantom subject's
forearm at such twists **from anatomy**: the radius turns about the ulna with
the trial synthesiser's own radio-ulnar model
(:func:`bonecap.phantom.trials.forearm_motion`: a screw about the line from the
radial-head centre to the ulnar-head fovea whose ends migrate a few mm with
the angle), never from the paper's quadratics, so the model that build-subject
fits is tested, not echoed.

Soft tissue follows: skin and fascia vertices that belong to the forearm and
hand (their nearest bone is the ulna, the radius or a hand bone) turn about the
same axis by a fraction of the twist that grows from 0 at the elbow to 1 at
the wrist, as the skin of a real forearm winds with the radius. The meshes keep
their topology, so capsules stuck to skin triangles ride along.

Frames: everything here is in the subject's world frame ``"model"`` (X
anterior, Y up, Z right, mm) at the MRI pose; :data:`MODEL_TO_LPS` turns it into
the LPS patient frame the DICOM stacks are written in.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from bonecap.model import Mesh, Skeleton
from bonecap.phantom.trials import ForearmSpec, forearm_motion, joint_table

__all__ = ["MODEL_TO_LPS", "PosedForearm", "pose_forearm", "forearm_bones"]

#: The template/subject world (X anterior, Y superior, Z right) in LPS patient
#: coordinates (+x left, +y posterior, +z superior): (x, y, z) -> (-z, -x, y).
MODEL_TO_LPS = np.array([[0.0, 0.0, -1.0, 0.0],
                         [-1.0, 0.0, 0.0, 0.0],
                         [0.0, 1.0, 0.0, 0.0],
                         [0.0, 0.0, 0.0, 1.0]])


@dataclass
class PosedForearm:
    """One forearm pose, world frame ``"model"`` (mm).

    Attributes
    ----------
    theta_deg : float
        Pronation twist (0 = the subject's supinated reference pose).
    bone_to_world : dict of str -> ndarray (4, 4)
        Posed ``bone_to_world`` of every bone that moved (radius, hand bones)
        and of the ulna (which does not).
    skin, muscle : Mesh
        The posed soft tissue (same topology as the subject's).
    axis_ends : ndarray (2, 3)
        Radial-head end and ulnar-head end of the radio-ulnar axis at this twist.
    elbow, wrist : ndarray (3,)
        Elbow and wrist joint centres: the stack's long axis.
    """

    theta_deg: float
    bone_to_world: dict[str, np.ndarray]
    skin: Mesh
    muscle: Mesh
    axis_ends: np.ndarray
    elbow: np.ndarray
    wrist: np.ndarray


def _descendants(skeleton: Skeleton, root: str) -> list[str]:
    out, todo = [], [root]
    while todo:
        b = todo.pop()
        out.append(b)
        todo += [n for n, bone in skeleton.bones.items() if bone.parent == b]
    return out


def forearm_bones(skeleton: Skeleton, spec: ForearmSpec) -> tuple[list[str], list[str]]:
    """``(moving, forearm)``: the bones that turn with the radius (radius and what hangs
    from it, the hand), and all forearm-and-hand bones (those plus the ulna)."""
    moving = _descendants(skeleton, spec.radius)
    hand_parent = spec.ulna
    extra = [b for b in _descendants(skeleton, hand_parent) if b not in moving and b != spec.ulna]
    # A hand hanging from the ulna (some models) turns with the radius as well.
    moving += extra
    return moving, moving + [spec.ulna]


def _tissue_weights(vertices: np.ndarray, bone_points: np.ndarray, bone_is_forearm: np.ndarray,
                    elbow: np.ndarray, wrist: np.ndarray) -> np.ndarray:
    """Share of the twist each soft-tissue vertex takes (0 off the forearm, 0 -> 1 elbow -> wrist)."""
    _, nearest = cKDTree(bone_points).query(vertices)
    on_forearm = bone_is_forearm[nearest]
    e = wrist - elbow
    s = (vertices - elbow) @ e / (e @ e)
    ramp = np.clip((s - 0.05) / 0.9, 0.0, 1.0)
    ramp = ramp * ramp * (3 - 2 * ramp)  # smoothstep: no crease at either end
    return np.where(on_forearm, ramp, 0.0)


def _screw_partial(points: np.ndarray, weights: np.ndarray, centre: np.ndarray, rotvec: np.ndarray) -> np.ndarray:
    """Rotate each point about the line (centre, rotvec) by ``weights`` x the full angle."""
    moved = points.copy()
    sel = weights > 0
    if np.any(sel):
        R = Rotation.from_rotvec(weights[sel, None] * rotvec[None])
        moved[sel] = R.apply(points[sel] - centre) + centre
    return moved


def pose_forearm(skeleton: Skeleton, skin: Mesh, muscle: Mesh, theta_deg: float, side: str = "r"
                 ) -> PosedForearm:
    """Pose one forearm of a phantom subject at a pronation twist.

    Parameters
    ----------
    skeleton : Skeleton
        The subject at its MRI pose (world frame ``"model"``).
    skin, muscle : Mesh
        The subject's soft-tissue surfaces, same frame.
    theta_deg : float
        Pronation twist, degrees (0 = supinated reference).
    side : {"r", "l"}

    Returns
    -------
    PosedForearm
    """
    if side not in ("r", "l"):
        raise ValueError(f"side must be 'r' or 'l', got {side!r}")
    table = joint_table(skeleton)
    key = f"radioulnar_{side}"
    if key not in table.forearms:
        raise ValueError(f"the skeleton has no {key} joint (bones {', '.join(skeleton.names)})")
    spec = table.forearms[key]
    U = skeleton.bones[spec.ulna].bone_to_world
    M, A, B = forearm_motion(spec, np.array([float(theta_deg)]))
    G = U @ M[0] @ np.linalg.inv(U)  # the radius's motion in the world frame
    moving, forearm = forearm_bones(skeleton, spec)
    posed = {b: G @ skeleton.bones[b].bone_to_world for b in moving}
    posed[spec.ulna] = U.copy()

    # Joint centres of the stack axis: the ulna's elbow and the radius's wrist.
    elbow = skeleton.bones[spec.ulna].landmark_in_world(_shared_centre(skeleton, spec.ulna, parent=True))
    wrist_name = _distal_centre(skeleton, spec.radius)
    wrist = skeleton.bones[spec.radius].landmark_in_world(wrist_name) if wrist_name else (U[:3, :3] @ spec.distal
                                                                                          + U[:3, 3])
    # Soft tissue: partial twist about the world axis of G.
    pts, is_fa = [], []
    for name, bone in skeleton.bones.items():
        if bone.mesh is None:
            continue
        v = skeleton.world_mesh(name).vertices[:: max(1, len(bone.mesh.vertices) // 400)]
        pts.append(v)
        is_fa.append(np.full(len(v), name in forearm))
    bone_points, bone_is_forearm = np.concatenate(pts), np.concatenate(is_fa)
    rotvec = Rotation.from_matrix(G[:3, :3]).as_rotvec()
    centre = U[:3, :3] @ A[0] + U[:3, 3]
    tissue = {}
    for label, mesh in (("skin", skin), ("muscle", muscle)):
        w = _tissue_weights(mesh.vertices, bone_points, bone_is_forearm, elbow, wrist)
        tissue[label] = Mesh(_screw_partial(mesh.vertices, w, centre, rotvec), mesh.faces.copy(), mesh.frame)
    ends = np.stack([U[:3, :3] @ A[0] + U[:3, 3], U[:3, :3] @ B[0] + U[:3, 3]])
    return PosedForearm(float(theta_deg), posed, tissue["skin"], tissue["muscle"], ends, elbow, wrist)


def _shared_centre(skeleton: Skeleton, bone: str, parent: bool) -> str:
    b = skeleton.bones[bone]
    other = skeleton.bones[b.parent] if parent and b.parent else None
    if other is not None:
        shared = sorted(set(b.joint_centres) & set(other.joint_centres))
        for prefer in ("elbow", "humeroulnar"):
            for s in shared:
                if prefer in s:
                    return s
        if shared:
            return shared[0]
    raise ValueError(f"bone {bone!r} has no joint centre shared with its parent")


def _distal_centre(skeleton: Skeleton, bone: str) -> str | None:
    for name in skeleton.bones[bone].joint_centres:
        if "wrist" in name or "radiocarpal" in name:
            return name
    return None
