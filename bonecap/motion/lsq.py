"""Joint-coupled least-squares bone poses, solved for all frames at once.

The skeleton is cut into rigid **segments** (:func:`plan_segments`): a bone
with enough markers gets its own pose, a bone without them rides on a
neighbour at its reference (MRI) relative pose. Each segment's pose minimises

.. math::

    \\sum_{m} w_m \\lVert T_s\\,p_m - q_m \\rVert^2
    + k \\sum_{j} \\lVert T_s\\,c^s_j - T_{s(j)}\\,c^{s(j)}_j \\rVert^2 ,

the marker term of Söderkvist & Wedin (1993) plus, for each joint ``j`` the
segment shares with a neighbour (its proximal joint with its parent, the
proximal joints of its children), a soft ball joint: the two bones' copies of
the joint centre are pulled together with a stiffness ``k`` counted in
*marker equivalents* (``joint_weight``; a joint weighs as much as ``k``
markers of weight 1). A hinge (:data:`~bonecap.skeleton.kinematics.HINGE_JOINTS`,
the elbow, where the bones give its axis and the template does not declare it
otherwise -- an OpenSim model's with one coordinate, the embedded skeleton's
always -- and only for a bone with fewer than two markers of its own
and its children) adds two more such pairs, the
points ``HINGE_LEVER_MM`` either side of the centre on the axis: the child
then keeps the axis and only flexes about it, and one marker off the axis
determines it (the ulna's). The sum over all segments is the global objective of Lu
& O'Connor (1999) with the joint constraints made soft. It is minimised by
block-coordinate descent: a segment refitted with its neighbours held is a
weighted rigid fit of its markers plus one pseudo-marker per joint placed
where the neighbour has the joint -- a closed-form problem solved for every
frame at once. The first sweep visits the segments top-down, one at a time,
so that each starts from a solved parent; the later sweeps go in red-black
order: the segments at even depths in the tree share no joint with each
other, nor do those at odd depths, so each colour is refitted in one batched
fit of all its segments and frames (the colours alternate). The sweeps never
increase the objective. Batching halved the solve time of the Rajagopal
model's 14 segments (2 130 -> 4 460 frames per CPU second on the phantom's
trials, same errors against the truth to 0.02 degree). Frames are
independent until the gap rule, so a long trial is solved in blocks of
``_BLOCK_FRAMES`` frames (the same result; the batched arrays stay in the
cache; long trials solve about as fast as one segment at a time did,
short ones 1.5-1.7x faster). Along weakly
determined directions (the axial twist of a shank with two markers) the
descent is slow: on the phantom's trials 6 sweeps (the default) gave the
same median / p95 bone errors as 30 within ~0.03 / 0.2 degree, while single
frames of such a bone still moved by up to ~3 degrees between 6 and 30
sweeps (``n_sweeps``). A thigh whose static binding is off is slower still:
on a whole-body phantom's walk (seed 1, standard protocol) its left femur
was 11.2 degrees off after 6 sweeps, 9.4 after 12, 6.8 after 30 and 5.2
after 100 (the median over bones 2.03 -> 1.93, the static trial settled in
6); over-relaxing the updates (1.5, 1.8) slowed it further.
``build-subject --functional`` reads the thigh's turn on these same sweeps.
Where the minimum itself is wanted (the static trial that binds the markers),
``newton=True`` finishes with Gauss-Newton steps on all segments at once
(:func:`_newton`, Levenberg-Marquardt damped): on a whole-body phantom's
static the sweeps took ~1 400 fits a round to settle to 1e-3 mm and stopped
0.12 degree short of the minimum (the femora); sweeps to 0.5 mm and then a
few steps reach it to 0.0003 degree in a third of the time.

The closed-form weighted fit is Horn's (1987) unit-quaternion solution with
the largest eigenvalue found by Newton's method on the characteristic
polynomial (the QCP method of Theobald 2005), compiled with numba
(:mod:`bonecap.motion._qcp`): one loop over a batch's fits and frames, no
per-frame LAPACK call and no numpy temporaries; the joint pseudo-markers are
placed by a compiled loop too. Python loops run over segments, colours and
sweeps only. Written with numpy arrays instead (per-frame arrays, ~150 array
operations a fit) the same fits took 2.5-4x longer on the Rajagopal
phantom's trials (3 700 -> 15 000 frames per CPU second; 9 800 -> 25 300 on
a 10 000-frame walk), most of it numpy's per-call overhead.

Shoulder girdles: the clavicle and scapula are one segment (one acromion
marker), turning on the thorax at the sternoclavicular joint. With one marker
its turn about the line from that joint to the marker is held by a weak
prior whose target swings with that line, so that the prior holds that turn
only and leaves the clavicle's elevation and retraction to the marker. The
scapula turns upward on the clavicle with the arm (scapulohumeral rhythm,
:func:`rhythm_turns`; Inman et al. 1944): each sweep takes the turn from the
poses so far, takes the scapula's markers back to where the girdle's rigid fit
carries them, and hangs the arm from the turned shoulder centre. On a phantom
whose girdles follow a rhythm (clavicle 0.12 E, scapula 0.2 E on it) the
scapulae of a tiny phantom's static went from 6.0 / 6.4 to 1.5 / 1.9 deg
off, of its arm raise from 7.2 / 7.6 to 2.9 / 3.2 (median; p95 20 -> 5-6).

Gaps: a segment that has fewer than three usable points (markers plus joint
pseudo-markers, not collinear) in a frame is filled from its neighbours:
its pose **relative to its parent segment** is interpolated (rotation by
slerp, translation linearly) across gaps of at most ``max_gap_frames``
frames; longer gaps leave it invalid (NaN) for those frames.

Frames: ``marker_local`` in each marker's bone frame (ISB), ``measured`` and
the results in the lab frame of the trial (Z up for Vicon C3D), mm.

References
----------
.. [1] Söderkvist I, Wedin P-Å (1993). Determining the movements of the
   skeleton using well-configured markers. J Biomech 26(12):1473-1477.
.. [2] Lu T-W, O'Connor JJ (1999). Bone position estimation from skin marker
   co-ordinates using global optimisation with joint constraints.
   J Biomech 32(2):129-134.
.. [3] Horn BKP (1987). Closed-form solution of absolute orientation using
   unit quaternions. J Opt Soc Am A 4(4):629-642.
.. [4] Theobald DL (2005). Rapid calculation of RMSDs using a
   quaternion-based characteristic polynomial. Acta Cryst A61:478-480.
.. [5] Kojima et al., section 8.2 (the forearm model used for radius and
   ulna, :mod:`bonecap.motion.forearm`).
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from bonecap.model import Motion, Skeleton
from bonecap.motion._qcp import place_points, qcp_fits
from bonecap.skeleton.kinematics import AXIS_HOLD_JOINTS, GIRDLE_JOINTS, HINGE_JOINTS, PIVOT_JOINTS, parent_joint_key

__all__ = ["Segment", "SegmentPlan", "plan_segments", "solve_lsq", "lowpass_markers", "DEFAULT_JOINT_WEIGHT",
           "Rhythm", "plan_rhythms", "rhythm_turns", "RHYTHM_SCAPULOTHORACIC"]

#: Default stiffness of a joint, in marker equivalents: ten markers' worth keeps the two
#: copies of a joint centre within a fraction of a millimetre of each other while still
#: letting a bone with many markers disagree with a poorly marked neighbour.
DEFAULT_JOINT_WEIGHT = 10.0

# the radius turns on the ulna about the radial head (see PIVOT_JOINTS)
_PREFERRED_JOINTS = PIVOT_JOINTS
_MIN_SPREAD = 1e-3  # as bonecap.motion.rigid: sqrt(s2/s1) below this is collinear
#: Frames solved together (see solve_lsq): the batched fits' arrays stay small.
_BLOCK_FRAMES = 4096
#: With ``solve_lsq(newton=True)``: the sweeps stop once no segment moves by more than this (mm), and
#: Gauss-Newton steps take it from there.
NEWTON_FROM_MM = 0.5
#: ... and only for at most this many frames (more: the sweeps go on to ``tol_mm``).
_NEWTON_MAX_FRAMES = 64
#: Distance (mm) of a hinge's two axis points from its centre: about the elbow's width, so that
#: the axis weighs like the markers 100-250 mm down the forearm.
HINGE_LEVER_MM = 40.0
#: A shoulder girdle's hold on its reference pose relative to the thorax, as a fraction of the
#: joint stiffness (:meth:`Segment.link_weights`): one marker (the acromion) and the
#: sternoclavicular joint leave the girdle's turn about the line through them free, which this
#: weak pull holds; it is small beside the acromion marker's weight, so the marker moves the
#: girdle (its elevation and protraction) nearly as far as it moves. With the one marker the
#: prior's target swings with the line to it (:func:`solve_lsq`), so that it holds that turn only.
GIRDLE_PRIOR = 0.01
#: The hold of a joint of :data:`~bonecap.skeleton.kinematics.AXIS_HOLD_JOINTS` (the ankle) on its
#: child's turns other than about the joint's axis, as a fraction of the joint stiffness for each
#: of two points :data:`HINGE_LEVER_MM` either side of the centre on the axis (see
#: :meth:`Segment.links`): the flexion about the axis moves neither, so it is the markers' alone.
AXIS_HOLD = 0.1


# ----------------------------------------------------------------------------- segments


@dataclass(frozen=True)
class Segment:
    """A set of bones moving as one rigid body.

    Attributes
    ----------
    root : str
        The bone whose frame is the segment's frame.
    members : tuple of str
        Every bone of the segment (``root`` first).
    parent : int
        Index of the parent segment in :attr:`SegmentPlan.segments`, ``-1`` for none.
    joint : str or None
        Name of the joint centre tying ``root`` to its parent bone (``None``: no coupling).
    joint_in_self, joint_in_parent : ndarray (3,) or None
        That joint centre in this segment's frame and in the parent segment's frame (mm).
    rest_to_root : dict of str -> ndarray (4, 4)
        Each member's frame -> the root's frame at the reference pose.
    axis_in_self, axis_in_parent : ndarray (3,) or None
        Where ``joint`` is a hinge: its unit axis in this segment's frame and in the
        parent segment's frame (the same line at the reference pose).
    prior_in_self, prior_in_parent : ndarray (3,) or None
        A shoulder girdle's (:data:`~bonecap.skeleton.kinematics.GIRDLE_JOINTS`) weak hold
        on its reference pose relative to the parent: one point of the girdle far from its
        joint, in this segment's frame and where it lies in the parent's at the reference
        pose, pulled together with :data:`GIRDLE_PRIOR` of the joint's stiffness.
    hold_in_self, hold_in_parent : ndarray (2, 3) or None
        Where ``joint`` is one of :data:`~bonecap.skeleton.kinematics.AXIS_HOLD_JOINTS` (and not
        a hinge): two points on its axis, :data:`HINGE_LEVER_MM` either side of the centre, in
        this segment's frame and in the parent's (the same line at the reference pose), pulled
        together with :data:`AXIS_HOLD` of the joint's stiffness each.
    """

    root: str
    members: tuple
    parent: int
    joint: str | None
    joint_in_self: np.ndarray | None
    joint_in_parent: np.ndarray | None
    rest_to_root: dict
    axis_in_self: np.ndarray | None = None
    axis_in_parent: np.ndarray | None = None
    prior_in_self: np.ndarray | None = None
    prior_in_parent: np.ndarray | None = None
    hold_in_self: np.ndarray | None = None
    hold_in_parent: np.ndarray | None = None

    def links(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """The points tying this segment to its parent, as (in self, in parent) pairs: the joint
        centre, for a hinge the two points :data:`HINGE_LEVER_MM` either side of it on the axis,
        a girdle's prior point and an axis hold's two points (these weighted apart,
        :meth:`link_weights`)."""
        if self.joint is None:
            return []
        out = [(self.joint_in_self, self.joint_in_parent)]
        if self.axis_in_self is not None:
            for sign in (1.0, -1.0):
                out.append((self.joint_in_self + sign * HINGE_LEVER_MM * self.axis_in_self,
                            self.joint_in_parent + sign * HINGE_LEVER_MM * self.axis_in_parent))
        if self.prior_in_self is not None:
            out.append((self.prior_in_self, self.prior_in_parent))
        if self.hold_in_self is not None:
            out.extend(zip(self.hold_in_self, self.hold_in_parent))
        return out

    def prior_slot(self) -> int | None:
        """The index of the prior point in :meth:`links` (None without one)."""
        if self.joint is None or self.prior_in_self is None:
            return None
        return 1 + (2 if self.axis_in_self is not None else 0)

    def link_weights(self, joint_weight: float) -> list[float]:
        """The weight of each of :meth:`links` (marker equivalents): ``joint_weight`` for the joint
        and hinge points, :data:`GIRDLE_PRIOR` of it for a girdle's prior point, :data:`AXIS_HOLD`
        for each of an axis hold's points."""
        if self.joint is None:
            return []
        w = [float(joint_weight)] * (3 if self.axis_in_self is not None else 1)
        if self.prior_in_self is not None:
            w.append(float(joint_weight) * GIRDLE_PRIOR)
        if self.hold_in_self is not None:
            w += [float(joint_weight) * AXIS_HOLD] * len(self.hold_in_self)
        return w


