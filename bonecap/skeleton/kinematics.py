"""Forward kinematics of a :class:`~bonecap.model.Skeleton`: joint rotations -> bone poses.

A skeleton's bones form a tree. Each child meets its parent at a joint centre
that both bones list under the same name in ``joint_centres`` (the generic
skeleton and the OpenSim reader both follow this rule). A pose of the whole
skeleton is the root bone's pose plus, for every other bone, a rotation about
its joint centre **expressed in the parent bone's frame**; translations at the
joints are not modelled (ball joints), which is what the phantom's motion
synthesis and the joint-coupled solvers need.

Frames: ``bone_to_world`` of the reference pose maps a bone frame to the
skeleton's world frame; the results here map each bone frame to the frame
the root pose is given in (``root_to_lab``), usually the lab.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from bonecap.model import Skeleton

__all__ = ["joint_groups", "proximal_joint", "joint_pair", "parent_joint_key", "pose_skeleton", "subtree",
           "turn_about", "PIVOT_JOINTS", "HINGE_JOINTS", "GIRDLE_JOINTS", "AXIS_HOLD_JOINTS"]

#: Where a bone shares several joint-centre names with its parent, the one that is a
#: true pivot. The radius shares "elbow", "proximal_radioulnar" and "distal_radioulnar"
#: with the ulna; it turns about the axis through the radial head, whose centre the
#: generic skeleton names "proximal_radioulnar" -- the other two slide by design.
PIVOT_JOINTS = ("proximal_radioulnar",)

#: Joints that are hinges (one rotational degree of freedom about the axis the bones give in
#: ``joint_axes``), by name without the side suffix. The humero-ulnar joint is one (a pin joint
#: in OpenSim's arm models, the phantom's elbow): the ulna flexes on the humerus and does not
#: turn with the radius. Its markers are few (one in the Rajagopal model's MarkerSet, the
#: ulnar styloid in Plug-in Gait), so without the hinge nothing holds its twist. The radius
#: turns on the ulna about the radio-ulnar axis (OpenSim's ``radioulnar`` pin joint; the axis
#: migrates by a few millimetres, Kojima et al.), so through that hinge the radius's wrist
#: markers also set the ulna's flexion, which its one marker over the proximal shaft, 10-15 mm
#: from where a template puts it, set 12-16 degrees off. The generic skeleton's radius pivots at
#: ``proximal_radioulnar``, which has no axis of that name: the forearm model drives it there.
#: The solver uses a hinge only where a bone's markers cannot hold it on ball joints
#: (:func:`bonecap.motion.lsq.plan_segments`), and, for a template that declares its joints (an
#: OpenSim model), only where it declares the joint with one coordinate (its pin joints); the
#: embedded skeleton declares none and takes these as the hinges anatomy makes them.
HINGE_JOINTS = ("elbow", "radioulnar")

#: Joints by which a shoulder girdle (clavicle and scapula) hangs on the thorax, by name without
#: the side suffix. The acromion marker rides on the girdle, and the girdle does not ride rigidly on
#: the thorax: with the arm's elevation the scapula turns upward and the clavicle rises (the
#: scapulohumeral rhythm, Inman et al. 1944; clavicle elevation and retraction, de Groot & Brand
#: 2001), and the acromion moves by centimetres. A girdle with a marker gets a pose of its own
#: (:func:`bonecap.motion.lsq.plan_segments`).
GIRDLE_JOINTS = ("sternoclavicular",)

#: Joints whose child turns freely about the joint's axis (``joint_axes``) and little otherwise, and
#: whose markers see those other turns poorly, by name without the side suffix: the ankle. The foot's
#: heel and toe markers lie 20-60 mm from the line through them and the ankle centre, so a heel
#: marker a few centimetres off its place (a real trial's left heel: 70-97 mm from the ankle marker in
#: one walk, 98 in the static) rolls the foot about that line by tens of degrees; Plug-in Gait takes
#: the foot's roll from the shank for the same reason. The solver holds the child's turns other than
#: about the axis weakly at their reference relative pose (:func:`bonecap.motion.lsq.plan_segments`).
AXIS_HOLD_JOINTS = ("ankle",)


def joint_groups(skeleton: Skeleton, tol_mm: float = 2.0) -> list[list[tuple[str, str]]]:
    """Joint centres that are one joint, as groups of ``(bone, joint name)``.

    Two bones list the same joint when the names match, or one is the other
    with a side suffix (the sacrum's ``sacroiliac_r`` and the right hip bone's
    ``sacroiliac``), and the two centres lie within ``tol_mm`` of each other
    in the skeleton's world. Used wherever a joint must be one place: the
    warp's shared joint centres, the phantom's bones re-placed on their
    parents' joints, build-subject's bone seeds across a joint.

    Parameters
    ----------
    skeleton : Skeleton
    tol_mm : float
        Largest distance between two listings of one joint (mm).

    Returns
    -------
    list of list of (str, str)
        Every joint centre of every bone in exactly one group (a joint
        listed by one bone only is a group of one).
    """
    if not tol_mm >= 0:
        raise ValueError(f"tol_mm must be >= 0, got {tol_mm}")
    entries = [(b, k) for b, bone in skeleton.bones.items() for k in bone.joint_centres]
    pos = np.array([skeleton.bones[b].landmark_in_world(k) for b, k in entries]) if entries else np.zeros((0, 3))
    parent = list(range(len(entries)))

    def find(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    if entries:
        for i, j in cKDTree(pos).query_pairs(tol_mm):
            (bi, ki), (bj, kj) = entries[i], entries[j]
            if bi != bj and (ki == kj or ki.startswith(kj + "_") or kj.startswith(ki + "_")):
                parent[find(i)] = find(j)
    groups: dict[int, list[tuple[str, str]]] = {}
    for i, e in enumerate(entries):
        groups.setdefault(find(i), []).append(e)
    return list(groups.values())


def turn_about(point, R) -> np.ndarray:
    """The rigid 4x4 that turns by the 3x3 rotation ``R`` about ``point`` (which stays where it is), in
    whatever frame both are given."""
    R = np.asarray(R, float)
    point = np.asarray(point, float)
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = point - R @ point
    return T


def subtree(skeleton: Skeleton, root: str) -> list[str]:
    """``root`` and every bone below it, parents before children (the skeleton's own order)."""
    out = [root]
    for name, b in skeleton.bones.items():
        if b.parent in out and name not in out:
            out.append(name)
    return out


def proximal_joint(skeleton: Skeleton, bone: str, pivots: Sequence[str] = ()) -> tuple[str, np.ndarray, np.ndarray]:
    """The joint where ``bone`` meets its parent.

    Parameters
    ----------
    skeleton : Skeleton
    bone : str
    pivots : sequence of str
        Where the bone shares several joint-centre names with its parent, the
        first of these among them is the joint (e.g. :data:`PIVOT_JOINTS` for
        the radius on the ulna); without one, sharing several is an error.

    Returns
    -------
    name : str
        The joint centre's name, shared by the bone and its parent.
    centre_in_parent : ndarray (3,)
        The joint centre in the parent's frame (mm).
    centre_in_child : ndarray (3,)
        The joint centre in the bone's own frame (mm).

    Raises
    ------
    ValueError
        If the bone is the root, or it shares no (or more than one, none of
        them in ``pivots``) joint centre name with its parent.
    """
    b = skeleton.bones[bone]
    if b.parent is None:
        raise ValueError(f"bone {bone!r} is the root: it has no proximal joint")
    parent = skeleton.bones[b.parent]
    shared = sorted(set(b.joint_centres) & set(parent.joint_centres))
    pivot = [n for n in pivots if n in shared]
    if len(shared) > 1 and pivot:
        shared = pivot[:1]
    if len(shared) != 1:
        raise ValueError(f"bone {bone!r} and its parent {b.parent!r} must share exactly one joint centre name, "
                         f"they share {shared or 'none'}")
    name = shared[0]
    return name, parent.joint_centres[name], b.joint_centres[name]


def joint_pair(skeleton: Skeleton, bone: str, pivots: Sequence[str] = ()) -> tuple[np.ndarray, np.ndarray] | None:
    """The joint centre tying ``bone`` to its parent as ``(centre_in_parent, centre_in_child)``, or None.

    :func:`proximal_joint`'s joint, or else a girdle joint (:data:`GIRDLE_JOINTS`) that the parent
    lists once per side: the embedded skeleton's sternum has ``sternoclavicular_r`` and
    ``sternoclavicular_l``, each clavicle its ``sternoclavicular``. None for the root and for a bone
    that meets its parent at no named joint (it rides on the parent).
    """
    b = skeleton.bones[bone]
    if b.parent is None:
        return None
    try:
        _, c_parent, c_child = proximal_joint(skeleton, bone, pivots)
        return c_parent, c_child
    except ValueError:
        pass
    for name in GIRDLE_JOINTS:
        key = parent_joint_key(skeleton, bone, name) if name in b.joint_centres else None
        if key is not None:
            return skeleton.bones[b.parent].joint_centres[key], b.joint_centres[name]
    return None


def parent_joint_key(skeleton: Skeleton, bone: str, joint: str) -> str | None:
    """The name under which ``bone``'s parent lists the joint ``joint``: the same, or with the bone's
    side suffix (the sternum's ``sternoclavicular_r`` for the right clavicle's ``sternoclavicular``);
    None when the parent does not list it."""
    parent = skeleton.bones[skeleton.bones[bone].parent]
    if joint in parent.joint_centres:
        return joint
    side = bone[-2:] if bone.endswith(("_r", "_l")) else ""
    return joint + side if side and joint + side in parent.joint_centres else None


def _as_matrices(rot, n_frames: int, bone: str) -> np.ndarray:
    rot = np.asarray(rot, dtype=float)
    if rot.shape[-2:] == (3, 3):
        mats = rot
    elif rot.shape[-1] == 3:
        mats = Rotation.from_rotvec(rot.reshape(-1, 3)).as_matrix().reshape(rot.shape[:-1] + (3, 3))
    else:
        raise ValueError(f"rotation of bone {bone!r} must be (F, 3) rotation vectors or (F, 3, 3) matrices, "
                         f"got shape {rot.shape}")
    return np.broadcast_to(mats, (n_frames, 3, 3))


def pose_skeleton(skeleton: Skeleton, root_to_lab: np.ndarray,
                  joint_rotations: dict[str, np.ndarray] | None = None, *,
                  pivots: Sequence[str] = ()) -> np.ndarray:
    """Bone poses for a sequence of joint rotations.

    Parameters
    ----------
    skeleton : Skeleton
        Bones in parent-before-child order, one root.
    root_to_lab : ndarray, shape (F, 4, 4) or (4, 4)
        Pose of the root bone's frame in the lab for every frame.
    joint_rotations : dict of str -> ndarray
        For each non-root bone, its rotation about its proximal joint centre
        relative to the reference pose, in the **parent bone's frame**: (F, 3)
        rotation vectors (radians) or (F, 3, 3) matrices. A bone left out keeps
        its reference orientation relative to its parent and needs no joint
        centre; a rotated bone must share exactly one joint centre name with
        its parent (:func:`proximal_joint`), or name one of ``pivots``.
    pivots : sequence of str
        See :func:`proximal_joint` (e.g. :data:`PIVOT_JOINTS`).

    Returns
    -------
    ndarray, shape (F, B, 4, 4)
        ``bone_to_lab`` for each bone of ``skeleton.names``. With all rotations
        zero and ``root_to_lab`` equal to the root's ``bone_to_world``, this is
        the reference pose.
    """
    root_to_lab = np.asarray(root_to_lab, dtype=float)
    if root_to_lab.shape == (4, 4):
        root_to_lab = root_to_lab[None]
    if root_to_lab.ndim != 3 or root_to_lab.shape[1:] != (4, 4):
        raise ValueError(f"root_to_lab must be (F, 4, 4) or (4, 4), got {root_to_lab.shape}")
    joint_rotations = joint_rotations or {}
    unknown = set(joint_rotations) - set(skeleton.bones)
    if unknown:
        raise ValueError(f"rotations given for bones not in the skeleton: {sorted(unknown)}")
    F = root_to_lab.shape[0]
    names = skeleton.names
    index = {n: i for i, n in enumerate(names)}
    out = np.zeros((F, len(names), 4, 4))
    roots = [n for n in names if skeleton.bones[n].parent is None]
    if len(roots) != 1:
        raise ValueError(f"the skeleton must have exactly one root bone, it has {roots}")
    for i, name in enumerate(names):
        bone = skeleton.bones[name]
        if bone.parent is None:
            out[:, i] = root_to_lab
            continue
        if index[bone.parent] > i:
            raise ValueError(f"bone {name!r} comes before its parent {bone.parent!r}")
        parent_to_world = skeleton.bones[bone.parent].bone_to_world
        rest = np.linalg.solve(parent_to_world, bone.bone_to_world)  # child -> parent at rest
        J = np.tile(np.eye(4), (F, 1, 1))
        if name in joint_rotations:
            # Only a rotated bone needs its joint centre; one that just follows its
            # parent (a sternum on T1) may have none.
            _, c_parent, _ = proximal_joint(skeleton, name, pivots)
            R = _as_matrices(joint_rotations[name], F, name)
            J[:, :3, :3] = R
            J[:, :3, 3] = c_parent - R @ c_parent  # rotate about the joint centre
        out[:, i] = out[:, index[bone.parent]] @ J @ rest
    return out