@dataclass(frozen=True)
class SegmentPlan:
    """The segments of a skeleton for a marker binding, parent before child."""

    segments: list
    segment_of: dict  # bone -> segment index

    def roots(self) -> list[str]:
        return [s.root for s in self.segments]


def _shared_joint(skeleton: Skeleton, bone: str, joints: Mapping[str, str]) -> str | None:
    b = skeleton.bones[bone]
    if b.parent is None:
        return None
    parent = skeleton.bones[b.parent]
    if bone in joints:
        name = joints[bone]
        if name not in b.joint_centres or name not in parent.joint_centres:
            raise ValueError(f"joints[{bone!r}] = {name!r} is not a joint centre of both {bone!r} and its "
                             f"parent {b.parent!r}")
        return name
    shared = [n for n in b.joint_centres if n in parent.joint_centres]
    if not shared:
        # a girdle's joint, which the parent lists once per side (the sternum's "sternoclavicular_r")
        shared = [n for n in b.joint_centres
                  if n in GIRDLE_JOINTS and parent_joint_key(skeleton, bone, n) is not None]
    if len(shared) <= 1:
        return shared[0] if shared else None
    for name in _PREFERRED_JOINTS:
        if name in shared:
            return name
    return shared[0]


def _hinge_axis(skeleton: Skeleton, bone: str, joint: str | None) -> np.ndarray | None:
    """The unit axis (in ``bone``'s frame) of the hinge ``joint`` tying ``bone`` to its parent, or None.

    A hinge is a joint named in :data:`HINGE_JOINTS`: where the template declares its joints
    (``skeleton.metadata["joints"]``, as read from an OpenSim model), one it declares with one
    coordinate; a template that declares none (the embedded skeleton) has every such joint a hinge.

    The parent's axis is preferred, carried into the bone's frame at the reference pose, so that
    both copies are one line there; a bone's own axis serves when the parent gives none."""
    if _base(joint) not in HINGE_JOINTS:
        return None
    # A template that declares its joints (an OpenSim model) has a hinge only where it models the
    # joint with one coordinate. The embedded skeleton declares none: its elbow is the hinge anatomy
    # makes it. (With the vertebrae scaled by the chest's size its static-only path put the shoulders
    # 53-81 mm high, and a hinged one-marker ulna then flipped the left arm by 51-174 deg; with the
    # spine's own scaling the hinge holds both arms, phantoms of seeds 1-3.)
    declared = skeleton.metadata.get("joints") or {}
    if declared and len((declared.get(joint) or {}).get("coordinates") or ()) != 1:
        return None
    return _joint_axis(skeleton, bone, joint)


def _joint_axis(skeleton: Skeleton, bone: str, joint: str) -> np.ndarray | None:
    """The unit axis (in ``bone``'s frame) of the joint ``joint`` tying ``bone`` to its parent, or None:
    the parent's ``joint_axes`` carried into the bone's frame at the reference pose, else the bone's own."""
    b = skeleton.bones[bone]
    parent = skeleton.bones[b.parent]
    if joint in parent.joint_axes:
        R = b.bone_to_world[:3, :3].T @ parent.bone_to_world[:3, :3]
        a = R @ np.asarray(parent.joint_axes[joint], float)
    elif joint in b.joint_axes:
        a = np.asarray(b.joint_axes[joint], float)
    else:
        return None
    n = np.linalg.norm(a)
    return a / n if n > 0 else None


def _base(joint: str | None) -> str | None:
    """A joint's name without its side suffix."""
    if joint is None:
        return None
    return joint[:-2] if joint.endswith(("_r", "_l")) else joint


def _girdle_prior_point(skeleton: Skeleton, root: str, members: Sequence[str],
                        joint_in_root: np.ndarray) -> np.ndarray | None:
    """The point a girdle's prior holds (root's frame, mm): of its bones' landmarks and joint centres,
    the one farthest from its proximal joint (the scapula's inferior angle on the embedded
    skeleton), the longest lever on the girdle's turn about the line from the joint to its marker."""
    T_r = skeleton.bones[root].bone_to_world
    best, far = None, 0.0
    for m in members:
        bone = skeleton.bones[m]
        T = np.linalg.solve(T_r, bone.bone_to_world)
        for p in list(bone.landmarks.values()) + list(bone.joint_centres.values()):
            q = T[:3, :3] @ np.asarray(p, float) + T[:3, 3]
            d = float(np.linalg.norm(q - joint_in_root))
            if d > far:
                best, far = q, d
    return best



# ----------------------------------------------------------------------------- scapulohumeral rhythm

#: Scapulohumeral rhythm: the scapula's upward rotation on the thorax per degree of the humerus's
#: elevation from the thorax's downward axis (Inman et al. 1944: two parts glenohumeral to one
#: scapulothoracic, so a third), relative to the reference pose.
RHYTHM_SCAPULOTHORACIC = 1.0 / 3.0
#: The scapula's upward rotation on the clavicle is held within these limits (deg).
RHYTHM_LIMITS_DEG = (-20.0, 60.0)


@dataclass(frozen=True)
class Rhythm:
    """A shoulder girdle whose scapula turns on its clavicle with the arm (:func:`rhythm_turns`).

    The solver carries the girdle (clavicle and scapula) as one segment: one acromion marker
    cannot see the scapula turn on the clavicle, yet it turns upward by a third of the arm's
    elevation on the thorax (Inman's 2:1), and carries the shoulder centre and the acromion
    marker with it. The part of the scapula's upward rotation that the clavicle's elevation
    at the sternoclavicular joint does not already give is put at the acromioclavicular joint.

    Attributes
    ----------
    segment, child, parent : int
        The girdle's segment (its root the clavicle), the arm's segment hanging from the
        scapula, and the thorax's segment, in :attr:`SegmentPlan.segments`.
    scapula : str
        The girdle's member that turns (on the root, at ``ac``).
    ac : ndarray (3,)
        The acromioclavicular joint centre, the clavicle's copy, in the girdle's frame (mm).
    axis : ndarray (3,)
        Unit axis of upward rotation in the girdle's frame: the scapula's ISB ``X`` (normal to the
        scapular plane), signed so that a positive turn lifts the shoulder centre.
    clavicle : ndarray (3,)
        Unit direction sternoclavicular -> acromioclavicular joint in the girdle's frame.
    up : ndarray (3,)
        The thorax's superior axis (ISB ``Y`` of the clavicle's parent bone) in the thorax
        segment's frame.
    arm : ndarray (3,)
        The arm's long axis (elbow -> shoulder centre) in the arm segment's frame.
    elevation_ref, clavicle_ref : float
        The arm's elevation and the clavicle's elevation above the thorax's transverse plane at
        the reference pose (deg).
    """

    segment: int
    child: int
    parent: int
    scapula: str
    ac: np.ndarray
    axis: np.ndarray
    clavicle: np.ndarray
    up: np.ndarray
    arm: np.ndarray
    elevation_ref: float
    clavicle_ref: float


def _elevations(up: np.ndarray, arm: np.ndarray, clavicle: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The arm's elevation from the thorax's downward axis and the clavicle's above its transverse
    plane (deg), from unit vectors in one frame: the thorax's superior axis, the arm's long axis
    (elbow -> shoulder) and the clavicle's (sternoclavicular -> acromioclavicular)."""
    return (np.degrees(np.arccos(np.clip((arm * up).sum(-1), -1.0, 1.0))),
            np.degrees(np.arcsin(np.clip((clavicle * up).sum(-1), -1.0, 1.0))))


def plan_rhythms(skeleton: Skeleton, plan: SegmentPlan) -> list[Rhythm]:
    """The girdles of ``plan`` whose scapula a rhythm turns (:class:`Rhythm`).

    A girdle segment (its root meets its parent at a :data:`~bonecap.skeleton.kinematics.GIRDLE_JOINTS`
    joint) qualifies when a member meets the root at a named joint (the scapula at the
    acromioclavicular joint) and the root of a child segment (the humerus) hangs from that member
    with a shoulder and an elbow centre. None for a skeleton without clavicles (an OpenSim model's
    arm hangs from the thorax).
    """
    from bonecap.skeleton.kinematics import joint_pair
    from bonecap.skeleton.shapes import unit

    segs, out = plan.segments, []
    for g, seg in enumerate(segs):
        if seg.parent < 0 or _base(seg.joint) not in GIRDLE_JOINTS or seg.joint_in_self is None:
            continue
        T_root = skeleton.bones[seg.root].bone_to_world
        for m in seg.members[1:]:
            if skeleton.bones[m].parent != seg.root:
                continue
            pair = joint_pair(skeleton, m)
            kids = [c for c, s in enumerate(segs) if s.parent == g and skeleton.bones[s.root].parent == m]
            if pair is None or len(kids) != 1:
                continue
            arm_bone = skeleton.bones[segs[kids[0]].root]
            jc = {k[:-2] if k.endswith(("_r", "_l")) else k: v for k, v in arm_bone.joint_centres.items()}
            if "shoulder" not in jc or "elbow" not in jc:
                continue
            arm = np.asarray(jc["shoulder"], float) - np.asarray(jc["elbow"], float)   # arm's frame
            ac = np.asarray(pair[0], float)                       # the clavicle's copy, root frame
            cl = ac - seg.joint_in_self
            if np.linalg.norm(arm) < 1e-9 or np.linalg.norm(cl) < 1e-9:
                continue
            arm, cl = unit(arm), unit(cl)
            T_par = skeleton.bones[segs[seg.parent].root].bone_to_world
            T_arm = arm_bone.bone_to_world
            up_w = skeleton.bones[skeleton.bones[seg.root].parent].bone_to_world[:3, 1]
            x_w = skeleton.bones[m].bone_to_world[:3, 0]
            gh_w = T_arm[:3, :3] @ np.asarray(jc["shoulder"], float) + T_arm[:3, 3]
            ac_w = T_root[:3, :3] @ ac + T_root[:3, 3]
            # positive: the shoulder centre rises (glenoid up, inferior angle lateral)
            sign = 1.0 if float(np.cross(x_w, gh_w - ac_w) @ up_w) >= 0 else -1.0
            elevation_ref, clavicle_ref = _elevations(up_w, T_arm[:3, :3] @ arm, T_root[:3, :3] @ cl)
            out.append(Rhythm(
                segment=g, child=kids[0], parent=seg.parent, scapula=m, ac=ac,
                axis=sign * (T_root[:3, :3].T @ x_w), clavicle=cl, up=T_par[:3, :3].T @ up_w, arm=arm,
                elevation_ref=float(elevation_ref), clavicle_ref=float(clavicle_ref)))
    return out


def rhythm_turns(rhythm: Rhythm, thorax: np.ndarray, girdle: np.ndarray, arm: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The scapula's turn on the clavicle for the girdle's neighbours' poses.

    Parameters
    ----------
    rhythm : Rhythm
    thorax, girdle, arm : ndarray (F, 4, 4)
        The thorax's, the girdle's and the arm's segment frames -> lab (any one frame for all
        three), NaN where unsolved.

    Returns
    -------
    turn : ndarray (F, 4, 4)
        In the girdle's frame: the scapula's pose in it is ``turn @ rest`` (identity where a
        pose is missing).
    alpha : ndarray (F,)
        The upward rotation (deg): :data:`RHYTHM_SCAPULOTHORACIC` of the arm's elevation from
        the thorax's downward axis, less the clavicle's own elevation above the thorax's
        transverse plane (it lifts the scapula with it), both relative to the reference pose,
        held within :data:`RHYTHM_LIMITS_DEG`.

    References
    ----------
    Inman VT, Saunders JBdeCM, Abbott LC (1944). Observations on the function of the shoulder
    joint. J Bone Joint Surg 26(1):1-30.
    """
    elevation, clavicle = _elevations(thorax[:, :3, :3] @ rhythm.up, arm[:, :3, :3] @ rhythm.arm,
                                      girdle[:, :3, :3] @ rhythm.clavicle)
    alpha = (RHYTHM_SCAPULOTHORACIC * (elevation - rhythm.elevation_ref)
             - (clavicle - rhythm.clavicle_ref))
    alpha = np.nan_to_num(np.clip(alpha, *RHYTHM_LIMITS_DEG), nan=0.0)
    # Rodrigues about the one axis: R = I + sin(a) K + (1 - cos(a)) K^2
    K = _skew(rhythm.axis)
    a = np.radians(alpha)[:, None, None]
    R = np.eye(3) + np.sin(a) * K + (1.0 - np.cos(a)) * (K @ K)
    turn = np.zeros((len(alpha), 4, 4))
    turn[:, :3, :3] = R
    turn[:, :3, 3] = rhythm.ac - R @ rhythm.ac
    turn[:, 3, 3] = 1.0
    return turn, alpha


def _is_vertebra(name: str) -> bool:
    """A vertebra's name: the embedded skeleton's ``c1``-``c7``, ``t1``-``t12``, ``l1``-``l5``, or an OpenSim
    lumbar model's ``lumbar1``-``lumbar5`` / ``thoracic1``-``thoracic12``."""
    return re.fullmatch(r"[ctl]\d{1,2}|(?:cervical|thoracic|lumbar)\d{1,2}", name) is not None


def plan_segments(skeleton: Skeleton, marker_bones: Sequence[str], *,
                  segments: Mapping[str, str] | None = None, joints: Mapping[str, str] | None = None,
                  own_pose: Sequence[str] = (), hold_axes: bool = True) -> SegmentPlan:
    """Cut a skeleton into rigid segments that its markers can drive.

    Default rule, bottom-up over the tree: a bone gets a pose of its own (is a
    segment root) when its markers -- its own plus those of descendants that
    ride on it -- determine it: at least 2 with a joint centre shared with its
    parent (the joint is the third point), 1 with a hinge (:meth:`Segment.links`;
    a hinge of :data:`~bonecap.skeleton.kinematics.HINGE_JOINTS` acts only where
    one of its two bones has fewer than 2 markers of its own), at least 3 without. A bone without
    markers whose children are segment roots takes them over (a talus carries
    calcaneus and foot, carpals carry the rays, marker-less vertebrae carry
    the spine above them), because a joint between marker-less bones cannot
    be observed; it then is a root if the pooled markers determine it. So
    does a vertebra whose markers alone cannot hold it, when its child root
    is the thorax (a vertebra the rib cage rides on): Plug-in Gait's T10 is a
    thorax marker (the thorax segment is C7, T10, CLAV, STRN), so T10's
    vertebra joins the thorax above it, and the marker-less lumbar vertebrae
    below carry the trunk down to L5/S1, where OpenSim's full-body models turn
    it on the pelvis (one lumbar joint). Left on the pelvis, the lumbar spine
    and T10 turned with it: a phantom's trunk turning on the pelvis in a walk
    left them 4-8 deg off, and T10 tilted a real subject's static pelvis 13
    deg from Plug-in Gait's. C7's vertebra does not take the neck and head
    over (they keep their own segment on the thorax). A shoulder girdle
    (the bone whose proximal joint is one of
    :data:`~bonecap.skeleton.kinematics.GIRDLE_JOINTS`, the clavicle, with the
    scapula riding on it) that carries a marker (Plug-in Gait's acromion
    marker) has a pose of its own, turning on the thorax at the
    sternoclavicular joint; with a single marker its turn about the line from
    the joint to the marker is held by a weak prior (:data:`GIRDLE_PRIOR`,
    :attr:`Segment.prior_in_self`). A segment whose proximal joint is one of
    :data:`~bonecap.skeleton.kinematics.AXIS_HOLD_JOINTS` (the ankle) and has an
    axis is held weakly at its reference relative pose by two points on that
    axis (:data:`AXIS_HOLD`, :attr:`Segment.hold_in_self`): its flexion is the
    markers' alone, its roll about the line through heel, toe and ankle centre,
    which they see poorly, mostly the hold's. Any
    other bone rides on its parent at the reference relative pose (a patella,
    a fibula, ribs).

    Parameters
    ----------
    skeleton : Skeleton
        Bones in parent-before-child order, one root; frames ISB.
    marker_bones : sequence of str
        The bone of each marker.
    segments : mapping of str -> str, optional
        Explicit segmentation: bone -> the root bone of its segment (every
        root maps to itself). Replaces the rule above, e.g. with the joints a
        model really has.
    joints : mapping of str -> str, optional
        Bone -> the joint-centre name coupling it to its parent, where the
        shared name is ambiguous or a different one is wanted.
    own_pose : sequence of str
        Bones that must be segment roots whatever their markers (the radius and
        ulna when the forearm model drives them).
    hold_axes : bool, default True
        Give the segments at :data:`~bonecap.skeleton.kinematics.AXIS_HOLD_JOINTS`
        their axis hold (False: none).

    Returns
    -------
    SegmentPlan
    """
    names = skeleton.names
    joints = dict(joints or {})
    unknown = sorted(set(marker_bones) - set(names))
    if unknown:
        raise ValueError(f"markers are bound to bones not in the skeleton: {unknown}")
    kids: dict[str, list[str]] = {n: [] for n in names}
    for n in names:
        p = skeleton.bones[n].parent
        if p is not None:
            kids[p].append(n)
    joint = {n: _shared_joint(skeleton, n, joints) for n in names}
    own = {n: 0 for n in names}
    for b in marker_bones:
        own[b] += 1
    # Hinges only where a bone's markers cannot hold it on ball joints (fewer than two): then its
    # proximal hinge and the hinges of its children carry it. A bone its markers do hold keeps its
    # ball joints: an MRI subject's elbow axis a few degrees off the true one turned a two-marker
    # ulna 1-4 degrees further off than its markers alone (phantom seed 1).
    axis = {n: _hinge_axis(skeleton, n, joint[n]) for n in names}
    weak = {n for n in names if axis[n] is not None and own[n] < 2}
    hinged = {n for n in names if axis[n] is not None and (n in weak or skeleton.bones[n].parent in weak)}

    if segments is not None:
        seg_root = {n: str(segments.get(n, n)) for n in names}
        for n, r in seg_root.items():
            if r not in skeleton.bones or seg_root[r] != r:
                raise ValueError(f"segments[{n!r}] = {r!r} must be a bone that is its own segment root")
        for b in own_pose:
            if seg_root.get(b) != b:
                raise ValueError(f"bone {b!r} must be its own segment root (it is driven by a model)")
    else:
        pending = dict(own)
        is_root: dict[str, bool] = {}

        def _holds_ribs(root):
            """Whether the rib cage rides on ``root``'s segment (the thorax, not the neck and head)."""
            stack = list(kids[root])
            while stack:
                n = stack.pop()
                if is_root.get(n):
                    continue
                if n.startswith("rib"):
                    return True
                stack.extend(kids[n])
            return False

        def determined(n_markers, bone):
            if bone in hinged:
                return n_markers >= 1
            return n_markers >= 3 or (joint[bone] is not None and n_markers >= 2)

        for b in reversed(names):
            kid_roots = [c for c in kids[b] if is_root[c]]
            pend = own[b] + sum(pending[c] for c in kids[b] if not is_root[c])
            if skeleton.bones[b].parent is None or b in own_pose:
                is_root[b] = True
            elif determined(pend, b):
                is_root[b] = True
            elif pend >= 1 and _base(joint[b]) in GIRDLE_JOINTS:
                # a shoulder girdle with its acromion marker: its own pose, held about the line through
                # marker and joint by a weak prior (Segment.prior_in_self); on the thorax it stood still
                # while the acromion moved by centimetres with the arm (a real trial's shoulder markers
                # 35-44 mm from the fit, and the arms hanging from them 36-61 mm)
                is_root[b] = True
            elif kid_roots and (own[b] == 0 or (_is_vertebra(b) and all(_is_vertebra(c) and _holds_ribs(c)
                                                                          for c in kid_roots))):
                movable = [c for c in kid_roots if c not in own_pose]
                pend += sum(pending[c] for c in movable)
                for c in movable:
                    is_root[c] = False
                is_root[b] = determined(pend, b)
            else:
                is_root[b] = False
            pending[b] = pend
        # A bone that is not a root rides on its parent's segment (a root absorbed by a
        # marker-less parent is that parent's child, so the same rule covers it).
        seg_root = {}
        for n in names:  # parent before child
            seg_root[n] = n if is_root[n] else seg_root[skeleton.bones[n].parent]

    roots = [n for n in names if seg_root[n] == n]
    index = {r: i for i, r in enumerate(roots)}
    pooled = {r: 0 for r in roots}
    for b in marker_bones:
        pooled[seg_root[b]] += 1
    # every root's world -> bone inverse in one call (a solve per member was most of a short trial's plan)
    to_root = dict(zip(roots, np.linalg.inv(np.array([skeleton.bones[r].bone_to_world for r in roots]))
                       if roots else []))
    segs = []
    for r in roots:
        members = [r] + [n for n in names if seg_root[n] == r and n != r]
        T_r = skeleton.bones[r].bone_to_world
        rest = {m: to_root[r] @ skeleton.bones[m].bone_to_world for m in members}
        pb = skeleton.bones[r].parent
        parent = -1 if pb is None else index[seg_root[pb]]
        j = joint[r] if parent >= 0 else None
        j_self = j_par = a_self = a_par = None
        if j is not None:
            j_self = skeleton.bones[r].joint_centres[j]
            P = to_root[roots[parent]] @ skeleton.bones[pb].bone_to_world
            j_par = P[:3, :3] @ skeleton.bones[pb].joint_centres[parent_joint_key(skeleton, r, j)] + P[:3, 3]
            a_self = axis[r] if r in hinged else None
            if a_self is not None:
                # the same line in the parent segment's frame at the reference pose
                a_par = np.linalg.solve(skeleton.bones[roots[parent]].bone_to_world[:3, :3],
                                        skeleton.bones[r].bone_to_world[:3, :3] @ a_self)
        hold_self = hold_par = None
        if hold_axes and j is not None and a_self is None and _base(j) in AXIS_HOLD_JOINTS:
            ax = _joint_axis(skeleton, r, j)
            if ax is not None:
                ax_par = np.linalg.solve(skeleton.bones[roots[parent]].bone_to_world[:3, :3],
                                         skeleton.bones[r].bone_to_world[:3, :3] @ ax)
                lever = np.array([[HINGE_LEVER_MM], [-HINGE_LEVER_MM]])
                hold_self, hold_par = j_self + lever * ax, j_par + lever * ax_par
        pr_self = pr_par = None
        if j is not None and _base(j) in GIRDLE_JOINTS and pooled[r] < 2:
            pr_self = _girdle_prior_point(skeleton, r, members, j_self)
            if pr_self is not None:
                pr_world = T_r[:3, :3] @ pr_self + T_r[:3, 3]
                pr_par = np.linalg.solve(skeleton.bones[roots[parent]].bone_to_world, np.r_[pr_world, 1.0])[:3]
        segs.append(Segment(r, tuple(members), parent, j, j_self, j_par, rest, a_self, a_par, pr_self, pr_par,
                            hold_self, hold_par))
    return SegmentPlan(segs, {n: index[seg_root[n]] for n in names})


# ----------------------------------------------------------------------------- batched fit


def _fit_qcp(P: np.ndarray, Q: np.ndarray, w: np.ndarray, newton_steps: int = 50):
    """Weighted rigid fit ``local -> lab`` for a batch, by Horn's quaternion + QCP.

    Parameters
    ----------
    P : ndarray (K, 3) or (G, K, 3)
        Local points, the same in every frame; with a leading axis, ``G``
        independent fits at once (several segments, padded with points of
        weight 0 to a common ``K``).
    Q : ndarray (F, 3, K) or (G, F, 3, K)
        Lab points, **coordinates first** and finite: a missing point has
        weight 0 and any finite value (the caller zeroes them once per trial).
    w : ndarray (F, K) or (G, F, K)
        Weights >= 0.
    newton_steps : int, default 50
        Most Newton steps on the characteristic polynomial; they stop at rounding level, after 3-4
        on a rigid body's markers. Where the two largest eigenvalues nearly meet (targets no rotation
        fits well) Newton converges only linearly: 10 steps left 9 of 5 000 random-target frames up to
        4e-5 above the SVD fit's minimum, 50 none (``/tmp/s42/nsteps.py``, session 42).

    Returns
    -------
    R (F, 3, 3), t (F, 3), valid (F,)
        ``valid``: at least 3 points of positive weight, not collinear
        (``sqrt(s2 / s1) >= 1e-3`` of the local scatter, as :mod:`bonecap.motion.rigid`).
        With ``G`` fits: (G, F, 3, 3), (G, F, 3), (G, F).

    Notes
    -----
    One compiled loop over fits and frames (:func:`bonecap.motion._qcp.qcp_fits`): no
    per-frame LAPACK call, no numpy temporaries.
    """
    single = P.ndim == 2
    if single:
        P, Q, w = P[None], Q[None], w[None]
    G, F, _, K = Q.shape
    R = np.empty((G, F, 3, 3))
    t = np.empty((G, F, 3))
    valid = np.empty((G, F), bool)

    def contiguous(a):
        # the kernel's one signature takes writable, contiguous float64 arrays: the first sweep's views
        # into the colour buffers become small copies, the batched sweeps' buffers pass as they are
        a = np.ascontiguousarray(a, dtype=float)
        return a if a.flags.writeable else a.copy()

    qcp_fits(contiguous(P), contiguous(Q), contiguous(w), int(newton_steps), _MIN_SPREAD, R, t, valid)
    if single:
        return R[0], t[0], valid[0]
    return R, t, valid


def _skew(v: np.ndarray) -> np.ndarray:
    """``S(v)`` with ``S(v) @ y == cross(v, y)``, for (..., 3) vectors."""
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2], S[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    S[..., 1, 0], S[..., 2, 0], S[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return S


def _newton(T: np.ndarray, var: Sequence[int], segs: Sequence[Segment], seg_local, seg_markers, meas: np.ndarray,
            w_vis: np.ndarray, joint_weight: float, tol_mm: float, max_iter: int = 100) -> bool:
    """Levenberg-Marquardt on the poses of the segments ``var`` at once, in place on ``T`` (S, F, 4, 4).

    The objective is the sweeps' (module docstring): the markers' weighted squares plus each
    joint's pair of centres (and a hinge's lever points) pulled together with ``joint_weight``
    (a girdle's prior point with its share of it, :meth:`Segment.link_weights`).
    Each segment's pose is updated by a small turn ``w`` about its origin and a shift ``t``
    (``p -> p + w x (p - o) + t``), every segment's at once: the normal equations are 6 rows per
    segment, solved per frame (dense: for the few frames of a static trial). The sweeps converge
    linearly, slowly along the directions that couple several segments (a thigh's twist through
    hip and knee: hundreds of sweeps on a static trial); these steps converge quadratically.
    Stops when no segment moves by more than ``tol_mm`` (its origin, or a point 100 mm from it)
    in a step. Frames are independent; a frame whose step does not lower its objective raises
    its damping and tries again. Returns False when the damping ran away in some frame (the
    poses keep the steps taken, each of which lowered its frame's objective).
    """
    S_all, F = T.shape[0], T.shape[1]
    var = list(var)
    col = {s: i for i, s in enumerate(var)}
    n = 6 * len(var)
    ident = np.eye(3)
    links = [(s, segs[s].parent, a, b, wl) for s in range(S_all) if segs[s].parent >= 0
             and (s in col or segs[s].parent in col)
             for (a, b), wl in zip(segs[s].links(), segs[s].link_weights(joint_weight))]

    def evaluate(T, want_normal=True):
        cost = np.zeros(F)
        H = np.zeros((F, n, n)) if want_normal else None
        g = np.zeros((F, n)) if want_normal else None

        def add(s, r_o, r, w, sign=1.0):
            # a residual r (F, K, 3) moving with segment s's point at r_o from its origin: the gradient
            # rows [r_o x r ; r] and the Gauss-Newton block [[|r_o|^2 I - r_o r_o^T, S(r_o)], [-S(r_o), I]]
            i = 6 * col[s]
            g[:, i:i + 3] += sign * np.einsum("fk,fki->fi", w, np.cross(r_o, r))
            g[:, i + 3:i + 6] += sign * np.einsum("fk,fki->fi", w, r)
            W = w.sum(1)
            R1 = np.einsum("fk,fki->fi", w, r_o)
            R2 = (np.einsum("fk,fk->f", w, (r_o * r_o).sum(-1))[:, None, None] * ident
                  - np.einsum("fk,fki,fkj->fij", w, r_o, r_o))
            H[:, i:i + 3, i:i + 3] += R2
            H[:, i:i + 3, i + 3:i + 6] += _skew(R1)
            H[:, i + 3:i + 6, i:i + 3] -= _skew(R1)
            H[:, i + 3:i + 6, i + 3:i + 6] += W[:, None, None] * ident

        for s in var:
            ms = seg_markers[s]
            if not ms:
                continue
            P = _apply(T[s][:, None], seg_local[s][:len(ms)][None])                # (F, K, 3)
            r = P - meas[:, ms]
            w = w_vis[:, ms]
            cost += np.einsum("fk,fk->f", w, (r * r).sum(-1))
            if want_normal:
                add(s, P - T[s][:, None, :3, 3], r, w)
        for s, p, a, b, wl in links:
            pa, pb = _apply(T[s], a), _apply(T[p], b)
            good = np.isfinite(pa).all(1) & np.isfinite(pb).all(1)
            w = np.where(good, wl, 0.0)[:, None]
            r = np.where(good[:, None], pa - pb, 0.0)[:, None]
            cost += w[:, 0] * (r[:, 0] ** 2).sum(-1)
            if not want_normal:
                continue
            ra = np.where(good[:, None], pa - T[s][:, :3, 3], 0.0)[:, None]
            rb = np.where(good[:, None], pb - T[p][:, :3, 3], 0.0)[:, None]
            if s in col:
                add(s, ra, r, w)
            if p in col:
                add(p, rb, r, w, sign=-1.0)
            if s in col and p in col:
                i, j = 6 * col[s], 6 * col[p]
                Sa, Sb = _skew(ra[:, 0]), _skew(rb[:, 0])
                ww = w[:, 0, None, None]
                # d r / d(step of s) = [-S(ra), I], d r / d(step of p) = [S(rb), -I]
                blk = np.zeros((F, 6, 6))
                blk[:, :3, :3] = Sa @ Sb
                blk[:, :3, 3:] = -Sa
                blk[:, 3:, :3] = Sb
                blk[:, 3:, 3:] = -ident
                H[:, i:i + 6, j:j + 6] += ww * blk
                H[:, j:j + 6, i:i + 6] += ww * np.swapaxes(blk, 1, 2)
        return cost, H, g

    def stepped(T, x):
        out = T.copy()
        for s, i in col.items():
            w, t = x[:, 6 * i:6 * i + 3], x[:, 6 * i + 3:6 * i + 6]
            out[s][:, :3, :3] = Rotation.from_rotvec(w).as_matrix() @ T[s][:, :3, :3]
            out[s][:, :3, 3] = T[s][:, :3, 3] + t
        return out

    lam = np.full(F, 1e-6)
    cost, H, g = evaluate(T)
    for _ in range(int(max_iter)):
        diag = np.einsum("fii->fi", H)
        A = H + (lam[:, None] * np.maximum(diag, 1e-9 * diag.max(axis=1, keepdims=True) + 1e-12))[:, :, None] * np.eye(n)
        x = -np.linalg.solve(A, g[..., None])[..., 0]
        trial = stepped(T, x)
        new_cost, _, _ = evaluate(trial, want_normal=False)
        better = new_cost <= cost
        if better.any():
            T[:, better] = trial[:, better]
        xs = x.reshape(F, -1, 6)
        move = np.maximum(np.abs(xs[..., 3:]).max(axis=-1), 100.0 * np.abs(xs[..., :3]).max(axis=-1))
        # converged: a (nearly undamped) step below the tolerance, taken or not (at the minimum a
        # step may raise the objective in its last digits)
        if move.max(initial=0.0) <= tol_mm and (lam <= 1e-3).all():
            return True
        lam = np.where(better, np.maximum(lam / 10.0, 1e-12), lam * 10.0)
        if (lam > 1e12).any():
            return False
        cost, H, g = evaluate(T)
    return False


#: Gauss-Newton rounds with the scapulae's turns held (:func:`solve_lsq`), until no turn changes by
#: more than ``_RHYTHM_TOL_DEG`` between rounds.
_RHYTHM_ROUNDS = 5
_RHYTHM_TOL_DEG = 0.01


def _unturned(T: np.ndarray, turn: np.ndarray) -> np.ndarray:
    """``T @ turn^-1 @ T^-1`` (F, 4, 4): a lab point of the turned scapula to where the girdle's
    unturned copy has it; the identity where ``T`` is unsolved."""
    good = np.isfinite(T).all(axis=(1, 2))
    R_T = np.where(good[:, None, None], T[:, :3, :3], np.eye(3))
    t_T = np.where(good[:, None], T[:, :3, 3], 0.0)
    # with turn = (Q, q): T turn^-1 T^-1 = (R_T Q^T R_T^T, t_T + R_T Q^T (-q) - R_T Q^T R_T^T t_T)
    Qt = np.swapaxes(turn[:, :3, :3], 1, 2)
    RQt = R_T @ Qt
    M = RQt @ np.swapaxes(R_T, 1, 2)
    out = np.zeros_like(turn)
    out[:, :3, :3] = M
    out[:, :3, 3] = t_T - np.einsum("fij,fj->fi", RQt, turn[:, :3, 3]) - np.einsum("fij,fj->fi", M, t_T)
    out[:, 3, 3] = 1.0
    out[~good] = np.eye(4)
    return out


def _swing(T_par: np.ndarray, T_seg: np.ndarray, d: np.ndarray, R_rest: np.ndarray, centre: np.ndarray
           ) -> np.ndarray:
    """The shortest turn (F, 4, 4; parent frame, about ``centre``) taking the unit line ``d`` (segment
    frame) from where the reference pose (``R_rest``: segment -> parent) has it to where the poses have
    it relative to the parent; the identity where a pose is unsolved."""
    a = R_rest @ d
    b = np.einsum("fji,fjk,k->fi", T_par[:, :3, :3], T_seg[:, :3, :3], d)
    axis = np.cross(a, b)
    s = np.linalg.norm(axis, axis=-1)
    angle = np.arctan2(s, b @ a)
    rv = np.where(s[:, None] > 1e-12, axis / np.where(s > 1e-12, s, 1.0)[:, None] * angle[:, None], 0.0)
    rv = np.nan_to_num(rv, nan=0.0)
    R = Rotation.from_rotvec(rv).as_matrix()
    out = np.tile(np.eye(4), (len(rv), 1, 1))
    out[:, :3, :3] = R
    out[:, :3, 3] = centre - R @ centre
    return out


def _with_turns(segs, seg_local, rhythms, slots, turns, swings):
    """Segments and local points with each rhythm's scapula turned as in ``turns`` and each swung
    prior's target as in ``swings`` (one frame): the scapula's markers and the arm's joint points move
    in the girdle's frame, the prior's point in its parent's."""
    from dataclasses import replace

    segs, seg_local = list(segs), list(seg_local)
    for g, S in swings.items():
        R, t = S[0, :3, :3], S[0, :3, 3]
        segs[g] = replace(segs[g], prior_in_parent=R @ segs[g].prior_in_parent + t)
    for rh in rhythms:
        J = turns[rh.segment][0]
        R, t = J[:3, :3], J[:3, 3]
        local = seg_local[rh.segment].copy()
        local[slots[rh.segment]] = local[slots[rh.segment]] @ R.T + t
        seg_local[rh.segment] = local
        c = segs[rh.child]
        segs[rh.child] = replace(
            c, joint_in_parent=R @ c.joint_in_parent + t,
            axis_in_parent=None if c.axis_in_parent is None else R @ c.axis_in_parent,
            prior_in_parent=None if c.prior_in_parent is None else R @ c.prior_in_parent + t,
            hold_in_parent=None if c.hold_in_parent is None else c.hold_in_parent @ R.T + t)
    return segs, seg_local


def _size_batches(group: Sequence[int], sizes: Mapping[int, int], waste: float = 0.25) -> list[list[int]]:
    """Split one colour's segments into batches of similar point counts.

    Padding every segment to the colour's largest count wastes up to half the
    arithmetic (the default phantom's 10-point spine segment beside 3-point
    feet): segments sorted by count join a batch while the padded size stays
    within ``1 + waste`` of the real one. On short blocks the calls' overhead
    costs more than the padding (``waste=inf``: one batch per colour, 18 %
    faster on 220 frames, 4-10 % slower on 2 000-20 000; measured with the
    numpy fit: with the compiled one the two are equal on the Rajagopal
    phantom's 110-210-frame trials, 15 030-15 040 frames per CPU second).
    """
    out: list[list[int]] = []
    cur: list[int] = []
    for s in sorted(group, key=lambda x: -sizes[x]):
        cand = cur + [s]
        if cur and sizes[cur[0]] * len(cand) > (1 + waste) * sum(sizes[x] for x in cand):
            out.append(cur)
            cur = [s]
        else:
            cur = cand
    if cur:
        out.append(cur)
    return out


def _to_T(R, t, valid):
    T = np.zeros(R.shape[:-2] + (4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    T[~valid] = np.nan
    return T


def _apply(T, p):
    # written out: numpy's batched matmul of 3x3 by 3-vectors is twice as slow
    p = np.asarray(p, dtype=float)
    return (T[..., :3, 0] * p[..., 0, None] + T[..., :3, 1] * p[..., 1, None] + T[..., :3, 2] * p[..., 2, None]
            + T[..., :3, 3])


def _inv(T):
    R = np.swapaxes(T[..., :3, :3], -1, -2)
    out = np.zeros_like(T)
    out[..., :3, :3] = R
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", R, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def _fill_gaps(rel: np.ndarray, ok: np.ndarray, max_gap: int) -> tuple[np.ndarray, np.ndarray]:
    """Interpolate transforms ``rel`` (F, 4, 4) across runs of ``~ok`` no longer than ``max_gap``."""
    F = len(ok)
    if ok.all() or not ok.any() or max_gap <= 0:
        return rel, ok
    idx = np.arange(F)
    prev = np.maximum.accumulate(np.where(ok, idx, -1))
    nxt = np.minimum.accumulate(np.where(ok, idx, F)[::-1])[::-1]
    fill = ~ok & (prev >= 0) & (nxt < F) & (nxt - prev - 1 <= max_gap)
    if not fill.any():
        return rel, ok
    f = idx[fill]
    a, b = prev[fill], nxt[fill]
    alpha = (f - a) / (b - a)
    Ra, Rb = rel[a, :3, :3], rel[b, :3, :3]
    d = Rotation.from_matrix(np.swapaxes(Ra, 1, 2) @ Rb).as_rotvec()
    Ri = Ra @ Rotation.from_rotvec(d * alpha[:, None]).as_matrix()
    out = rel.copy()
    out[f] = np.eye(4)
    out[f, :3, :3] = Ri
    out[f, :3, 3] = (1 - alpha)[:, None] * rel[a, :3, 3] + alpha[:, None] * rel[b, :3, 3]
    ok = ok | fill
    return out, ok


# ----------------------------------------------------------------------------- solver


def _check_inputs(skeleton, marker_bones, marker_local, measured, weights):
    if not isinstance(skeleton, Skeleton):
        raise ValueError(f"skeleton must be a bonecap.model.Skeleton, got {type(skeleton).__name__}")
    marker_bones = [str(b) for b in marker_bones]
    local = np.asarray(marker_local, dtype=float)
    meas = np.asarray(measured, dtype=float)
    M = len(marker_bones)
    if local.shape != (M, 3):
        raise ValueError(f"marker_local must have shape ({M}, 3) -- each marker in its bone frame, mm -- "
                         f"got {local.shape}")
    if not np.isfinite(local).all():
        raise ValueError("marker_local must be finite (every marker needs a position on its bone)")
    if meas.ndim != 3 or meas.shape[1:] != (M, 3):
        raise ValueError(f"measured must have shape (frames, {M}, 3) in the lab frame, mm, got {meas.shape}")
    if weights is None:
        w = np.ones(M)
    else:
        w = np.asarray(weights, dtype=float)
        if w.shape not in ((M,), (meas.shape[0], M)):
            raise ValueError(f"weights must have shape ({M},) or ({meas.shape[0]}, {M}), got {w.shape}")
        if not np.isfinite(w).all() or (w < 0).any():
            raise ValueError("weights must be finite and non-negative (0 leaves a marker out)")
    return marker_bones, local, meas, np.broadcast_to(w, meas.shape[:2])


def solve_lsq(skeleton: Skeleton, marker_bones: Sequence[str], marker_local, measured, *, weights=None,
              joint_weight: float = DEFAULT_JOINT_WEIGHT, n_sweeps: int = 6, max_gap_frames: int = 10,
              forearm=None, marker_labels: Sequence[str] | None = None, rate_hz: float = 100.0,
              first_frame: int = 1, segments: Mapping[str, str] | None = None,
              joints: Mapping[str, str] | None = None, progress: bool = False,
              tol_mm: float | None = None, newton: bool = False, hold_axes: bool = True,
              rhythm: bool = True) -> Motion:
    """Bone poses from markers by joint-coupled weighted least squares, all frames at once.

    Parameters
    ----------
    skeleton : Skeleton
        The subject at its reference pose: ``bone_to_world`` (any world, e.g.
        LPS for an MRI subject), joint centres in each bone's frame (ISB).
        Bones that share a joint-centre name with their parent are coupled
        there (:func:`bonecap.skeleton.kinematics.proximal_joint`).
    marker_bones : sequence of str, length M
        The bone carrying each marker.
    marker_local : array_like, shape (M, 3)
        Each marker in its bone's frame (mm).
    measured : array_like, shape (F, M, 3)
        Marker trajectories in the lab frame of the trial (Z up), mm, NaN in gaps.
    weights : array_like, shape (M,) or (F, M), optional
        Non-negative marker weights (default 1).
    joint_weight : float, default 10
        Stiffness of every joint in marker equivalents (see the module
        documentation); 0 uncouples the segments (a per-segment rigid fit).
    n_sweeps : int, default 6
        Block-coordinate sweeps (the first top-down, then red-black); with
        ``tol_mm`` the most that are run.
    tol_mm : float, optional
        Stop the sweeps once a sweep moved no segment by more than this: the
        largest change of a segment's origin or of a point 100 mm from it (its
        rotation's), over all frames. For few frames, where a sweep costs
        little and a full convergence matters (the static trial that binds the
        markers, :func:`bonecap.build_subject.pose_to_static`).
    newton : bool, default False
        With ``tol_mm``: sweep only until no segment moves by more than
        :data:`NEWTON_FROM_MM`, then take Gauss-Newton (Levenberg-Marquardt)
        steps on all segments at once to ``tol_mm`` (:func:`_newton`): the same
        minimum, reached in a few steps where the sweeps take hundreds. Dense
        per frame (6 unknowns per segment): for the few frames of a static
        trial (at most 64; more are swept to ``tol_mm``). Not with a forearm
        model (its radius is placed, not fitted).
    max_gap_frames : int, default 10
        Longest run of frames over which a segment that cannot be solved is
        interpolated (relative to its parent); longer runs are NaN and invalid.
    forearm : ForearmModel or mapping of side -> ForearmModel, optional
        Place the radius by the pronation model of Kojima et al. §8.2
        (:mod:`bonecap.motion.forearm`) instead of its few markers: the ulna is
        solved first (its markers and the elbow joint), then the radius's
        ``theta = 0`` pose is carried with it and turned by the model's
        ``f(theta)``, the twist measured against the epicondyles carried with the
        ulna from the reference pose; the hand then settles on the radius in a
        few more sweeps. A single model applies to both sides. Needs
        ``marker_labels`` with the wrist (``RWRA``, ``RWRB``) and elbow
        (``RELB``, ``RMEP``) markers of a side (left: ``L...``); sides without
        them are solved without the model.
    marker_labels : sequence of str, optional
        Marker names (for the output and the forearm markers).
    rate_hz : float, default 100
        Frame rate, for ``Motion.times``.
    first_frame : int, default 1
    segments, joints : mapping, optional
        Override the segmentation and the coupling joints, see :func:`plan_segments`.
    progress : bool
        Show a progress bar over the sweeps.
    hold_axes : bool, default True
        Hold the turns of a foot its markers see poorly on the shank (see
        :func:`plan_segments`). A static trial binds the markers without it:
        its foot takes its roll from the shank by rule
        (:func:`bonecap.build_subject.neutral_twist`), and the hold's pull on
        the shank's and thigh's twist would come from the feet's placed markers.
    rhythm : bool, default True
        Turn each shoulder girdle's scapula upward on its clavicle with the arm's elevation
        (scapulohumeral rhythm, :func:`rhythm_turns`; girdles of :func:`plan_rhythms`): the
        scapula's markers and the shoulder centre go with it in every sweep. False: the scapula
        rides on the clavicle at its reference relative pose.

    Returns
    -------
    Motion
        ``transforms`` (F, B, 4, 4) bone -> lab (mm) for every bone of the
        skeleton, NaN where invalid; ``valid`` (F, B); ``residuals`` (F, M)
        mm; ``flags["forearm_clamped"]`` (F, B) where the forearm model's
        twist was outside its fitted range and held at its end (the pose
        stays valid).

    Raises
    ------
    ValueError
        On shapes that disagree, unknown bones, negative weights or joint weight.

    References
    ----------
    .. [1] Söderkvist I, Wedin P-Å (1993). J Biomech 26(12):1473-1477.
    .. [2] Lu T-W, O'Connor JJ (1999). J Biomech 32(2):129-134.
    .. [3] Kojima et al., section 8.2 (forearm).
    """
    marker_bones, local, meas, w_markers = _check_inputs(skeleton, marker_bones, marker_local, measured, weights)
    if not (np.isfinite(joint_weight) and joint_weight >= 0):
        raise ValueError(f"joint_weight must be a finite number >= 0 (marker equivalents), got {joint_weight!r}")
    if int(n_sweeps) < 1:
        raise ValueError(f"n_sweeps must be >= 1, got {n_sweeps!r}")
    if tol_mm is not None and not (np.isfinite(tol_mm) and tol_mm > 0):
        raise ValueError(f"tol_mm must be a finite number > 0 (mm), got {tol_mm!r}")
    if int(max_gap_frames) < 0:
        raise ValueError(f"max_gap_frames must be >= 0, got {max_gap_frames!r}")
    F, M, _ = meas.shape
    labels = [str(x) for x in marker_labels] if marker_labels is not None else [f"m{i}" for i in range(M)]
    if len(labels) != M:
        raise ValueError(f"marker_labels has {len(labels)} names for {M} markers")

    model_bones = []
    if forearm is not None:
        # The radius turns about the ulna: solve everything else first (the ulna from its
        # markers and the elbow), then place the radius by the model, then let the hand
        # settle on it with a few more sweeps.
        from bonecap.motion.forearm import forearm_poses_from_markers

        probe = forearm_poses_from_markers(skeleton, forearm, labels, marker_bones, local, meas[:1])
        model_bones = sorted(b for b in probe if b.startswith("radius"))
    # dense normal equations per frame (6 rows a segment): a static trial's few frames, not a trial's
    newton = bool(newton) and tol_mm is not None and not model_bones and F <= _NEWTON_MAX_FRAMES
    sweep_tol = max(tol_mm, NEWTON_FROM_MM) if newton else tol_mm
    plan = plan_segments(skeleton, marker_bones, segments=segments, joints=joints,
                         own_pose=model_bones + [b.replace("radius", "ulna") for b in model_bones],
                         hold_axes=hold_axes)
    rhythms = plan_rhythms(skeleton, plan) if rhythm else []
    if rhythms and newton and F > 1:
        # the Gauss-Newton steps hold the scapula's turn fixed per frame from one set of local
        # points: one frame (a static trial); more are swept to tol_mm
        newton, sweep_tol = False, tol_mm
    segs = plan.segments
    S = len(segs)
    children = [[c for c in range(S) if segs[c].parent == s] for s in range(S)]

    # Per segment: local points (markers then joint centres) in the segment frame.
    seg_markers = [[] for _ in range(S)]
    for m, b in enumerate(marker_bones):
        seg_markers[plan.segment_of[b]].append(m)
    seg_local = []
    for s, seg in enumerate(segs):
        ms = seg_markers[s]
        # each marker from its bone's frame into the segment's (one batched product per segment)
        rest = np.array([seg.rest_to_root[marker_bones[m]] for m in ms]).reshape(-1, 4, 4)
        pts = list(_apply(rest, local[ms]))
        pts += [p_self for p_self, _ in seg.links()]
        pts += [p_par for c in children[s] for _, p_par in segs[c].links()]
        seg_local.append(np.array(pts).reshape(-1, 3))
    # a rhythm's girdle: its scapula's markers (their slots in the segment), and the arm hanging from it
    hung = {rh.child: rh for rh in rhythms}
    # A girdle with one marker: its prior holds only its turn about the line from its joint to the
    # marker, which the marker cannot see; the line's own swing (the clavicle's elevation and
    # retraction) is the marker's. The prior point's target swings with the line (a fixed target had
    # resisted the elevation: the acromion's 60 mm rise at 150 deg weighed like a marker 19 mm off).
    swung = {}
    for g, seg in enumerate(segs):
        if seg.prior_in_self is not None and len(seg_markers[g]) == 1:
            d = seg_local[g][0] - seg.joint_in_self
            if np.linalg.norm(d) > 1e-6:
                R_rest = np.linalg.solve(skeleton.bones[segs[seg.parent].root].bone_to_world[:3, :3],
                                         skeleton.bones[seg.root].bone_to_world[:3, :3])
                swung[g] = (d / np.linalg.norm(d), R_rest)
    scapula_slots = {rh.segment: [i for i, m in enumerate(seg_markers[rh.segment])
                                  if marker_bones[m] == rh.scapula] for rh in rhythms}

    # Each segment's links as pseudo-marker tables, once per solve: the points in the parent's
    # frame (its own links, targets from the parent) and in its own (the links its parent's fit
    # takes as targets from it), their weights, and runs of consecutive links that share a
    # neighbour pose (a one-marker girdle's prior point is carried by the swung parent pose).
    def _link_table(s_, side):
        seg = segs[s_]
        links = seg.links()
        if not links:
            return np.zeros((0, 3)), np.zeros(0), []
        prior = seg.prior_slot() if s_ in swung else None
        runs, a = [], 0
        for i in range(1, len(links) + 1):
            if i == len(links) or (i == prior) != (i - 1 == prior):
                runs.append((a == prior, a, i))
                a = i
        return (np.array([pair[side] for pair in links], float),
                np.array(seg.link_weights(joint_weight), float), runs)

    own_links = [_link_table(s_, 1) for s_ in range(S)]
    child_links = [_link_table(s_, 0) for s_ in range(S)]

    T = np.full((S, F, 4, 4), np.nan)
    ok = np.zeros((S, F), bool)
    model_clamped = {b: np.zeros(F, bool) for b in model_bones}
    # markers coordinates-first and finite once for all sweeps: a gap is weight 0
    visible = np.isfinite(meas).all(axis=-1)
    w_vis = np.where(visible, w_markers, 0.0)
    meas_t = np.ascontiguousarray(np.where(visible[..., None], meas, 0.0).transpose(0, 2, 1))
    # Red-black order: segments at even and at odd depths in the tree share no joint, so each
    # colour's segments are refitted at once in one batched fit (padded to a common number of
    # points); the sweeps alternate the colours. The first sweep goes top-down one segment at a
    # time, so that every segment starts from a solved parent.
    depth = []
    for seg in segs:                              # parent before child
        depth.append(0 if seg.parent < 0 else depth[seg.parent] + 1)
    colours = [[s_ for s_ in range(S) if depth[s_] % 2 == c] for c in (0, 1)]
    colours = [c for c in colours if c]
    sizes = {s_: len(seg_local[s_]) for s_ in range(S)}
    schedule = [(k, None) for k in range(int(n_sweeps))]
    if model_bones:
        schedule.append((0, "model"))
        schedule += [(k, None) for k in range(max(2, int(n_sweeps) // 2))]
    # Frames are solved independently until the gap rule, so long trials go in blocks of
    # _BLOCK_FRAMES: the batched arrays then stay small (on a 20 000-frame walk, 0.9-1.2x the
    # one-segment-at-a-time sweeps within this machine's noise, 0.6-0.9x without blocks).
    blocks = [(lo, min(lo + _BLOCK_FRAMES, F)) for lo in range(0, F, _BLOCK_FRAMES)]
    steps = schedule
    if progress:
        from bonecap.progress import progress as _bar

        if len(blocks) > 1:
            blocks = _bar(blocks, "lsq frame blocks", total=len(blocks))
        else:
            steps = _bar(schedule, "lsq sweeps", total=len(schedule))
    free_any: set = set()

    for lo, hi in blocks:
        Fb = hi - lo
        Tb, okb = T[:, lo:hi], ok[:, lo:hi]      # views: the block's poses land in T and ok
        meas_b, w_vis_b, meas_t_b = meas[lo:hi], w_vis[lo:hi], meas_t[lo:hi]
        # the scapula's turn on its clavicle (girdle frame), per rhythm's girdle: none until solved
        turns = {rh.segment: np.tile(np.eye(4), (Fb, 1, 1)) for rh in rhythms}
        swings = {g: np.tile(np.eye(4), (Fb, 1, 1)) for g in swung}
        unturned = dict(turns)            # T_g turn^-1 T_g^-1 of each girdle (see _unturned)
        unswung = dict(swings)            # the same for each swung prior, in its parent
        fixed = set()
        free = list(range(S))
        # per colour: a (G, Fb, 3, Kmax) target buffer and (G, Fb, Kmax) weights, markers filled
        # once; each segment's (Fb, 3, K) and (Fb, K) buffers are views into them
        bufs: list = [None] * S
        batches = []
        # a short block is bound by the calls' overhead, a long one by the padded arithmetic
        waste = 0.25 if Fb >= 1024 else np.inf
        for group in (g for colour in colours for g in _size_batches(colour, sizes, waste)):
            Kmax = max(len(seg_local[s_]) for s_ in group)
            Pg = np.zeros((len(group), Kmax, 3))
            Qg = np.zeros((len(group), Fb, 3, Kmax))
            Wg = np.zeros((len(group), Fb, Kmax))
            for i, s_ in enumerate(group):
                K = len(seg_local[s_])
                ms = seg_markers[s_]
                Pg[i, :K] = seg_local[s_]
                Qg[i, :, :, :len(ms)] = meas_t_b[:, :, ms]
                Wg[i, :, :len(ms)] = w_vis_b[:, ms]
                bufs[s_] = (Qg[i, :, :, :K], Wg[i, :, :K])
            batches.append((group, Pg, Qg, Wg))

        def turn_rhythms():
            # each girdle's scapula turned for the poses so far; its markers' targets taken back to
            # where the unturned scapula of the girdle's rigid fit would carry them; each one-marker
            # girdle's prior target swung with its marker's line
            # (a segment is refitted once a sweep, after these: each one's own pose is still the one
            # these were taken from when its pseudo-markers are filled)
            for g, (d, R_rest) in swung.items():
                swings[g] = _swing(Tb[segs[g].parent], Tb[g], d, R_rest, segs[g].joint_in_parent)
                unswung[g] = _unturned(Tb[segs[g].parent], swings[g])
            for rh in rhythms:
                g = rh.segment
                turns[g] = rhythm_turns(rh, Tb[rh.parent], Tb[g], Tb[rh.child])[0]
                back = unturned[g] = _unturned(Tb[g], turns[g])
                slots = scapula_slots[g]
                if slots:
                    Q, _ = bufs[g]
                    q = meas_t_b[:, :, [seg_markers[g][i] for i in slots]]
                    moved = np.einsum("fij,fjk->fik", back[:, :3, :3], q) + back[:, :3, 3, None]
                    Q[:, :, slots] = np.where(np.isfinite(moved), moved, q)

        def fill_pseudo(s_):
            # joint pseudo-markers where the neighbours put them; none where a neighbour
            # is not solved in a frame (weight 0), none from a model-placed radius onto
            # the ulna it was placed on
            seg = segs[s_]
            Q, Wt = bufs[s_]
            slot = len(seg_markers[s_])
            pts, wts, runs = own_links[s_]
            if runs:
                # an arm hangs from its girdle's turned scapula; a one-marker girdle's prior swings
                T_par = Tb[seg.parent] @ turns[seg.parent] if s_ in hung else Tb[seg.parent]
                for prior, a, b in runs:
                    Tn = Tb[seg.parent] @ swings[s_] if prior else T_par
                    place_points(Tn, pts[a:b], wts[a:b], 1.0, Q, Wt, slot + a)
                slot += len(pts)
            for c in children[s_]:
                wc = 0.0 if segs[c].root in fixed else 1.0
                T_c = unturned[s_] @ Tb[c] if c in hung else Tb[c]
                pts, wts, runs = child_links[c]
                for prior, a, b in runs:
                    Tn = unswung[c] @ Tb[c] if prior else T_c
                    place_points(Tn, pts[a:b], wts[a:b], wc, Q, Wt, slot + a)
                slot += len(pts)

        def sweep(k, tol):
            """One red-black sweep over the free segments; with ``tol``: whether none moved more."""
            free_set = set(free)
            before = Tb[free] if tol is not None else None     # a copy (fancy indexing)
            turn_rhythms()
            # colour 0's batches come first in the list: reversed, colour 1 goes first
            for group, Pg, Qg, Wg in (batches if k % 2 == 0 else batches[::-1]):
                todo = [i for i, s in enumerate(group) if s in free_set]
                if not todo:
                    continue
                for i in todo:
                    fill_pseudo(group[i])
                R, t, v = _fit_qcp(Pg, Qg, Wg)
                Tg = _to_T(R, t, v)
                for i in todo:
                    Tb[group[i]] = Tg[i]
                    okb[group[i]] = v[i]
            if before is None:
                return False
            after = Tb[free]
            d = np.abs(after[..., :3, :] - before[..., :3, :]) * np.array([100.0, 100.0, 100.0, 1.0])
            return bool(np.nan_to_num(d, nan=0.0).max(initial=0.0) <= tol
                        and (np.isnan(after) == np.isnan(before)).all())

        first = True
        converged = False         # with tol_mm: the sweeps before (or after) the model step are done
        for k, step in steps:
            if converged and step is None:
                continue
            converged = False
            if step == "model":
                # An ulna its markers cannot hold (one styloid marker and the elbow, as in Plug-in
                # Gait) takes the model's own ulna pose, carried by the four forearm markers' elbow frame.
                by_markers = forearm_poses_from_markers(skeleton, forearm, labels, marker_bones, local, meas_b)
                held = set()
                for b in model_bones:
                    u = b.replace("radius", "ulna")
                    su = plan.segment_of[u]
                    if u in by_markers and segs[su].root == u:
                        gap = ~okb[su] & np.isfinite(by_markers[u]["transforms"]).all(axis=(1, 2))
                        Tb[su][gap] = by_markers[u]["transforms"][gap]
                        okb[su] |= gap
                        if gap.any():
                            held.add(u)      # the next sweeps could not hold it either: keep it
                ulnas = {b.replace("radius", "ulna"): Tb[plan.segment_of[b.replace("radius", "ulna")]]
                         for b in model_bones}
                poses = forearm_poses_from_markers(skeleton, forearm, labels, marker_bones, local, meas_b,
                                                   ulna_to_lab=ulnas)
                for b in model_bones:
                    model_clamped[b][lo:hi] = poses[b]["clamped"]
                    Tb[plan.segment_of[b]] = poses[b]["transforms"]
                    okb[plan.segment_of[b]] = np.isfinite(poses[b]["transforms"]).all(axis=(1, 2))
                fixed = set(model_bones) | held
                free = [s for s in range(S) if segs[s].root not in fixed]
                continue
            if first:
                for s in free:
                    fill_pseudo(s)
                    R, t, v = _fit_qcp(seg_local[s], *bufs[s])
                    Tb[s] = _to_T(R, t, v)
                    okb[s] = v
                first = False
                continue
            converged = sweep(k, sweep_tol)
        if newton:
            # the sweeps stopped at sweep_tol: Gauss-Newton steps from there (see _newton); should
            # they fail, the sweeps go on to tol_mm as without them
            var = [s_ for s_ in free if np.isfinite(Tb[s_]).all()]
            done = not var
            # the scapulae's turns and the priors' swings held while the steps run, then taken again
            # from their result (one frame: rhythms make newton False for more), until they settle
            moving = bool(rhythms or swung)
            turn_rhythms()
            for _ in range(_RHYTHM_ROUNDS if moving else 1):
                if done:
                    break
                held = [x.copy() for x in (*turns.values(), *swings.values())]
                segs_n, local_n = _with_turns(segs, seg_local, rhythms, scapula_slots, turns, swings)
                if not _newton(Tb, var, segs_n, local_n, seg_markers, meas_b, w_vis_b, joint_weight, tol_mm):
                    for k in range(int(n_sweeps)):
                        if sweep(k, tol_mm):
                            break
                    break
                turn_rhythms()
                done = not moving or max(float(np.abs(a[:, :3, :3] - b[:, :3, :3]).max())
                                         for a, b in zip(held, (*turns.values(), *swings.values()))) \
                    <= np.radians(_RHYTHM_TOL_DEG)

        # A segment frame counts as solved only where its own visible markers and its proximal
        # joint (its parent solved there) make three points: pseudo-markers from its children
        # refine a determined pose but do not determine one -- a thigh without its thigh marker,
        # held by hip, knee marker and the shank's knee, has a twist nothing pins down (tested on
        # the phantom walk: up to 35 degrees off). Such frames go to the gap rule below.
        for s in free:
            n_points = np.count_nonzero(w_vis_b[:, seg_markers[s]], axis=1)
            if segs[s].joint is not None and segs[s].parent >= 0:
                n_points = n_points + len(segs[s].links()) * okb[segs[s].parent]
            okb[s] &= n_points >= 3
            Tb[s][~okb[s]] = np.nan
        free_any |= set(free)
    free = sorted(free_any)

    # Gaps: interpolate each segment relative to its parent, top-down.
    valid_seg = ok.copy()
    for s in free:
        p = segs[s].parent
        if valid_seg[s].all():
            continue
        if p < 0:
            T[s], valid_seg[s] = _fill_gaps(np.where(ok[s][:, None, None], T[s], np.eye(4)), ok[s],
                                            int(max_gap_frames))
        else:
            rel = np.where(ok[s][:, None, None], _inv(np.nan_to_num(T[p])) @ np.nan_to_num(T[s]), np.eye(4))
            rel, filled = _fill_gaps(rel, ok[s] & valid_seg[p], int(max_gap_frames))
            newT = T[p] @ rel
            use = filled & ~ok[s]
            T[s][use] = newT[use]
            valid_seg[s] = (ok[s] | use) & np.isfinite(T[s]).all(axis=(1, 2))
        T[s][~valid_seg[s]] = np.nan

    names = skeleton.names
    out = np.full((F, len(names), 4, 4), np.nan)
    valid = np.zeros((F, len(names)), bool)
    clamped = np.zeros((F, len(names)), bool)
    scapula_turn = {rh.scapula: rhythm_turns(rh, T[rh.parent], T[rh.segment], T[rh.child])[0] for rh in rhythms}
    for i, n in enumerate(names):
        s = plan.segment_of[n]
        out[:, i] = T[s] @ (scapula_turn[n] @ segs[s].rest_to_root[n] if n in scapula_turn
                            else segs[s].rest_to_root[n])
        valid[:, i] = valid_seg[s]
        if n in model_clamped:
            # held at the end of the model's fitted range: a pose, flagged, not a gap (a few degrees of
            # hyper-pronation or -supination are common in real trials)
            clamped[:, i] = model_clamped[n] & valid[:, i]
    out[~np.isfinite(out).all(axis=(2, 3))] = np.nan
    bi = np.array([names.index(b) for b in marker_bones], int)
    pred = _apply(out[:, bi], local[None])
    residuals = np.linalg.norm(pred - meas, axis=-1)
    return Motion(bones=names, times=np.arange(F) / float(rate_hz), transforms=out, valid=valid,
                  first_frame=int(first_frame), marker_labels=labels, residuals=residuals,
                  flags={"forearm_clamped": clamped} if model_clamped else {})


# ----------------------------------------------------------------------------- filtering


def lowpass_markers(measured, rate_hz: float, cutoff_hz: float = 6.0, order: int = 2) -> np.ndarray:
    """Zero-lag Butterworth low-pass of marker trajectories, gap aware.

    A Butterworth filter of ``order`` run forward and backward
    (:func:`scipy.signal.filtfilt`: zero phase lag, effective order
    ``2 * order``, the -3 dB point of the pair at ~``cutoff_hz``). Each run of
    finite samples of a marker is filtered on its own, so a gap (NaN) neither
    spreads nor is bridged; runs too short for the filter's edge padding are
    left as measured. 6 Hz is the usual cut-off for walking (Winter 2009).

    Parameters
    ----------
    measured : array_like, shape (F, M, 3)
        Markers in the lab frame, mm, NaN in gaps.
    rate_hz : float
        Frame rate (Hz).
    cutoff_hz : float, default 6
        Cut-off frequency (Hz), below the Nyquist frequency ``rate_hz / 2``.
    order : int, default 2

    Returns
    -------
    ndarray, shape (F, M, 3)
        Filtered markers, NaN where the input was NaN.

    References
    ----------
    .. [1] Winter DA (2009). Biomechanics and Motor Control of Human Movement,
       4th ed., Wiley, ch. 3.
    """
    from scipy.signal import butter, filtfilt

    x = np.asarray(measured, dtype=float)
    if x.ndim != 3 or x.shape[2] != 3:
        raise ValueError(f"measured must have shape (frames, markers, 3), got {x.shape}")
    if not (rate_hz > 0):
        raise ValueError(f"rate_hz must be positive, got {rate_hz!r}")
    if not (0 < cutoff_hz < rate_hz / 2):
        raise ValueError(f"cutoff_hz must lie in (0, {rate_hz / 2}) (the Nyquist frequency), got {cutoff_hz!r}")
    b, a = butter(int(order), cutoff_hz / (rate_hz / 2))
    padlen = 3 * max(len(a), len(b))
    F, M, _ = x.shape
    flat = x.reshape(F, M * 3)
    out = flat.copy()
    finite = np.isfinite(flat)
    if finite.all() and F > padlen:
        return filtfilt(b, a, flat, axis=0).reshape(F, M, 3)
    # Gap-aware: filter each run of finite samples; runs are grouped by (start, stop) so
    # every column sharing a run is filtered in one call.
    runs: dict[tuple[int, int], list[int]] = {}
    for col in range(M * 3):
        f = np.concatenate([[False], finite[:, col], [False]])
        d = np.flatnonzero(np.diff(f.astype(np.int8)))
        for s0, s1 in zip(d[::2], d[1::2]):
            runs.setdefault((int(s0), int(s1)), []).append(col)
    for (s0, s1), cols in runs.items():
        if s1 - s0 > padlen:
            out[s0:s1, cols] = filtfilt(b, a, flat[s0:s1, cols], axis=0)
    return out.reshape(F, M, 3)
