"""Synthetic motion-capture trials of a phantom subject, with their ground truth.

The phantom's skeleton (the generic template, a varied copy of it, or an
OpenSim model) is moved through five trials -- ``static``, ``walk``,
``arm_raise``, ``pronation`` and ``touch`` -- and the markers of a marker set,
stuck on the subject's skin, are written as C3D files in a Z-up lab together
with everything needed to score a reconstruction: the bone poses, the joint
centres, the markers before and after soft-tissue artefact, and the true
marker-to-bone binding.

Public API
----------
- :func:`make_trials` ``(skeleton, marker_set, out_dir, *, skin=None, seed=0,
  ...) -> dict``: everything, written under ``out_dir``.
- :func:`synthesize_trials` -- the same in memory (:class:`PhantomTrial` per
  trial, no files).
- :func:`joint_table` ``(skeleton) -> JointTable``: the anatomical joints
  the motions drive, resolved for the skeleton at hand
  (:func:`reference_pose_offsets` reads an MRI reference pose to undo).
- :func:`trial_motion` ``(name, table, ...) -> TrialMotion``: joint-angle
  time series of one trial; :func:`pose_trial` turns it into bone poses.
- :func:`place_phantom_markers` ``(marker_set, skeleton, skin=None) ->
  MarkerBinding``; :func:`build_sta_model` ``(binding, table, skeleton,
  seed) -> SoftTissueModel``; :func:`sta_class` ``(marker, bone) -> str``.

Frames and units
----------------
- Millimetres, seconds, degrees in angle series (radians only inside
  rotations). Poses are 4x4 ``a_to_b`` transforms (``p_b = T @ p_a``).
- **Skeleton world** (``bone_to_world`` of the reference pose): the template
  convention, X anterior, Y superior, Z to the subject's right. A skeleton in
  another world frame (an MRI subject in LPS) is handled: the anatomical
  directions are measured on the skeleton itself (hip centres give *right*,
  ankles -> hips give *up*, see :func:`anatomical_frame`) and everything
  below uses those directions, so nothing assumes the reference (MRI) pose is
  the pose of any trial.
- **Lab**: Z up, X the walking direction, Y to the subject's left
  (:data:`~bonecap.skeleton.template.MODEL_TO_LAB_ZUP` applied to the
  anatomical frame); the floor is ``z = 0``; 100 Hz.

The joint table and its angle conventions
-----------------------------------------
Each joint is a rotation of its *child* bone about the joint centre shared
with its parent, expressed in the **parent bone's frame** (as
:func:`~bonecap.skeleton.kinematics.pose_skeleton` wants it), built as the
intrinsic sequence flexion -> abduction -> axial rotation (the order of
Grood & Suntay 1983 and of the ISB recommendations, Wu et al. 2002/2005)::

    R = Rot(a_flex, flex) @ Rot(a_abd, abd) @ Rot(a_rot, rot)

The three axes are the anatomical directions expressed in the parent frame
at the anatomical pose, so the table works for ISB bone frames and for OpenSim
body frames alike. Angles are always **anatomical**: 0 is the anatomical
standing pose, not the skeleton's reference pose. When the reference is an
MRI pose (:mod:`bonecap.phantom.subject` abducts arms and legs so the skin
segments per slice; it records the angles in
``metadata["phantom"]["pose"]``, see :func:`reference_pose_offsets`), each
such joint gets a ``neutral`` rotation that undoes its offset, so the same
angles give the same bone poses whatever the scan pose was. Positive angles
mean, for either side:

============  ===================  =====================  ======================
joint         flexion (+)          abduction (+)          rotation (+)
============  ===================  =====================  ======================
hip_x         thigh forward        leg away from midline  internal rotation
knee_x        shank backward       (varus/valgus, unused) internal rotation
ankle_x       dorsiflexion         inversion              internal (toes in)
mtp_x         toe extension        --                     --
lumbar        trunk forward        bend to the right      turn to the left
shoulder_x    arm forward          arm away from midline  internal rotation
elbow_x       forearm up           --                     --
wrist_x       palmar flexion       radial deviation       --
============  ===================  =====================  ======================

(flexion axis: the right-pointing axis, sign flipped for the knee and
lumbar spine; abduction: the anterior axis, sign by side; rotation: the
superior axis, sign by side). Where the model has a one-axis joint (an
OpenSim ``PinJoint``: elbow, ankle) its own axis replaces the world-derived
flexion axis (same sense), and the other two are re-orthogonalised.

Bones not in the table follow their parent (zero joint rotation): fibula,
calcaneus, foot, vertebrae above the lumbar joint, ribs, sternum, skull,
mandible, carpals and rays below the wrist. Three extra rules:
the **shoulder girdle** follows the arm (scapulohumeral rhythm,
:data:`GIRDLE_RHYTHM`): for a humerus raised ``E`` degrees from the thorax's
downward axis the clavicle rises by 0.12 E and retracts by 0.12 E at the
sternoclavicular joint and the scapula turns upward by 0.2 E at the
acromioclavicular joint, about the normal of its own plane (ISB's ``X``; the
scapula ~0.3 E on the thorax: Inman's 2:1), the
humerus keeping the orientation its shoulder angles give it relative to the
thorax while the girdle carries its centre (at 150 deg the acromion moves
~70 mm, the shoulder centre ~80 mm; an OpenSim model without clavicles has
no girdle). The reference pose's girdle is the rhythm's at the reference's own
``E`` (an MRI pose's arms lie abducted), so a pose turns it by the rhythm of
``E - E_ref``;
the **patella**, when it hangs from the femur, turns about the knee flexion
axis through the knee centre by 0.7 x knee flexion (it rides the trochlea; its
joint centre then slides on the femur by design); the **radius** is driven by
the forearm model below, whatever its parent bone is.

Forearm pronation-supination
----------------------------
The radius turns relative to the ulna about the radio-ulnar axis: from the
centre of the radial head to the fovea of the ulnar head (generic skeleton:
landmarks ``radial_head_centre`` on the radius and ``ulnar_head_fovea`` on the
ulna; OpenSim: the radius's one-axis ``pro_sup`` joint, its distal end taken at
the level of the radius's distal joint). The angle ``theta`` (deg) is 0 at the
skeleton's reference pose -- the anatomical, supinated position (palm forward,
radius lateral and parallel to the ulna) for both templates -- and grows with
pronation up to 180 deg. Positive ``theta`` is a right-hand rotation about the
proximally pointing axis for the right forearm (distally pointing for the
left), which carries the radial styloid anteriorly then medially.

The axis is not fixed in the ulna: in vivo its ends wander by 0.1-2.4 mm at
the ulnar head (Appl Sci 2022;12:3108) and the radius slides ~1 mm proximally
in mid-pronation (Fu et al. 2009). This module's own model (not the quadratic
of the paper under test): with ``c = (1 - cos theta) / 2`` and
``s = sin theta``, in the ulna frame,

- proximal end ``A = A0 + 1.0 c e_p + 0.5 s e_l`` (mm),
- distal end ``B = B0 + 2.5 c e_p + 1.0 s e_l`` (mm),
- a translation of ``0.8 sin(theta)^2`` mm along the axis, proximally,

with ``e_p`` the palmar (anterior at the reference) direction normal to the
axis and ``e_l = p x e_p`` (``p`` the proximal direction). The radius pose relative to the ulna is a screw
about the line through ``A`` and ``B``: rotation ``theta`` plus that small axial
slide, so the finite helical axis from the 0 deg pose *is* the stored axis.

Soft-tissue artefact (STA)
--------------------------
Each marker is classified (:func:`sta_class`) and given a peak amplitude
(:data:`STA_AMPLITUDE_MM`): thigh 12 mm, upper arm 10 mm, shank and forearm
6 mm, other soft places (scapula) 6 mm, markers over bony landmarks 2.5 mm
(Leardini et al. 2005; Peters et al. 2010). The displacement of marker ``m``
relative to its bone, in the bone frame, is a smooth function of the angles
of the joints next to its segment -- the kinematics-driven STA model of
Camomilla et al. (2015)::

    d_m(t) = tau_c(t) + omega_c(t) x (p_m - pbar_c) + n_m(t)
    tau, omega, n = sum_k  U_k s_k(t) + V_k s_k(t)^2,
    s_k = sin(pi/2 * clip((q_k - q0_k) / range_k, -1, 1))

``q_k`` are the anatomical angles of the joints next to the segment (its own
joint, the joints it carries; for the forearm bones also the elbow, the
pronation angle and the wrist; the pelvis angles for a segment without
any), ``c`` is the marker's cluster (same bone, same class): ``tau_c`` and
``omega_c`` move the cluster rigidly, ``n_m`` is each marker's own
(non-rigid) share. Rigid and non-rigid cluster modes are of similar size or
the rigid one dominates (Grimpampi et al. 2014; Dumas et al. 2014; Camomilla
et al. 2017), so a fraction ``rho`` of 0.6-0.8 (drawn per cluster) of the
amplitude goes to the rigid part (markers of different classes on one bone --
the epicondyles and the mid-humerus marker -- form different clusters: a
rigid motion common to both would move the bony marker as much as the soft
one). Coefficient vectors have random directions; each part is scaled so that
its peak over the poses of the standard trials (static, walk, arm raise,
pronation) is its share of the amplitude (gain capped at 6), and a smooth
saturation keeps ``|d_m| <= amplitude`` in any other pose. The same pose
gives the same artefact in every trial, so calibration and movement trials
agree. Then 0.5 mm Gaussian noise per coordinate, then occlusion gaps (NaN)
of configurable number and length.

Walking
-------
Two cycles of 1.1 s from right heel strike, toe off at 62 %. The lowest foot
point rests on the floor in every frame (sole soft tissue: measured on the
skin, 10 mm without one). The pelvis advances so that the supporting foot
does not slide at its contact point (the support is blended over double
support); its mean speed is ~1.1-1.2 m/s for an adult, but because textbook
joint-angle curves are not exactly consistent with each other its forward
speed pulsates within the cycle more than in real walking (~0.5-2 m/s)
rather than letting the stance foot skate.

References
----------
.. [1] Leardini A, Chiari L, Della Croce U, Cappozzo A (2005). Human movement
   analysis using stereophotogrammetry. Part 3. Soft tissue artifact
   assessment and compensation. Gait Posture 21(2):212-225.
.. [2] Peters A, Galna B, Sangeux M, Morris M, Baker R (2010). Quantification
   of soft tissue artifact in lower limb human motion analysis: a systematic
   review. Gait Posture 31(1):1-8.
.. [3] Camomilla V, Bonci T, Dumas R, Cheze L, Cappozzo A (2015). A model of
   the soft tissue artefact rigid component. J Biomech 48(10):1752-1759.
.. [4] Camomilla V, Dumas R, Cappozzo A (2017). Human movement analysis: the
   soft tissue artefact issue. J Biomech 62:1-4 (and, in that issue, the
   high-density marker-cluster study, J Biomech 62:21-26: translations and
   rotations of the cluster remain the main STA modes).
.. [5] Grimpampi E, Camomilla V, Cereatti A, de Leva P, Cappozzo A (2014).
   Metrics for describing soft-tissue artefact and its effect on pose, size,
   and shape of marker clusters. IEEE Trans Biomed Eng 61(2):362-367.
.. [6] Dumas R, Camomilla V, Bonci T, Cheze L, Cappozzo A (2014). Generalized
   mathematical representation of the soft tissue artefact. J Biomech
   47(2):476-481.
.. [7] Fu E, Li G, Souer S, et al. (2009). Elbow position affects distal
   radioulnar joint kinematics. J Hand Surg Am 34(7):1261-1268.
.. [8] Is the fovea ulnaris truly isometric during forearm rotation? An in
   vivo analysis using superimpositions of 3-D reconstructions (2022). Appl
   Sci 12(6):3108.
.. [9] Kadaba MP, Ramakrishnan HK, Wootten ME (1990). Measurement of lower
   extremity kinematics during level walking. J Orthop Res 8(3):383-392
   (shape of the sagittal gait curves used for ``walk``).
.. [10] Wu G et al. (2002, 2005). ISB recommendation on definitions of joint
   coordinate systems. J Biomech 35:543-548; 38:981-992.
.. [11] Leardini A, Benedetti MG, Berti L, Bettinelli D, Nativo R, Giannini S
   (2007). Rizzoli multi-segment foot model for motion analysis. Gait Posture
   25(3):453-462 (the rearfoot's inversion and rotation on the shank in ``walk``).
"""

from __future__ import annotations

import functools
import json
import os
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from bonecap.errors import DataError, InputError
from bonecap.io.atomic import atomic_path
from bonecap.markers import MarkerSet, check_marker_set
from bonecap.model import Mesh, Skeleton, Trial
from bonecap.skeleton.kinematics import pose_skeleton, proximal_joint
from bonecap.skeleton.template import MODEL_TO_LAB_ZUP

__all__ = [
    "TRIAL_NAMES", "RATE_HZ", "STA_AMPLITUDE_MM", "GIRDLE_RHYTHM", "JointSpec", "GirdleSpec", "ForearmSpec",
    "JointTable", "girdle_angles",
    "anatomical_frame", "reference_pose_offsets", "joint_table", "TrialMotion", "trial_motion", "pose_trial", "forearm_motion",
    "MarkerBinding", "place_phantom_markers", "sta_class", "SoftTissueModel", "build_sta_model",
    "PhantomTrial", "synthesize_trials", "make_trials",
]

#: Trials made by default, in this order.
TRIAL_NAMES = ("static", "walk", "arm_raise", "pronation", "touch")
#: Frame rate of every trial (Hz).
RATE_HZ = 100.0
#: Peak soft-tissue displacement per marker class (mm), before ``sta_scale``.
STA_AMPLITUDE_MM = {"thigh": 12.0, "upper_arm": 10.0, "shank": 6.0, "forearm": 6.0, "soft": 6.0, "bony": 2.5}

# Forearm axis migration (mm), see the module documentation.
_MIG_PROX = (1.0, 0.5)    # proximal end: palmar * (1 - cos)/2, lateral * sin
_MIG_DIST = (2.5, 1.0)    # distal end
_AXIAL_SLIDE_MM = 0.8     # proximal slide of the radius, * sin^2
_PATELLA_RATIO = 0.7      # patellar flexion / knee flexion
_NO_SKIN_PAD_MM = 10.0    # sole soft tissue below the foot bones when there is no skin
_MAX_STA_GAIN = 6.0       # cap of the STA calibration gain (segments that barely move stay small)

# Normalisation ranges (deg) of the joint angles in the STA model: flexion, abduction, rotation.
_STA_RANGES = {"hip": (90, 45, 45), "knee": (120, 20, 20), "ankle": (30, 20, 20), "mtp": (45, 20, 20),
               "lumbar": (30, 30, 30), "shoulder": (150, 150, 90), "elbow": (130, 20, 20),
               "wrist": (70, 30, 30), "pelvis": (10, 10, 10)}


# ----------------------------------------------------------------------------------------------
# Small geometry helpers
# ----------------------------------------------------------------------------------------------

def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=float)
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.maximum(n, 1e-12)


def _rotvec_matrices(axis: np.ndarray, angle_rad: np.ndarray) -> np.ndarray:
    """Rotations ``(F, 3, 3)`` about the unit ``axis`` (3,) or (F, 3) by ``angle_rad`` (F,)."""
    angle_rad = np.asarray(angle_rad, dtype=float).reshape(-1)
    axis = np.broadcast_to(np.asarray(axis, dtype=float), (len(angle_rad), 3))
    return Rotation.from_rotvec(axis * angle_rad[:, None]).as_matrix()


def _apply(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Map points ``p`` (..., 3) by transforms ``T`` (..., 4, 4) (broadcasting)."""
    return (T[..., :3, :3] @ np.asarray(p, float)[..., None])[..., 0] + T[..., :3, 3]


def _children(skeleton: Skeleton) -> dict[str, list[str]]:
    kids: dict[str, list[str]] = {n: [] for n in skeleton.bones}
    for n, b in skeleton.bones.items():
        if b.parent is not None:
            kids[b.parent].append(n)
    return kids


def _subtree(skeleton: Skeleton, bone: str, kids: dict[str, list[str]] | None = None) -> list[str]:
    kids = kids or _children(skeleton)
    out, stack = [], [bone]
    while stack:
        b = stack.pop()
        out.append(b)
        stack.extend(kids[b])
    return out


def _root(skeleton: Skeleton) -> str:
    roots = [n for n, b in skeleton.bones.items() if b.parent is None]
    if len(roots) != 1:
        raise DataError(f"the phantom skeleton must have exactly one root bone, it has {roots}")
    return roots[0]


def _world_points(skeleton: Skeleton, bone: str, max_points: int = 400, hull: bool = False) -> np.ndarray:
    """Points of a bone in the world frame at the reference pose: mesh vertices (subsampled) or,
    without a mesh, its joint centres and landmarks. ``hull``: the vertices of the mesh's convex
    hull instead (they hold the extreme point in every direction: floor contact)."""
    b = skeleton.bones[bone]
    if b.mesh is not None and len(b.mesh.vertices):
        v = b.mesh.vertices
        if hull and len(v) >= 4:
            try:
                from scipy.spatial import ConvexHull

                v = v[ConvexHull(v).vertices]
            except Exception:  # degenerate (flat) mesh: keep the vertices
                pass
        if len(v) > max_points:
            v = v[np.linspace(0, len(v) - 1, max_points).astype(int)]
    else:
        v = np.array(list(b.joint_centres.values()) + list(b.landmarks.values()) or [np.zeros(3)])
    return _apply(b.bone_to_world, v)


# ----------------------------------------------------------------------------------------------
# Anatomical directions and the joint table
# ----------------------------------------------------------------------------------------------

_CANDIDATES = {
    "femur": ("femur_{s}",),
    "tibia": ("tibia_{s}",),
    "patella": ("patella_{s}",),
    "talus": ("talus_{s}", "calcn_{s}", "calcaneus_{s}", "foot_{s}"),
    "toes": ("toes_{s}",),
    "humerus": ("humerus_{s}",),
    "ulna": ("ulna_{s}",),
    "radius": ("radius_{s}",),
    "hand": ("hand_{s}", "carpals_{s}"),
    "clavicle": ("clavicle_{s}",),
    "scapula": ("scapula_{s}",),
}
_LUMBAR_CANDIDATES = ("torso", "l5", "lumbar5", "l4", "thorax")


def _find_bone(skeleton: Skeleton, role: str, side: str) -> str | None:
    for pattern in _CANDIDATES[role]:
        name = pattern.format(s=side)
        if name in skeleton.bones:
            return name
    return None


def _joint_centre_world(skeleton: Skeleton, bone: str) -> np.ndarray:
    _, _, c_child = proximal_joint(skeleton, bone)
    return _apply(skeleton.bones[bone].bone_to_world, c_child)


def anatomical_frame(skeleton: Skeleton) -> np.ndarray:
    """The anatomical directions of the skeleton at its reference pose, in its world frame.

    Parameters
    ----------
    skeleton : Skeleton
        Any world frame (template: X anterior, Y up, Z right; an MRI subject: LPS).

    Returns
    -------
    ndarray, shape (3, 3)
        Columns: anterior, superior, right unit vectors in world coordinates
        (``anat_to_world`` rotation). *Right* is hip centre right minus left,
        *superior* the mean ankle -> mean hip direction made normal to it,
        *anterior* ``superior x right``. When these are within 10 deg of the
        world axes (a template), the world axes themselves are returned, so
        template angles are exactly about X, Y, Z.
    """
    try:
        hips = {s: _joint_centre_world(skeleton, _find_bone(skeleton, "femur", s)) for s in "rl"}
        ankles = {s: _joint_centre_world(skeleton, _find_bone(skeleton, "talus", s)) for s in "rl"}
    except (TypeError, KeyError, ValueError):
        return np.eye(3)
    right = _unit(hips["r"] - hips["l"])
    up = (hips["r"] + hips["l"]) / 2 - (ankles["r"] + ankles["l"]) / 2
    up = _unit(up - (up @ right) * right)
    anterior = np.cross(up, right)
    A = np.stack([anterior, up, right], axis=1)
    angle = np.degrees(np.arccos(np.clip((np.trace(A) - 1) / 2, -1, 1)))
    return np.eye(3) if angle < 10.0 else A


@dataclass(frozen=True)
class JointSpec:
    """One driven joint of the table.

    Attributes
    ----------
    name : str
        ``hip_r``, ``knee_r``, ``ankle_r``, ``mtp_r``, ``lumbar``, ``shoulder_r``,
        ``elbow_r``, ``wrist_r`` (and ``_l``).
    kind : str
        The name without side (``hip``...).
    side : int
        +1 right, -1 left, 0 midline.
    child, parent : str
        The bone that moves and its parent bone.
    joint : str
        Name of the shared joint centre.
    centre : ndarray (3,)
        Joint centre in the parent frame (mm).
    axes : ndarray (3, 3)
        Rows: flexion, abduction and rotation unit axes in the parent frame.
    neutral : ndarray (3, 3)
        Rotation (parent frame) from the skeleton's reference pose back to the anatomical
        pose: identity unless the reference is not anatomical (an MRI pose with the limbs
        abducted, see :func:`reference_pose_offsets`). The joint rotation given to
        :func:`~bonecap.skeleton.kinematics.pose_skeleton` is ``R(angles) @ neutral``, so angles
        are always anatomical.
    """

    name: str
    kind: str
    side: int
    child: str
    parent: str
    joint: str
    centre: np.ndarray
    axes: np.ndarray
    neutral: np.ndarray = field(default_factory=lambda: np.eye(3))


#: The shoulder girdle's share of the arm's elevation (the scapulohumeral rhythm), per degree of the
#: humerus's elevation from the thorax's downward axis: the clavicle rises and retracts at the
#: sternoclavicular joint and the scapula turns upward at the acromioclavicular joint. Over 0-120 deg
#: of elevation the clavicle rises ~10-15 deg and retracts ~15-20 deg and the scapula turns upward by
#: ~35-40 deg relative to the thorax (Ludewig et al. 2009; Inman et al. 1944's 2:1 glenohumeral to
#: scapulothoracic ratio); the acromion moves by centimetres.
GIRDLE_RHYTHM = {"clavicle_elevation": 0.12, "clavicle_retraction": 0.12, "scapula_upward_rotation": 0.2}


@dataclass(frozen=True)
class GirdleSpec:
    """A shoulder girdle that follows the arm's elevation (:data:`GIRDLE_RHYTHM`).

    Attributes
    ----------
    side : int
        +1 right, -1 left.
    sternum, clavicle, scapula, humerus : str
        The bones: the clavicle turns on the sternum, the scapula on the clavicle; the humerus keeps
        the orientation its shoulder angles give it relative to the thorax and is carried to where the
        scapula puts the shoulder joint.
    sc_centre : ndarray (3,)
        The sternoclavicular joint centre in the sternum's frame (mm).
    ac_centre : ndarray (3,)
        The acromioclavicular joint centre in the clavicle's frame (mm).
    elevation_axis, retraction_axis : ndarray (3,)
        Unit axes in the sternum's frame: turning about them by a positive angle lifts / draws back
        the clavicle's lateral end.
    upward_axis : ndarray (3,)
        Unit axis in the clavicle's frame, the scapula's ISB ``X`` at the reference pose (the normal
        of the scapular plane): a positive turn about it turns the scapula upward (glenoid up,
        inferior angle lateral).
    shoulder_in_humerus : ndarray (3,)
        The shoulder joint centre in the humerus's frame (mm).
    """

    side: int
    sternum: str
    clavicle: str
    scapula: str
    humerus: str
    sc_centre: np.ndarray
    ac_centre: np.ndarray
    elevation_axis: np.ndarray
    retraction_axis: np.ndarray
    upward_axis: np.ndarray
    shoulder_in_humerus: np.ndarray


def _girdle_spec(skeleton: Skeleton, side: str, anat: np.ndarray) -> GirdleSpec | None:
    """The girdle of one side, or None where the skeleton has none (an OpenSim model's arm hangs on the
    thorax): a clavicle with its sternoclavicular and acromioclavicular centres under a parent (the
    sternum), a scapula on the clavicle, a humerus on the scapula."""
    clavicle, scapula = _find_bone(skeleton, "clavicle", side), _find_bone(skeleton, "scapula", side)
    humerus = _find_bone(skeleton, "humerus", side)
    if clavicle is None or scapula is None or humerus is None:
        return None
    bc, bs, bh = skeleton.bones[clavicle], skeleton.bones[scapula], skeleton.bones[humerus]
    if bs.parent != clavicle or bh.parent != scapula or bc.parent is None:
        return None
    st = skeleton.bones[bc.parent]
    sc = bc.joint_centres.get("sternoclavicular")
    ac = bc.joint_centres.get("acromioclavicular")
    try:
        _, _, gh = proximal_joint(skeleton, humerus)
    except ValueError:
        return None
    if sc is None or ac is None:
        return None
    sign = 1.0 if side == "r" else -1.0
    R_st, R_cl = st.bone_to_world[:3, :3], bc.bone_to_world[:3, :3]
    sc_world = _apply(bc.bone_to_world, sc)
    # The scapula turns upward about the normal of its own plane, ISB's X_s (Wu et al. 2005: the line
    # perpendicular to the plane of the inferior angle, acromial angle and trigonum spinae; upward rotation
    # is the turn about it in the scapula's Y-X-Z sequence, as Ludewig et al. 2009 report it). The blade lies
    # round the thorax, so the body's anterior axis (session 31's) is not that axis (24 deg from it on the
    # embedded skeleton). Pointed forward.
    xs = bs.bone_to_world[:3, 0]
    xs = xs if xs @ anat[:, 0] >= 0 else -xs
    # lateral is +right for the right side: a turn about -anterior lifts it, about -superior draws it back
    return GirdleSpec(side=int(sign), sternum=bc.parent, clavicle=clavicle, scapula=scapula, humerus=humerus,
                      sc_centre=_apply(np.linalg.inv(st.bone_to_world), sc_world), ac_centre=np.asarray(ac, float),
                      elevation_axis=R_st.T @ (-sign * anat[:, 0]), retraction_axis=R_st.T @ (-sign * anat[:, 1]),
                      upward_axis=R_cl.T @ (-sign * xs), shoulder_in_humerus=np.asarray(gh, float))


def girdle_angles(table: "JointTable", angles: Mapping[str, np.ndarray], side: str) -> dict[str, np.ndarray]:
    """The girdle's angles (deg, (F,) each, keys of :data:`GIRDLE_RHYTHM`) for a side's shoulder angles.

    The humerus's elevation is the angle between its long axis and the thorax's downward axis for the
    anatomical shoulder angles (flexion and abduction both raise it); the girdle takes
    :data:`GIRDLE_RHYTHM` of it."""
    spec = table.joints[f"shoulder_{side}"]
    a = np.atleast_2d(np.asarray(angles.get(f"shoulder_{side}", np.zeros((1, 3))), float))
    E = _arm_elevation(spec, _angles_to_matrix(spec.axes, a))
    return {k: c * E for k, c in GIRDLE_RHYTHM.items()}


def _arm_elevation(spec: "JointSpec", R: np.ndarray) -> np.ndarray:
    """The humerus's elevation (deg, (F,)) from the thorax's downward axis for shoulder rotations ``R``
    (F, 3, 3) from the anatomical pose (parent frame)."""
    # the rotation axis is the superior one times the side (_AXES): the humerus's long axis points down
    down = -spec.axes[2] * spec.side
    cosE = np.einsum("fij,j,i->f", R, down, down)
    return np.degrees(np.arccos(np.clip(cosE, -1.0, 1.0)))


def _move_girdles(T: np.ndarray, skeleton: Skeleton, table: "JointTable", angles: Mapping[str, np.ndarray],
                  kids: dict[str, list[str]]) -> None:
    """Turn each girdle by the rhythm (in place on ``T`` (F, B, 4, 4)), the arm carried with it: the
    humerus keeps its orientation, its shoulder centre goes where the scapula puts it."""
    index = {n: i for i, n in enumerate(skeleton.names)}
    F = T.shape[0]
    for s, g in table.girdles.items():
        if not all(b in index for b in (g.sternum, g.clavicle, g.scapula, g.humerus)) \
                or f"shoulder_{s}" not in table.joints:
            continue
        # The reference pose's girdle is where the rhythm has it for the reference's own arms (an MRI
        # pose's arms lie abducted ~20 deg): the trial's girdle turns from there. (It had been taken as the
        # rhythm's zero, the arm hanging straight down, so that a walk's hanging arm turned the scapula
        # upward on the MRI's by ~2 deg while the arm came down ~15 deg.)
        E_ref = _arm_elevation(table.joints[f"shoulder_{s}"], table.joints[f"shoulder_{s}"].neutral.T[None])[0]
        ga = {k: np.broadcast_to(v - GIRDLE_RHYTHM[k] * E_ref, (F,))
              for k, v in girdle_angles(table, angles, s).items()}
        if not np.any([np.any(v) for v in ga.values()]):
            continue
        B = skeleton.bones
        rest_c = np.linalg.solve(B[g.sternum].bone_to_world, B[g.clavicle].bone_to_world)
        rest_s = np.linalg.solve(B[g.clavicle].bone_to_world, B[g.scapula].bone_to_world)
        Rc = _rotvec_matrices(g.elevation_axis, np.radians(ga["clavicle_elevation"])) \
            @ _rotvec_matrices(g.retraction_axis, np.radians(ga["clavicle_retraction"]))
        Rs = _rotvec_matrices(g.upward_axis, np.radians(ga["scapula_upward_rotation"]))
        H = T[:, index[g.humerus]].copy()
        gh_before = _apply(H, g.shoulder_in_humerus)
        for bone, parent, R, c, rest in ((g.clavicle, g.sternum, Rc, g.sc_centre, rest_c),
                                         (g.scapula, g.clavicle, Rs, g.ac_centre, rest_s)):
            J = np.tile(np.eye(4), (F, 1, 1))
            J[:, :3, :3] = R
            J[:, :3, 3] = c - R @ c
            _apply_subtree_correction(T, index, _subtree(skeleton, bone, kids), bone, T[:, index[parent]] @ J @ rest)
        # the arm's orientation stays the one its angles give relative to the thorax
        H[:, :3, 3] += _apply(T[:, index[g.humerus]], g.shoulder_in_humerus) - gh_before
        _apply_subtree_correction(T, index, _subtree(skeleton, g.humerus, kids), g.humerus, H)


@dataclass(frozen=True)
class ForearmSpec:
    """The radio-ulnar joint of one forearm (see the module documentation).

    Attributes
    ----------
    name : str
        ``radioulnar_r`` / ``radioulnar_l``.
    side : int
    ulna, radius : str
    proximal, distal : ndarray (3,)
        Radial-head centre and ulnar-head fovea at 0 deg, in the **ulna frame** (mm).
    axis : ndarray (3,)
        Unit pronation axis (ulna frame): pronation is a right-hand rotation about it.
    palmar : ndarray (3,)
        Unit palmar direction normal to the axis (ulna frame, anterior at the reference).
    source : str
        ``"landmarks"``, ``"joint_axis"`` (OpenSim pro_sup) or ``"fallback"``.
    """

    name: str
    side: int
    ulna: str
    radius: str
    proximal: np.ndarray
    distal: np.ndarray
    axis: np.ndarray
    palmar: np.ndarray
    source: str


@dataclass
class JointTable:
    """The joints the phantom's motions drive, resolved for one skeleton.

    Attributes
    ----------
    joints : dict of str -> JointSpec
    forearms : dict of str -> ForearmSpec
    anat : ndarray (3, 3)
        :func:`anatomical_frame` (columns anterior, superior, right in world).
    root : str
        The root bone (pelvis).
    pelvis_centre : ndarray (3,)
        Mid-point of the hip centres, world frame: the pelvis rotates about it.
    patellae : dict of str -> tuple (patella, knee joint name)
        Patellae that follow the knee-flexion rule.
    feet : dict of str -> list of str
        Per side, the bones from the ankle down (floor contact).
    hands : dict of str -> str
        Per side, the bone below the wrist (hand_r / carpals_r).
    girdles : dict of str -> GirdleSpec
        Per side, the shoulder girdle that follows the arm's elevation (skeletons with clavicles).
    """

    joints: dict[str, JointSpec]
    forearms: dict[str, ForearmSpec]
    anat: np.ndarray
    root: str
    pelvis_centre: np.ndarray
    patellae: dict[str, tuple[str, str]] = field(default_factory=dict)
    feet: dict[str, list[str]] = field(default_factory=dict)
    hands: dict[str, str] = field(default_factory=dict)
    girdles: dict[str, GirdleSpec] = field(default_factory=dict)

    def describe(self) -> dict[str, Any]:
        """A JSON-able description (bones, parent, axes in the parent frame)."""
        out = {n: {"child": j.child, "parent": j.parent, "joint_centre": j.joint,
                   "axes_in_parent": {"flexion": j.axes[0].round(4).tolist(),
                                      "abduction": j.axes[1].round(4).tolist(),
                                      "rotation": j.axes[2].round(4).tolist()}}
               for n, j in self.joints.items()}
        for n, f in self.forearms.items():
            out[n] = {"child": f.radius, "relative_to": f.ulna, "source": f.source,
                      "axis_in_ulna": f.axis.round(4).tolist(),
                      "proximal_in_ulna": f.proximal.round(2).tolist(),
                      "distal_in_ulna": f.distal.round(2).tolist()}
        for s, (p, knee) in self.patellae.items():
            out[f"patella_{s}"] = {"child": p, "rule": f"{_PATELLA_RATIO} x {knee} flexion about the knee axis"}
        return out


# Anatomical axis of each component (in the anatomical frame: 0 anterior, 1 superior, 2 right)
# as (index, sign, multiply sign by side?) for flexion, abduction, rotation.
_AXES = {
    "hip": ((2, 1, False), (0, -1, True), (1, 1, True)),
    "knee": ((2, -1, False), (0, -1, True), (1, 1, True)),
    "ankle": ((2, 1, False), (0, 1, True), (1, 1, True)),
    "mtp": ((2, 1, False), (0, 1, True), (1, 1, True)),
    "lumbar": ((2, -1, False), (0, 1, False), (1, 1, False)),
    "shoulder": ((2, 1, False), (0, -1, True), (1, 1, True)),
    "elbow": ((2, 1, False), (0, -1, True), (1, 1, True)),
    "wrist": ((2, 1, False), (0, -1, True), (1, 1, True)),
}


def reference_pose_offsets(skeleton: Skeleton) -> dict[str, np.ndarray]:
    """Joint angles (deg) of the skeleton's reference pose relative to the anatomical pose.

    Parameters
    ----------
    skeleton : Skeleton
        ``metadata["reference_pose_deg"]`` (joint name -> flexion, abduction, rotation), or
        the MRI pose written by :func:`bonecap.phantom.subject.make_subject` in
        ``metadata["phantom"]["pose"]`` (``arm_abduction_deg_r/_l``: each arm abducted about
        the shoulder centre, ``leg_abduction_deg``: both legs about the hip centres).

    Returns
    -------
    dict of str -> ndarray (3,)
        Empty for a skeleton in the anatomical pose (the templates).
    """
    out: dict[str, np.ndarray] = {}
    pose = (skeleton.metadata.get("phantom") or {}).get("pose") or {}
    for s in "rl":
        if f"arm_abduction_deg_{s}" in pose:
            out[f"shoulder_{s}"] = np.array([0.0, float(pose[f"arm_abduction_deg_{s}"]), 0.0])
        if "leg_abduction_deg" in pose:
            out[f"hip_{s}"] = np.array([0.0, float(pose["leg_abduction_deg"]), 0.0])
    for k, v in (skeleton.metadata.get("reference_pose_deg") or {}).items():
        out[str(k)] = np.asarray(v, float).reshape(3)
    return out


def _angles_to_matrix(axes: np.ndarray, a_deg: np.ndarray) -> np.ndarray:
    """``Rot(flex) @ Rot(abd) @ Rot(rot)`` (F, 3, 3) for angles (F, 3) in degrees."""
    a = np.radians(np.atleast_2d(np.asarray(a_deg, float)))
    return _rotvec_matrices(axes[0], a[:, 0]) @ _rotvec_matrices(axes[1], a[:, 1]) \
        @ _rotvec_matrices(axes[2], a[:, 2])


def _make_joint(skeleton: Skeleton, kind: str, name: str, child: str, side: int, anat: np.ndarray,
                offset: np.ndarray | None = None) -> JointSpec | None:
    bone = skeleton.bones[child]
    if bone.parent is None:
        return None
    try:
        joint, c_parent, _ = proximal_joint(skeleton, child)
    except ValueError:
        return None
    parent = skeleton.bones[bone.parent]
    R_pw = parent.bone_to_world[:3, :3]
    world_axes = []
    for idx, sign, by_side in _AXES[kind]:
        world_axes.append(anat[:, idx] * sign * (side if by_side and side else 1))
    axes = np.array([R_pw.T @ a for a in world_axes])
    # A one-axis joint of the model (PinJoint) is the better flexion axis: keep its sense.
    model_axis = bone.joint_axes.get(joint)
    if model_axis is not None and kind in ("knee", "ankle", "mtp", "elbow"):
        a = R_pw.T @ bone.bone_to_world[:3, :3] @ model_axis
        if abs(a @ axes[0]) > np.cos(np.radians(35)):
            axes[0] = a * np.sign(a @ axes[0])
    f = _unit(axes[0])
    ab = _unit(axes[1] - (axes[1] @ f) * f)
    r = _unit(axes[2] - (axes[2] @ f) * f - (axes[2] @ ab) * ab)
    axes = np.stack([f, ab, r])
    neutral = np.eye(3) if offset is None else _angles_to_matrix(axes, offset)[0].T
    return JointSpec(name=name, kind=kind, side=side, child=child, parent=bone.parent, joint=joint,
                     centre=np.asarray(c_parent, float), axes=axes, neutral=neutral)


def _forearm_spec(skeleton: Skeleton, ulna: str, radius: str, side: int, anat: np.ndarray,
                  hand: str | None) -> ForearmSpec:
    U, Rd = skeleton.bones[ulna], skeleton.bones[radius]
    to_ulna = np.linalg.inv(U.bone_to_world) @ Rd.bone_to_world  # radius frame -> ulna frame (rest)
    source = "fallback"
    if "radial_head_centre" in Rd.landmarks and "ulnar_head_fovea" in U.landmarks:
        A = _apply(to_ulna, Rd.landmarks["radial_head_centre"])
        B = U.landmarks["ulnar_head_fovea"].copy()
        source = "landmarks"
    else:
        shared = sorted(set(Rd.joint_centres) & set(U.joint_centres))
        axis = None
        A = None
        for j in shared:
            if j in Rd.joint_axes or j in U.joint_axes:
                A = _apply(to_ulna, Rd.joint_centres[j])
                axis = (to_ulna[:3, :3] @ Rd.joint_axes[j]) if j in Rd.joint_axes else U.joint_axes[j]
                break
        # distal reference: the radius's joint with the hand, else its farthest point
        if hand is not None:
            try:
                _, c_par, _ = proximal_joint(skeleton, hand)
                D = _apply(to_ulna, c_par) if skeleton.bones[hand].parent == radius else \
                    _apply(np.linalg.inv(U.bone_to_world) @ skeleton.bones[skeleton.bones[hand].parent].bone_to_world,
                           c_par)
            except ValueError:
                D = None
        else:
            D = None
        if A is None:
            pts = np.array(list(Rd.joint_centres.values()) or [np.zeros(3)])
            A = _apply(to_ulna, pts[0])
        if D is None:
            pts = _apply(np.linalg.inv(U.bone_to_world), _world_points(skeleton, radius))
            D = pts[np.argmax(np.linalg.norm(pts - A, axis=1))]
        if axis is not None:
            axis = _unit(axis)
            B = A + axis * ((D - A) @ axis)
            source = "joint_axis"
        else:
            B = D
    p = _unit(A - B)                       # proximal direction, ulna frame
    axis = p * (side if side else 1)       # right: proximal; left: distal (right-hand rule)
    ant = np.linalg.inv(U.bone_to_world)[:3, :3] @ anat[:, 0]
    palmar = _unit(ant - (ant @ p) * p)
    return ForearmSpec(name=f"radioulnar_{'r' if side >= 0 else 'l'}", side=side, ulna=ulna, radius=radius,
                       proximal=np.asarray(A, float), distal=np.asarray(B, float), axis=axis, palmar=palmar,
                       source=source)


def joint_table(skeleton: Skeleton) -> JointTable:
    """Resolve the driven joints for ``skeleton`` (generic template, varied subject or OpenSim model).

    Parameters
    ----------
    skeleton : Skeleton
        Reference pose in any world frame (see :func:`anatomical_frame`). When the reference is
        not the anatomical pose (:func:`reference_pose_offsets`, e.g. the MRI pose of a phantom
        subject with its limbs abducted), the axes are taken from the skeleton brought back to
        the anatomical pose and each offset joint gets the ``neutral`` rotation that undoes its
        offset, so the same angles give the same poses whatever the scan pose was.

    Returns
    -------
    JointTable
        Joints whose bones exist; missing ones are simply left out (a legs-only
        model gets no arm joints).
    """
    offsets = reference_pose_offsets(skeleton)
    if not offsets:
        return _table_from(skeleton, {})
    # Bring the skeleton to the anatomical pose. A joint's axes depend on its parent's anatomical
    # orientation, so nested offsets need as many rounds as their depth (3 is plenty).
    from dataclasses import replace

    anatomical = skeleton
    root = _root(skeleton)
    for _ in range(3):
        table = _table_from(anatomical, offsets)
        rots = {j.child: j.neutral[None] for j in table.joints.values() if j.name in offsets}
        T = pose_skeleton(skeleton, skeleton.bones[root].bone_to_world, rots)[0]
        anatomical = Skeleton(bones={n: replace(b, bone_to_world=T[i]) for i, (n, b) in
                                     enumerate(skeleton.bones.items())}, world=skeleton.world,
                              metadata=skeleton.metadata)
    return _table_from(anatomical, offsets)


def _table_from(skeleton: Skeleton, offsets: Mapping[str, np.ndarray]) -> JointTable:
    """The table of a skeleton whose ``bone_to_world`` is the anatomical pose; ``offsets`` give
    the neutral rotations back from the original reference pose."""
    anat = anatomical_frame(skeleton)
    root = _root(skeleton)
    joints: dict[str, JointSpec] = {}
    forearms: dict[str, ForearmSpec] = {}
    patellae: dict[str, tuple[str, str]] = {}
    feet: dict[str, list[str]] = {}
    hands: dict[str, str] = {}
    kids = _children(skeleton)

    def add(kind: str, name: str, child: str | None, side: int):
        if child is None:
            return
        spec = _make_joint(skeleton, kind, name, child, side, anat, offsets.get(name))
        if spec is not None:
            joints[name] = spec

    hip_centres = []
    for s, sign in (("r", 1), ("l", -1)):
        femur = _find_bone(skeleton, "femur", s)
        tibia = _find_bone(skeleton, "tibia", s)
        talus = _find_bone(skeleton, "talus", s)
        add("hip", f"hip_{s}", femur, sign)
        add("knee", f"knee_{s}", tibia, sign)
        add("ankle", f"ankle_{s}", talus, sign)
        add("mtp", f"mtp_{s}", _find_bone(skeleton, "toes", s), sign)
        add("shoulder", f"shoulder_{s}", _find_bone(skeleton, "humerus", s), sign)
        ulna = _find_bone(skeleton, "ulna", s)
        radius = _find_bone(skeleton, "radius", s)
        hand = _find_bone(skeleton, "hand", s)
        add("elbow", f"elbow_{s}", ulna, sign)
        add("wrist", f"wrist_{s}", hand, sign)
        if femur is not None:
            hip_centres.append(_joint_centre_world(skeleton, femur))
        if talus is not None:
            feet[s] = _subtree(skeleton, talus, kids)
        if hand is not None:
            hands[s] = hand
        if ulna is not None and radius is not None:
            fs = _forearm_spec(skeleton, ulna, radius, sign, anat, hand)
            forearms[fs.name] = fs
        patella = _find_bone(skeleton, "patella", s)
        if patella is not None and femur is not None and f"knee_{s}" in joints \
                and skeleton.bones[patella].parent == femur:
            patellae[s] = (patella, f"knee_{s}")
    for cand in _LUMBAR_CANDIDATES:
        if cand in skeleton.bones and skeleton.bones[cand].parent is not None:
            add("lumbar", "lumbar", cand, 0)
            break
    if hip_centres:
        pelvis_centre = np.mean(hip_centres, axis=0)
    else:
        pelvis_centre = skeleton.bones[root].bone_to_world[:3, 3].copy()
    girdles = {}
    for s in "rl":
        g = _girdle_spec(skeleton, s, anat) if f"shoulder_{s}" in joints else None
        if g is not None:
            girdles[s] = g
    return JointTable(joints=joints, forearms=forearms, anat=anat, root=root, pelvis_centre=pelvis_centre,
                      patellae=patellae, feet=feet, hands=hands, girdles=girdles)


# ----------------------------------------------------------------------------------------------
# Motions: joint-angle time series
# ----------------------------------------------------------------------------------------------

@dataclass
class TrialMotion:
    """Joint-angle time series of one trial.

    Attributes
    ----------
    name : str
    times : ndarray (F,)
        Seconds from 0 at :data:`RATE_HZ`.
    angles : dict of str -> ndarray (F, 3)
        Per table joint: flexion, abduction, rotation in degrees (conventions in the module doc).
    twist : dict of str -> ndarray (F,)
        Per forearm (``radioulnar_r``...): pronation angle in degrees, 0 = reference (supinated).
    pelvis : ndarray (F, 3)
        Pelvis anterior tilt, obliquity (right side up) and rotation (right side forward), deg,
        about the pelvis centre relative to the reference orientation.
    position : ndarray (F, 3)
        Pelvis centre in the lab (mm; x forward, y left); z is set by floor contact.
    walking : bool
    support : dict of str -> ndarray (F,)
        Walking only: per side, the share of the body carried by that foot (1 in single support,
        ramping over double support, 0 in swing); the pelvis advances so the supporting foot
        does not slide.
    events : list of dict
        C3D events (``label``, ``context``, ``time``).
    """

    name: str
    times: np.ndarray
    angles: dict[str, np.ndarray]
    twist: dict[str, np.ndarray]
    pelvis: np.ndarray
    position: np.ndarray
    walking: bool = False
    support: dict[str, np.ndarray] = field(default_factory=dict)
    events: list[dict[str, Any]] = field(default_factory=list)

    @property
    def n_frames(self) -> int:
        return len(self.times)


def _keyframes(t: np.ndarray, keys: Sequence[tuple[float, float]]) -> np.ndarray:
    """Piecewise cosine interpolation through ``(time, value)`` keys: smooth (C1), zero velocity at keys."""
    kt = np.array([k[0] for k in keys], float)
    kv = np.array([k[1] for k in keys], float)
    out = np.full_like(t, kv[0], dtype=float)
    for i in range(len(kt) - 1):
        m = (t >= kt[i]) & (t <= kt[i + 1])
        if kt[i + 1] > kt[i]:
            u = (t[m] - kt[i]) / (kt[i + 1] - kt[i])
            out[m] = kv[i] + (kv[i + 1] - kv[i]) * (1 - np.cos(np.pi * u)) / 2
    out[t > kt[-1]] = kv[-1]
    return out


def _periodic(points: Sequence[tuple[float, float]]) -> "CubicSpline":  # noqa: F821
    """Periodic cubic spline through ``(percent of cycle, value)`` points (0 and 100 equal)."""
    # scipy.interpolate and scipy.optimize are imported where they are used: the phantom's main
    # process imports this module but makes its trials in a child, and the two held ~9 MiB there
    from scipy.interpolate import CubicSpline

    x = np.array([p[0] for p in points], float) / 100.0
    y = np.array([p[1] for p in points], float)
    return CubicSpline(x, y, bc_type="periodic")


# Normal gait curves (deg) vs % of the cycle from heel strike; shapes after Kadaba et al. (1990)
# and Winter's normative data, smoothed by a periodic spline. Hip flexion is relative to the
# *anatomically neutral* pelvis of the skeleton (Plug-in Gait reports it against a pelvis frame
# tilted ~10 deg forward, hence ~8 deg less here); knee and ankle were then adjusted so that the
# swing foot clears the floor (>= 0 mm, typically 5-20 mm) while the stance foot carries the body.
# The knots here; the splines are made on first use (:func:`_gait`).
_GAIT_POINTS = {
    "hip_flex": [(0, 22), (10, 20), (20, 13), (30, 5), (40, -4), (50, -13), (55, -16), (60, -13),
                 (65, -6), (70, 3), (75, 12), (80, 20), (87, 26), (93, 26), (100, 22)],
    "hip_abd": [(0, 0), (20, -5), (50, -1), (65, 5), (82, 2), (100, 0)],
    "hip_rot": [(0, 0), (20, 4), (50, -1), (70, -5), (100, 0)],
    "knee_flex": [(0, 5), (8, 14), (15, 18), (22, 16), (32, 9), (42, 6), (50, 10), (55, 18), (60, 35),
                  (65, 51), (72, 63), (78, 61), (85, 53), (91, 34), (96, 15), (100, 5)],
    "ankle_flex": [(0, 0), (6, -5), (12, -2), (20, 4), (30, 7), (40, 10), (46, 9), (52, 2), (57, -8),
                   (62, -17), (67, -7), (73, 2), (80, 5), (88, 5), (100, 0)],
    "mtp_flex": [(0, 0), (40, 5), (55, 28), (62, 25), (70, 6), (78, 0), (100, 0)],
    # the rearfoot on the shank (talocrural and subtalar together): eversion through the loading
    # response, inversion through push-off, ~10 deg in all; internal rotation in the loading response,
    # external in late stance (shapes after Leardini et al. 2007's rearfoot-tibia angles [11])
    "ankle_inv": [(0, 2), (12, -4), (30, -3), (45, 0), (60, 7), (70, 4), (85, 1), (100, 2)],
    "ankle_rot": [(0, 0), (12, 3), (35, 1), (55, -4), (65, -5), (80, -1), (100, 0)],
}


@functools.lru_cache(maxsize=1)
def _gait() -> dict[str, "CubicSpline"]:  # noqa: F821
    """The gait curves (:data:`_GAIT_POINTS`) as periodic splines of the cycle fraction, made once."""
    return {k: _periodic(v) for k, v in _GAIT_POINTS.items()}


_TOE_OFF = 0.62
_GAIT_CYCLE_S = 1.1


def trial_motion(name: str, table: JointTable, *, duration_scale: float = 1.0, rate: float = RATE_HZ,
                 skeleton: Skeleton | None = None, skin: Mesh | None = None) -> TrialMotion:
    """Joint-angle time series of a trial.

    Parameters
    ----------
    name : str
        ``static`` (1 s standing, arms abducted 60 deg -- at least 30 deg beyond
        any MRI pose of :mod:`bonecap.phantom.subject`, which abducts them by at
        most 30 deg -- elbows flexed 15 deg, forearms pronated 40 deg),
        ``walk`` (two gait cycles of 1.1 s), ``arm_raise`` (both arms: abduction
        to 150 deg with elbow flexion to 120 deg and external rotation, then
        forward flexion to 150 deg), ``pronation`` (elbows to 90 deg, then the
        forearms 0 -> 180 -> 0 deg twice), ``touch`` (hands meet in front of the
        chest, then rest on the hips; needs ``skeleton``, solved by inverse
        kinematics).
    table : JointTable
    duration_scale : float
        Scripted trials are played ``1/duration_scale`` times faster; ``walk``
        keeps its cadence and is cut to ``duration_scale`` of its two cycles
        (at least one cycle); ``static`` lasts ``duration_scale`` s (>= 0.2 s).
    rate : float
        Frames per second.
    skeleton, skin : optional
        Needed by ``touch`` (targets from the body's own dimensions).

    Returns
    -------
    TrialMotion
    """
    if duration_scale <= 0:
        raise InputError(f"duration_scale must be positive, got {duration_scale}")
    k = float(duration_scale)
    sides = ("r", "l")

    def frames_for(seconds: float) -> np.ndarray:
        return np.arange(max(int(round(seconds * rate)), 2)) / rate

    def finish(t, angles, twist, pelvis=None, position=None, **kw) -> TrialMotion:
        F = len(t)
        full = {j: np.zeros((F, 3)) for j in table.joints}
        for j, v in angles.items():
            if j in full:
                full[j] = np.asarray(v, float).reshape(F, 3)
        tw = {f: np.zeros(F) for f in table.forearms}
        for f, v in twist.items():
            if f in tw:
                tw[f] = np.broadcast_to(np.asarray(v, float), (F,)).copy()
        return TrialMotion(name=name, times=t, angles=full, twist=tw,
                           pelvis=np.zeros((F, 3)) if pelvis is None else pelvis,
                           position=np.zeros((F, 3)) if position is None else position, **kw)

    if name == "static":
        t = frames_for(max(1.0 * k, 0.2))
        F = len(t)
        angles, twist = {}, {}
        for s in sides:
            angles[f"shoulder_{s}"] = np.tile([0.0, 60.0, 0.0], (F, 1))
            angles[f"elbow_{s}"] = np.tile([15.0, 0.0, 0.0], (F, 1))
            angles[f"hip_{s}"] = np.tile([0.0, 3.0, 0.0], (F, 1))
            twist[f"radioulnar_{s}"] = 40.0
        return finish(t, angles, twist)

    if name == "walk":
        cycles = max(2.0 * k, 1.0)
        t = frames_for(cycles * _GAIT_CYCLE_S)
        F = len(t)
        angles, twist = {}, {}
        for s, shift in (("r", 0.0), ("l", 0.5)):
            ph = (t / _GAIT_CYCLE_S + shift) % 1.0
            gait = _gait()
            angles[f"hip_{s}"] = np.stack([gait["hip_flex"](ph), gait["hip_abd"](ph), gait["hip_rot"](ph)], 1)
            angles[f"knee_{s}"] = np.stack([gait["knee_flex"](ph), 0 * ph, 0 * ph], 1)
            angles[f"ankle_{s}"] = np.stack([gait["ankle_flex"](ph), gait["ankle_inv"](ph), gait["ankle_rot"](ph)], 1)
            angles[f"mtp_{s}"] = np.stack([gait["mtp_flex"](ph), 0 * ph, 0 * ph], 1)
            # arm swings against the leg of the same side
            angles[f"shoulder_{s}"] = np.stack([5 - 15 * np.cos(2 * np.pi * ph), 8 + 0 * ph, 0 * ph], 1)
            angles[f"elbow_{s}"] = np.stack([15 + 6 * (1 - np.cos(2 * np.pi * ph)), 0 * ph, 0 * ph], 1)
            twist[f"radioulnar_{s}"] = 70.0
        ph = (t / _GAIT_CYCLE_S) % 1.0
        pelvis = np.stack([2.0 * np.cos(4 * np.pi * ph), 4.0 * np.sin(2 * np.pi * ph + np.pi / 6),
                           5.0 * np.cos(2 * np.pi * ph)], 1)
        angles["lumbar"] = np.stack([-1.5 * np.cos(4 * np.pi * ph), 0.9 * pelvis[:, 1], -1.6 * pelvis[:, 2]], 1)
        # lateral sway of the pelvis over the stance foot (lab +y is the subject's left)
        position = np.stack([0 * t, -20.0 * np.sin(2 * np.pi * ph), 0 * t], 1)
        ds = _TOE_OFF - 0.5  # double support after each heel strike
        support = {}
        for s, shift in (("r", 0.0), ("l", 0.5)):
            ph = (t / _GAIT_CYCLE_S + shift) % 1.0
            support[s] = np.clip(ph / ds, 0, 1) * (ph <= 0.5) + np.clip((0.5 + ds - ph) / ds, 0, 1) * (ph > 0.5)
        events = []
        for s, shift, ctx in (("r", 0.0, "Right"), ("l", 0.5, "Left")):
            for label, at in (("Foot Strike", 0.0), ("Foot Off", _TOE_OFF)):
                c0 = (at - shift) % 1.0
                for c in np.arange(c0, t[-1] / _GAIT_CYCLE_S + 1e-9, 1.0):
                    events.append({"label": label, "context": ctx, "time": float(c * _GAIT_CYCLE_S)})
        events.sort(key=lambda e: e["time"])
        return finish(t, angles, twist, pelvis=pelvis, position=position, walking=True, support=support,
                      events=events)

    if name == "arm_raise":
        key = [0.5, 2.5, 3.0, 5.0, 5.5, 7.5, 8.0, 10.0]
        T = [x * k for x in key]
        t = frames_for(10.5 * k)
        abd = _keyframes(t, [(0, 0), (T[0], 0), (T[1], 150), (T[2], 150), (T[3], 0)])
        flex = _keyframes(t, [(0, 0), (T[4], 0), (T[5], 150), (T[6], 150), (T[7], 0)])
        rot = _keyframes(t, [(0, 0), (T[0], 0), (T[1], -40), (T[2], -40), (T[3], 0)])
        elbow = _keyframes(t, [(0, 0), (T[0], 0), (T[1], 120), (T[2], 120), (T[3], 0), (T[4], 0), (T[5], 60),
                               (T[6], 60), (T[7], 0)])
        angles, twist = {}, {}
        for s in sides:
            angles[f"shoulder_{s}"] = np.stack([flex, abd, rot], 1)
            angles[f"elbow_{s}"] = np.stack([elbow, 0 * t, 0 * t], 1)
            twist[f"radioulnar_{s}"] = 20.0
        return finish(t, angles, twist)

    if name == "pronation":
        t0, period = 1.5 * k, 3.5 * k
        t = frames_for(t0 + 2 * period + 0.5 * k)
        elbow = _keyframes(t, [(0, 0), (0.3 * k, 0), (1.3 * k, 90)])
        u = np.clip((t - t0) / period, 0, 2)
        theta = 90.0 - 90.0 * np.cos(2 * np.pi * u)
        angles, twist = {}, {}
        for s in sides:
            angles[f"shoulder_{s}"] = np.stack([0 * t, 10 + 0 * t, 0 * t], 1)
            angles[f"elbow_{s}"] = np.stack([elbow, 0 * t, 0 * t], 1)
            twist[f"radioulnar_{s}"] = theta
        return finish(t, angles, twist)

    if name == "touch":
        if skeleton is None:
            raise InputError("the 'touch' trial needs the skeleton (its hands are placed by inverse kinematics)")
        poses = _touch_poses(skeleton, table, skin)
        key = [0.5, 2.0, 3.0, 4.5, 6.0, 7.0, 8.5]
        T = [x * k for x in key]
        t = frames_for(9.0 * k)
        angles, twist = {}, {}
        for s in sides:
            if f"shoulder_{s}" not in table.joints:
                continue
            rest = poses["rest"][s]
            front, hips = poses["front"][s], poses["hips"][s]
            cols = []
            for i in range(5):  # shoulder flex, abd, rot, elbow flex, twist
                cols.append(_keyframes(t, [(0, rest[i]), (T[0], rest[i]), (T[1], front[i]), (T[2], front[i]),
                                           (T[3], rest[i]), (T[4], hips[i]), (T[5], hips[i]), (T[6], rest[i])]))
            angles[f"shoulder_{s}"] = np.stack(cols[:3], 1)
            angles[f"elbow_{s}"] = np.stack([cols[3], 0 * t, 0 * t], 1)
            twist[f"radioulnar_{s}"] = cols[4]
        m = finish(t, angles, twist)
        return m

    raise InputError(f"unknown trial {name!r} (known: {', '.join(TRIAL_NAMES)})")


# ----------------------------------------------------------------------------------------------
# Poses
# ----------------------------------------------------------------------------------------------

def _joint_rotations(table: JointTable, angles: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Rotation matrices (F, 3, 3) per child bone, in the parent frame, from anatomical angles (deg)."""
    out = {}
    for name, spec in table.joints.items():
        a = np.asarray(angles.get(name, np.zeros((1, 3))), float)
        identity = np.allclose(spec.neutral, np.eye(3))
        if not np.any(a) and identity:
            continue
        R = _angles_to_matrix(spec.axes, a)
        out[spec.child] = R if identity else R @ spec.neutral
    return out


def forearm_motion(spec: ForearmSpec, theta_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pose of the radius relative to the ulna for pronation angles ``theta_deg``.

    Parameters
    ----------
    spec : ForearmSpec
    theta_deg : ndarray (F,)
        Pronation angle, 0 = the reference (supinated) pose.

    Returns
    -------
    M : ndarray (F, 4, 4)
        The motion, in the **ulna frame**, that takes the radius from its reference
        relation to the ulna to the pronated one: ``radius_to_ulna(theta) = M @ radius_to_ulna(0)``.
        A screw about the line through ``A`` and ``B``.
    A, B : ndarray (F, 3)
        Radial-head and ulnar-head ends of the radio-ulnar axis at each angle, ulna frame (mm).
    """
    th = np.radians(np.asarray(theta_deg, float).reshape(-1))
    c, s = (1 - np.cos(th)) / 2, np.sin(th)
    p0 = _unit(spec.proximal - spec.distal)
    lateral = _unit(np.cross(p0, spec.palmar))
    A = spec.proximal + (_MIG_PROX[0] * c)[:, None] * spec.palmar + (_MIG_PROX[1] * s)[:, None] * lateral
    B = spec.distal + (_MIG_DIST[0] * c)[:, None] * spec.palmar + (_MIG_DIST[1] * s)[:, None] * lateral
    p = _unit(A - B)
    u = p * (spec.side if spec.side else 1)
    R = _rotvec_matrices(u, th)
    M = np.tile(np.eye(4), (len(th), 1, 1))
    M[:, :3, :3] = R
    M[:, :3, 3] = A - (R @ A[..., None])[..., 0] + (_AXIAL_SLIDE_MM * np.sin(th) ** 2)[:, None] * p
    return M, A, B


def _apply_subtree_correction(transforms: np.ndarray, index: dict[str, int], bones: list[str],
                              bone: str, target: np.ndarray) -> None:
    """Move ``bone`` to ``target`` (F, 4, 4) and carry its descendants ``bones`` rigidly with it."""
    i = index[bone]
    C = target @ np.linalg.inv(transforms[:, i])
    for b in bones:
        j = index[b]
        transforms[:, j] = C @ transforms[:, j]


def _pose_core(skeleton: Skeleton, table: JointTable, angles: Mapping[str, np.ndarray],
               twist: Mapping[str, np.ndarray], root_to_lab: np.ndarray) -> tuple[np.ndarray, dict]:
    """Bone poses (F, B, 4, 4) for angles, forearm twists and a root pose. Bones of the table that
    are not in ``skeleton`` (a sub-skeleton for IK) are skipped."""
    rots = {b: R for b, R in _joint_rotations(table, angles).items() if b in skeleton.bones}
    T = pose_skeleton(skeleton, root_to_lab, rots)
    names = skeleton.names
    index = {n: i for i, n in enumerate(names)}
    kids = _children(skeleton)
    _move_girdles(T, skeleton, table, angles, kids)
    extra: dict[str, np.ndarray] = {}
    F = T.shape[0]
    for s, (patella, knee) in table.patellae.items():
        if patella not in index:
            continue
        spec = table.joints[knee]
        femur = spec.parent
        flex = np.radians(np.asarray(angles.get(knee, np.zeros((F, 3))), float)[:, 0]) * _PATELLA_RATIO
        M = np.tile(np.eye(4), (F, 1, 1))
        M[:, :3, :3] = _rotvec_matrices(spec.axes[0], np.broadcast_to(flex, (F,)))
        M[:, :3, 3] = spec.centre - M[:, :3, :3] @ spec.centre
        rest = np.linalg.solve(skeleton.bones[femur].bone_to_world, skeleton.bones[patella].bone_to_world)
        target = T[:, index[femur]] @ M @ rest
        _apply_subtree_correction(T, index, _subtree(skeleton, patella, kids), patella, target)
    for name, fs in table.forearms.items():
        if fs.radius not in index or fs.ulna not in index:
            continue
        theta = np.broadcast_to(np.asarray(twist.get(name, np.zeros(F)), float), (F,))
        M, A, B = forearm_motion(fs, theta)
        rest = np.linalg.solve(skeleton.bones[fs.ulna].bone_to_world, skeleton.bones[fs.radius].bone_to_world)
        U = T[:, index[fs.ulna]]
        target = U @ M @ rest
        _apply_subtree_correction(T, index, _subtree(skeleton, fs.radius, kids), fs.radius, target)
        extra[name] = {"theta": np.array(theta), "A_ulna": A, "B_ulna": B, "A_lab": _apply(U, A),
                       "B_lab": _apply(U, B)}
    return T, extra


def _world_to_lab(table: JointTable) -> np.ndarray:
    """Skeleton world -> lab at standing: anatomical axes onto the lab (X forward, Y left, Z up)."""
    W = np.eye(4)
    W[:3, :3] = table.anat.T   # world -> anatomical (X ant, Y up, Z right)
    return MODEL_TO_LAB_ZUP @ W


def _root_poses(skeleton: Skeleton, table: JointTable, motion: TrialMotion) -> np.ndarray:
    F = motion.n_frames
    W2L = _world_to_lab(table)
    c = table.pelvis_centre
    # pelvis rotation about its centre, in the world frame: tilt about -right, obliquity about
    # -anterior (right side up), rotation about +up (right side forward)
    a = np.radians(motion.pelvis)
    ax = table.anat
    R = _rotvec_matrices(-ax[:, 2], a[:, 0]) @ _rotvec_matrices(-ax[:, 0], a[:, 1]) \
        @ _rotvec_matrices(ax[:, 1], a[:, 2])
    P = np.tile(np.eye(4), (F, 1, 1))
    P[:, :3, :3] = R
    P[:, :3, 3] = c - R @ c
    G = np.tile(np.eye(4), (F, 1, 1))
    G[:, :3, 3] = motion.position - _apply(W2L, c)[None]
    return G @ W2L @ P @ skeleton.bones[table.root].bone_to_world


def _foot_points(skeleton: Skeleton, table: JointTable) -> dict[str, tuple[list[int], list[np.ndarray]]]:
    """Per side: bone indices and their points in each bone's own frame (floor contact)."""
    index = {n: i for i, n in enumerate(skeleton.names)}
    out = {}
    for s, bones in table.feet.items():
        idx, pts = [], []
        for b in bones:
            w = _world_points(skeleton, b, 600, hull=True)
            idx.append(index[b])
            pts.append(_apply(np.linalg.inv(skeleton.bones[b].bone_to_world), w))
        out[s] = (idx, pts)
    return out


def _sole_pad(skeleton: Skeleton, table: JointTable, skin: Mesh | None) -> float:
    """Thickness (mm) between the lowest foot-bone point and the floor at the reference pose."""
    if skin is None or not table.feet:
        return _NO_SKIN_PAD_MM
    up = table.anat[:, 1]
    bones = [b for bs in table.feet.values() for b in bs]
    low_bone = min(float((_world_points(skeleton, b, 600, hull=True) @ up).min()) for b in bones)
    low_skin = float((skin.vertices @ up).min())
    pad = low_bone - low_skin
    return pad if 0.0 <= pad <= 60.0 else _NO_SKIN_PAD_MM


def _lowest_points(T: np.ndarray, idx: Sequence[int], pts: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Each frame's lowest point of a foot: its index into ``concatenate(pts)`` and its lab height.

    Parameters
    ----------
    T : ndarray (F, B, 4, 4)
        Bone -> lab poses (Z-up lab, mm).
    idx : sequence of int
        The foot's bones (indices into ``T``'s second axis).
    pts : sequence of ndarray (P_i, 3)
        Their points in each bone's own frame (mm).

    Returns
    -------
    low : ndarray (F,) of int
    z_low : ndarray (F,)

    Notes
    -----
    Heights only, one bone at a time: the full (F, P, 3) lab positions took ~100 MB
    on the long trials, all the bones' heights at once ~110 MiB, the default
    phantom's peak. The first lowest point on ties, as one ``argmin`` over all the
    points would give.
    """
    frames = np.arange(T.shape[0])
    low = z_low = None
    first = 0
    for i, p in zip(idx, pts):
        Zi = p @ T[:, i, 2, :3].T + T[:, i, 2, 3]          # (P_i, F)
        j = np.argmin(Zi, axis=0)
        zj = Zi[j, frames]
        del Zi
        if low is None:
            low, z_low = j + first, zj
        else:
            lower = zj < z_low                          # strictly: an earlier bone wins a tie
            low, z_low = np.where(lower, j + first, low), np.where(lower, zj, z_low)
        first += len(p)
    return low, z_low


def pose_trial(skeleton: Skeleton, table: JointTable, motion: TrialMotion, *, skin: Mesh | None = None
               ) -> tuple[np.ndarray, dict[str, Any]]:
    """Bone poses of a trial in the Z-up lab, feet on the floor.

    Parameters
    ----------
    skeleton : Skeleton
        Reference pose in its world frame.
    table : JointTable
    motion : TrialMotion
    skin : Mesh, optional
        Skin at the reference pose (skeleton world frame): the sole thickness
        below the foot bones is measured on it (10 mm without).

    Returns
    -------
    transforms : ndarray (F, B, 4, 4)
        ``bone_to_lab`` (mm) for ``skeleton.names``.
    info : dict
        ``forearms`` (per forearm: ``theta``, axis ends ``A_ulna``/``B_ulna`` in the ulna frame and
        ``A_lab``/``B_lab`` in the lab), ``speed_mm_s`` and ``sole_pad_mm``.

    Notes
    -----
    Every frame is lifted so that the lowest foot point is ``pad`` above ``z = 0``
    (standing feet rest on the floor; in walking the stance foot does, which gives
    the pelvis its vertical excursion). For walking, the pelvis advances at the
    speed that keeps the supporting foot from sliding: minus the forward velocity,
    relative to the pelvis, of the centroid of the supporting foot (blended over
    double support), integrated; ``speed_mm_s`` is the mean.
    """
    root = _root_poses(skeleton, table, motion)
    T, forearms = _pose_core(skeleton, table, motion.angles, motion.twist, root)
    F = T.shape[0]
    pad = _sole_pad(skeleton, table, skin)
    feet = _foot_points(skeleton, table)
    speed = 0.0
    if feet:
        sides = list(feet)
        lows, contact_vx = [], []
        frames = np.arange(F)
        prev, nxt = np.maximum(frames - 1, 0), np.minimum(frames + 1, F - 1)
        for s in sides:
            idx, pts = feet[s]
            low, z_low = _lowest_points(T, idx, pts)
            lows.append(z_low)
            P_all = np.concatenate(pts)
            bone_of = np.concatenate([np.full(len(p), i) for i, p in zip(idx, pts)])
            P_low, b_low = P_all[low], bone_of[low]

            def x_at(g):                          # lab x of each frame's lowest point at frames g
                Tg = T[g, b_low, 0]               # (F, 4): first rows of the bones' poses
                return np.einsum("fj,fj->f", Tg[:, :3], P_low) + Tg[:, 3]

            # forward velocity of the material point of the foot that is lowest now (the
            # contact point when the foot is on the floor: zero for rolling without slipping)
            contact_vx.append((x_at(nxt) - x_at(prev)) / np.maximum(nxt - prev, 1) * RATE_HZ)
        lows = np.array(lows)
        # No foot may go below the floor and one always touches it. The gait curves are tuned so
        # that the lowest foot is the stance foot (swing clearance >= 0), so this is also "the
        # stance foot carries the body".
        ground = lows.min(axis=0)
        T[:, :, 2, 3] += (pad - ground)[:, None]
        if motion.walking and motion.support and F > 2:
            # The pelvis advances so that the supporting foot does not slide at its contact
            # point: its forward velocity is minus the support-weighted contact velocity.
            w = np.array([motion.support.get(s, np.zeros(F)) for s in sides])
            v = -(w * np.array(contact_vx)).sum(axis=0) / np.maximum(w.sum(axis=0), 1e-9)
            x = np.concatenate([[0.0], np.cumsum((v[1:] + v[:-1]) / 2)]) / RATE_HZ
            speed = float(x[-1] / max(motion.times[-1], 1e-9))
            x -= x[-1] / 2  # centre the walk on the lab origin
            T[:, :, 0, 3] += x[:, None]
    for name, d in forearms.items():
        # the lab positions of the axis ends were computed before the lift and progression
        i = skeleton.names.index(table.forearms[name].ulna)
        d["A_lab"] = _apply(T[:, i], d["A_ulna"])
        d["B_lab"] = _apply(T[:, i], d["B_ulna"])
    return T, {"forearms": forearms, "speed_mm_s": speed if motion.walking else 0.0, "sole_pad_mm": pad}


# ----------------------------------------------------------------------------------------------
# The touch trial: arm postures by inverse kinematics
# ----------------------------------------------------------------------------------------------

def _hand_point(skeleton: Skeleton, table: JointTable, side: str) -> tuple[str, np.ndarray]:
    """A mid-palm point, in the frame of the bone below the wrist: the centroid of the hand's bones."""
    hand = table.hands.get(side)
    if hand is None:
        fs = table.forearms.get(f"radioulnar_{side}")
        bone = fs.radius if fs else _find_bone(skeleton, "radius", side)
        pts = _world_points(skeleton, bone)
        c = pts[np.argmin(pts @ table.anat[:, 1])]
        return bone, _apply(np.linalg.inv(skeleton.bones[bone].bone_to_world), c)
    pts = np.concatenate([_world_points(skeleton, b, 300) for b in _subtree(skeleton, hand)])
    return hand, _apply(np.linalg.inv(skeleton.bones[hand].bone_to_world), pts.mean(axis=0))


def _arm_subskeleton(skeleton: Skeleton, bones: list[str]) -> Skeleton:
    keep: set[str] = set()
    for b in bones:
        while b is not None and b not in keep:
            keep.add(b)
            b = skeleton.bones[b].parent
    return Skeleton(bones={n: skeleton.bones[n] for n in skeleton.names if n in keep}, world=skeleton.world)


def _touch_poses(skeleton: Skeleton, table: JointTable, skin: Mesh | None) -> dict[str, dict[str, np.ndarray]]:
    """Shoulder (flex, abd, rot), elbow flexion and twist for rest, hands-together and hands-on-hips."""
    from scipy.optimize import least_squares        # (here, see _periodic)

    anat = table.anat
    up, right, ant = anat[:, 1], anat[:, 2], anat[:, 0]
    shoulders = {s: _apply(skeleton.bones[table.joints[f"shoulder_{s}"].parent].bone_to_world,
                           table.joints[f"shoulder_{s}"].centre)
                 for s in "rl" if f"shoulder_{s}" in table.joints}
    if not shoulders:
        return {"rest": {}, "front": {}, "hips": {}}
    hips = {s: _joint_centre_world(skeleton, table.joints[f"hip_{s}"].child)
            for s in "rl" if f"hip_{s}" in table.joints}
    mid_s = np.mean(list(shoulders.values()), axis=0)
    mid_h = np.mean(list(hips.values()), axis=0) if hips else mid_s - 500 * up
    trunk = float((mid_s - mid_h) @ up)  # ~ 500 mm for an adult
    front_centre = mid_s + 0.62 * trunk * ant - 0.55 * trunk * up
    # Lateral extent of the body beside the iliac crest: the pelvis bones + 65 mm (soft tissue
    # and half a hand), or, with a skin, the skin there + 20 mm. Skin farther out than the bones
    # + 120 mm is an arm (abducted in the MRI pose), not the hip.
    crest = mid_h + 0.2 * trunk * up
    # the pelvis region: the root and its children that no table joint moves (hip bones, sacrum)
    moved = {j.child for j in table.joints.values()}
    pelvis_bones = [table.root] + [b for b in skeleton.names
                                   if skeleton.bones[b].parent == table.root and b not in moved]
    pts = np.concatenate([_world_points(skeleton, b) for b in pelvis_bones] or [crest[None]])
    bone_half = float(np.abs((pts - crest) @ right).max())
    half = bone_half + 65.0
    if skin is not None:
        v = skin.vertices
        lateral = np.abs((v - crest) @ right)
        near = (np.abs((v - crest) @ up) < 40) & (np.abs((v - crest) @ ant) < 80) & (lateral < bone_half + 120)
        if near.any():
            half = float(lateral[near].max()) + 20.0
    out: dict[str, dict[str, np.ndarray]] = {"rest": {}, "front": {}, "hips": {}}
    for s, sign in (("r", 1), ("l", -1)):
        if f"shoulder_{s}" not in table.joints or f"elbow_{s}" not in table.joints:
            continue
        hand_bone, hand_local = _hand_point(skeleton, table, s)
        fs = table.forearms.get(f"radioulnar_{s}")
        sub = _arm_subskeleton(skeleton, [hand_bone] + ([fs.radius, fs.ulna] if fs else []))
        i_hand = sub.names.index(hand_bone)
        root_T = skeleton.bones[sub.names[0]].bone_to_world

        def hand_at(X, twist, s=s, sub=sub, i_hand=i_hand, root_T=root_T, hand_local=hand_local):
            """Mid-palm points (n, 3), world frame, for arm postures X (n, 4); one batched pose."""
            X = np.atleast_2d(X)
            n = len(X)
            ang = {f"shoulder_{s}": X[:, :3], f"elbow_{s}": np.stack([X[:, 3], 0 * X[:, 3], 0 * X[:, 3]], 1)}
            T, _ = _pose_core(sub, table, ang, {f"radioulnar_{s}": np.full(n, twist)},
                              np.broadcast_to(root_T, (n, 4, 4)))
            return _apply(T[:, i_hand], hand_local)

        targets = {"front": (front_centre + sign * 22.0 * right, 90.0, np.array([45.0, 0.0, 30.0, 90.0])),
                   "hips": (crest + sign * half * right, 100.0, np.array([0.0, 40.0, 0.0, 100.0]))}
        out["rest"][s] = np.array([0.0, 5.0, 0.0, 10.0, 80.0])
        for key, (target, twist, prior) in targets.items():
            def resid(x, target=target, twist=twist, prior=prior):
                return np.concatenate([hand_at(x, twist)[0] - target, 0.3 * (x - prior)])

            def jac(x, target=target, twist=twist):
                # forward differences, the 4 perturbed postures in one batched pose
                h = 1e-3
                P = hand_at(np.vstack([x, x + h * np.eye(4)]), twist)
                J = np.zeros((7, 4))
                J[:3] = ((P[1:] - P[0]) / h).T
                J[3:] = 0.3 * np.eye(4)
                return J
            sol = least_squares(resid, prior, jac=jac, bounds=([-60, -40, -90, 0], [160, 160, 90, 145]),
                                x_scale=10.0)
            out[key][s] = np.concatenate([sol.x, [twist]])
    return out


# ----------------------------------------------------------------------------------------------
# Markers on the skin and their binding
# ----------------------------------------------------------------------------------------------

@dataclass
class MarkerBinding:
    """Markers stuck on the subject at the reference pose.

    Attributes
    ----------
    names : list of str
    bones : list of str
        Bone each marker is bound to (the first of its ``tracks``).
    local : ndarray (M, 3)
        Marker centre in that bone's frame (mm): the true binding.
    world : ndarray (M, 3)
        Marker centre in the skeleton world frame at the reference pose.
    method : list of str
        ``"skin_ray"`` (ray from the landmark to the skin, + radius), ``"skin_nearest"``,
        ``"bone_offset"`` (:func:`~bonecap.markers.place_markers`, no skin) or ``"location"``.
    """

    names: list[str]
    bones: list[str]
    local: np.ndarray
    world: np.ndarray
    method: list[str]


def _skin_normals(tm, tri: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Vertex normals interpolated at ``points`` on triangles ``tri`` (smoother than face normals)."""
    import trimesh

    bary = trimesh.triangles.points_to_barycentric(tm.triangles[tri], points)
    vn = tm.vertex_normals[tm.faces[tri]]  # (n, 3, 3)
    n = np.einsum("nk,nki->ni", bary, vn)
    bad = ~np.isfinite(n).all(axis=1) | (np.linalg.norm(n, axis=1) < 1e-6)
    n[bad] = tm.face_normals[tri[bad]]
    return _unit(n)


def _place_on_bones(marker_set: MarkerSet, skeleton: Skeleton, names: list[str]) -> np.ndarray:
    """:func:`~bonecap.markers.place_markers` as an (M, 3) array, world frame (model, mm)."""
    from bonecap.markers import place_markers

    placed = place_markers(marker_set, skeleton, list(names))
    return np.array([placed[n] for n in names], dtype=float).reshape(len(names), 3)


def place_phantom_markers(marker_set: MarkerSet, skeleton: Skeleton, skin: Mesh | None = None, *,
                          names: list[str] | None = None, marker_radius_mm: float = 7.0,
                          max_ray_mm: float = 120.0) -> MarkerBinding:
    """Place a marker set's physical markers on the subject at the reference pose and bind them.

    Parameters
    ----------
    marker_set : MarkerSet
        Landmark-defined (Plug-in Gait, the paper's set) or location-defined (an OpenSim MarkerSet).
    skeleton : Skeleton
        Reference pose, world frame.
    skin : Mesh, optional
        The subject's skin at the reference pose, in the **skeleton world frame**. With it, each
        landmark marker sits on the skin above its landmark: a ray is cast from the landmark along
        the direction :func:`~bonecap.markers.place_markers` pushes it off the bone (the bone
        surface normal), and the marker centre is the first skin crossing plus ``marker_radius_mm``
        along the skin normal. A missed ray (or one longer than ``max_ray_mm``) falls back to the
        skin point nearest the bone-offset position. Location markers go to the nearest skin point
        plus the radius. Without a skin, the markers are where
        :func:`~bonecap.markers.place_markers` puts them (bone surface + the set's soft-tissue
        offset; it is called here).
    names : list of str, optional
        Default: ``marker_set.physical`` (no virtual, no optional markers).
    marker_radius_mm : float
        Half the marker diameter (14 mm markers).

    Returns
    -------
    MarkerBinding
    """
    check_marker_set(marker_set, skeleton)
    names = list(names) if names is not None else list(marker_set.physical)
    world = _place_on_bones(marker_set, skeleton, names).reshape(-1, 3)
    method = ["location" if marker_set.markers[n].location is not None else "bone_offset" for n in names]
    if skin is not None and len(names):
        tm = skin.to_trimesh()
        for i, n in enumerate(names):
            m = marker_set.markers[n]
            bone = skeleton.bones[m.bone]
            hit = None
            if m.location is None:
                L = bone.landmark_in_world(m.landmark)
                d = world[i] - L
                if np.linalg.norm(d) < 1e-6:
                    centre = _apply(bone.bone_to_world, bone.mesh.vertices.mean(axis=0)) \
                        if bone.mesh is not None else bone.bone_to_world[:3, 3]
                    d = L - centre
                d = _unit(d)
                locs, _, tri = tm.ray.intersects_location(L[None], d[None], multiple_hits=True)
                if len(locs):
                    dist = (locs - L) @ d
                    ok = dist > 1e-6
                    if ok.any():
                        j = np.flatnonzero(ok)[np.argmin(dist[ok])]
                        nrm = _skin_normals(tm, tri[j:j + 1], locs[j:j + 1])[0]
                        if dist[j] <= max_ray_mm and nrm @ d > 0:
                            hit = (locs[j], nrm, "skin_ray")
            if hit is None:
                closest, _, tri = tm.nearest.on_surface(world[i][None])
                nrm = _skin_normals(tm, tri, closest)[0]
                hit = (closest[0], nrm, "skin_nearest")
            world[i] = hit[0] + marker_radius_mm * hit[1]
            method[i] = hit[2] if m.location is None else "skin_nearest_location"
        # The interpolated normal is not exactly the direction to the nearest skin point on a
        # coarse or bumpy mesh: a few projections put every marker at one radius from the skin
        # (the marker rests on it) without moving it off its landmark by more than a fraction of
        # a millimetre.
        for _ in range(4):
            q, dist, tri = tm.nearest.on_surface(world)
            away = _unit(world - q)
            inward = np.einsum("ij,ij->i", away, tm.face_normals[tri]) <= 0
            away[inward] = tm.face_normals[tri[inward]]
            world = q + marker_radius_mm * away
    bones, local = [], []
    for i, n in enumerate(names):
        m = marker_set.markers[n]
        b = next((t for t in m.tracks if t in skeleton.bones), m.bone)
        bones.append(b)
        local.append(_apply(np.linalg.inv(skeleton.bones[b].bone_to_world), world[i]))
    return MarkerBinding(names=names, bones=bones, local=np.array(local).reshape(-1, 3), world=world,
                         method=method)


# ----------------------------------------------------------------------------------------------
# Soft-tissue artefact
# ----------------------------------------------------------------------------------------------

_CLASS_PATTERNS = (
    ("thigh", ("THI", "TH1", "TH2", "TH3", "TH4", "THIGH")),
    ("shank", ("TIB", "TB1", "TB2", "TB3", "TB4", "SHANK", "SHN")),
    ("upper_arm", ("UPA", "UA1", "UA2", "UA3", "UA4", "SHA", "SHP", "ASH", "PSH", "ELA", "UPPERARM")),
    ("forearm", ("FRM", "FA", "FOREARM")),
    ("bony", ("ASI", "PSI", "SACR", "KNE", "LFC", "MFC", "LFE", "MFE", "ANK", "MAL", "LMAL", "MMAL", "HEE",
              "CAL", "TOE", "MT", "ELB", "LEL", "MEL", "MEP", "EPL", "EPM", "ELP", "WRA", "WRB", "WRR", "WRU",
              "RSP", "USP", "STY", "FIN", "IPIP", "IDIP", "RPIP", "RDIP", "PIP", "DIP", "MH", "FHD", "BHD",
              "FH", "BH", "C7", "T10", "T8", "CLAV", "STRN", "IJ", "PX", "SHO", "ACR")),
)
_BONE_CLASSES = (("femur", "thigh"), ("tibia", "shank"), ("fibula", "shank"), ("humerus", "upper_arm"),
                 ("radius", "forearm"), ("ulna", "forearm"), ("scapula", "soft"))


def sta_class(marker: str, bone: str) -> str:
    """The soft-tissue class of a marker: ``thigh``, ``upper_arm``, ``shank``, ``forearm``, ``soft``
    or ``bony``.

    Parameters
    ----------
    marker : str
        Label; a leading side letter (``R``/``L``, optionally with ``_`` or ``.``) is dropped and the
        rest matched against Plug-in Gait / the paper's / OpenSim-style names (``RTHI``, ``RTH2``,
        ``RUA1``, ``RFAradius``, ``RLMAL``...). Matching is on the beginning of the name.
    bone : str
        Bone the marker is bound to: decides when the name does not (femur -> thigh, tibia and
        fibula -> shank, humerus -> upper arm, radius and ulna -> forearm, scapula -> soft,
        anything else -> bony).

    Returns
    -------
    str
    """
    base = marker.upper().replace(" ", "")
    stripped = base[1:].lstrip("_.") if len(base) > 2 and base[0] in "RL" else base
    for candidate in (stripped, base):
        for cls, pats in _CLASS_PATTERNS:
            if any(candidate.startswith(p) for p in pats):
                return cls
    low = bone.lower()
    for key, cls in _BONE_CLASSES:
        if key in low:
            return cls
    return "bony"


@dataclass
class SoftTissueModel:
    """Kinematics-driven soft-tissue artefact of each marker (module documentation, [3]).

    Attributes
    ----------
    markers, bones, classes : list of str
        Per marker: name, bone it is bound to, STA class.
    amplitude_mm : ndarray (M,)
        Peak displacement bound per marker (class amplitude x ``sta_scale``).
    rigid_fraction : ndarray (M,)
        Share of the bound given to its cluster's rigid motion (0.6-0.8).
    clusters : list of tuple
        Per marker, its cluster key ``(bone, class)``.
    dofs : list of tuple (str, int)
        The angle variables: ``(joint, component)`` with component 0-2 for table joints,
        ``(forearm, 0)`` for a pronation angle, ``("pelvis", k)`` for the pelvis angles.
    centre_deg, range_deg : ndarray (K,)
        Normalisation: ``s = sin(pi/2 clip((q - centre) / range, -1, 1))``.
    rigid, nonrigid : ndarray (M, K, 2, 3)
        Coefficients (bone frame, mm) of ``s`` and ``s**2`` for the rigid and the non-rigid parts.
    """

    markers: list[str]
    bones: list[str]
    classes: list[str]
    amplitude_mm: np.ndarray
    rigid_fraction: np.ndarray
    clusters: list[tuple[str, str]]
    dofs: list[tuple[str, int]]
    centre_deg: np.ndarray
    range_deg: np.ndarray
    rigid: np.ndarray
    nonrigid: np.ndarray

    def dof_values(self, motion: TrialMotion) -> np.ndarray:
        """The angle variables (F, K) in degrees for a trial motion."""
        F = motion.n_frames
        out = np.zeros((F, len(self.dofs)))
        for k, (name, comp) in enumerate(self.dofs):
            if name in motion.angles:
                out[:, k] = motion.angles[name][:, comp]
            elif name in motion.twist:
                out[:, k] = motion.twist[name]
            elif name == "pelvis":
                out[:, k] = motion.pelvis[:, comp]
        return out

    def displacement(self, q_deg: np.ndarray, part: str = "total") -> np.ndarray:
        """STA of every marker in its bone's frame, (F, M, 3) mm.

        Parameters
        ----------
        q_deg : ndarray (F, K)
            From :meth:`dof_values`.
        part : {"total", "rigid", "nonrigid"}
            ``"total"`` is ``rigid + nonrigid``, softly saturated so that its norm never exceeds
            ``amplitude_mm`` (the saturation only acts in poses beyond those the gains were
            calibrated on: there the sum is already within the bound).

        Returns
        -------
        ndarray (F, M, 3)
        """
        u = np.clip((np.asarray(q_deg, float) - self.centre_deg) / self.range_deg, -1.0, 1.0)
        s = np.sin(np.pi / 2 * u)
        basis = np.stack([s, s * s], axis=-1)  # (F, K, 2)
        coef = {"total": self.rigid + self.nonrigid, "rigid": self.rigid, "nonrigid": self.nonrigid}[part]
        F, K = s.shape
        d = (basis.reshape(F, 2 * K) @ coef.transpose(1, 2, 0, 3).reshape(2 * K, -1)).reshape(F, -1, 3)
        if part == "total":
            d = _saturate(d, self.amplitude_mm)
        return d


def _saturate(d: np.ndarray, bound: np.ndarray, knee: float = 0.9) -> np.ndarray:
    """Scale vectors ``d`` (..., M, 3) so their norm stays below ``bound`` (M,): identity up to
    ``knee * bound``, then a tanh roll-off (continuous with continuous slope)."""
    r = np.linalg.norm(d, axis=-1)
    b = np.broadcast_to(np.asarray(bound, float), r.shape)
    r0 = knee * b
    w = np.maximum(b - r0, 1e-12)
    over = r > r0
    if not over.any():
        return d
    target = np.where(over, r0 + w * np.tanh((r - r0) / w), r)
    scale = np.where(over & (r > 0), target / np.maximum(r, 1e-12), 1.0)
    return d * scale[..., None]


def _segment_heads(skeleton: Skeleton, table: JointTable) -> set[str]:
    heads = {j.child for j in table.joints.values()} | {f.radius for f in table.forearms.values()}
    heads.add(table.root)
    return heads


def _segment_of(skeleton: Skeleton, heads: set[str], bone: str) -> str:
    b = bone
    while b not in heads:
        parent = skeleton.bones[b].parent
        if parent is None:
            return b
        b = parent
    return b


def _segment_dofs(skeleton: Skeleton, table: JointTable, heads: set[str], seg: str) -> list[tuple[str, int]]:
    """The angle variables next to a segment: its own joint, the joints it carries, and for the
    forearm bones the elbow, the pronation and the wrist."""
    out: list[tuple[str, int]] = []
    for name, j in table.joints.items():
        if j.child == seg or _segment_of(skeleton, heads, j.parent) == seg:
            out += [(name, 0), (name, 1), (name, 2)]
    for name, f in table.forearms.items():
        if seg in (f.radius, f.ulna):
            out.append((name, 0))
            for jn, j in table.joints.items():
                if (j.child == f.ulna or j.parent == f.radius) and (jn, 0) not in out:
                    out += [(jn, 0), (jn, 1), (jn, 2)]
    if not out:
        out = [("pelvis", 0), ("pelvis", 1), ("pelvis", 2)]
    return out


def build_sta_model(binding: MarkerBinding, table: JointTable, skeleton: Skeleton, seed: int = 0, *,
                    sta_scale: float = 1.0, amplitudes: Mapping[str, float] | None = None,
                    classes: Mapping[str, str] | None = None, rigid_fraction: tuple[float, float] = (0.6, 0.8)
                    ) -> SoftTissueModel:
    """Draw the soft-tissue artefact model of a marker binding.

    Parameters
    ----------
    binding : MarkerBinding
    table : JointTable
    skeleton : Skeleton
    seed : int
        The same seed gives the same coefficients.
    sta_scale : float
        Multiplies every amplitude (0 disables the artefact).
    amplitudes : mapping, optional
        Class -> peak mm, overriding :data:`STA_AMPLITUDE_MM`.
    classes : mapping, optional
        Marker -> class, overriding :func:`sta_class`.
    rigid_fraction : (low, high)
        Range of the rigid share per cluster (>= 0.5, see [3]-[6]).

    Returns
    -------
    SoftTissueModel
    """
    if sta_scale < 0:
        raise InputError(f"sta_scale must be >= 0, got {sta_scale}")
    if not 0.5 <= rigid_fraction[0] <= rigid_fraction[1] <= 1.0:
        raise InputError(f"rigid_fraction must lie in [0.5, 1], got {rigid_fraction}")
    amp_table = dict(STA_AMPLITUDE_MM)
    amp_table.update(amplitudes or {})
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x57A]))
    heads = _segment_heads(skeleton, table)
    M = len(binding.names)
    cls = [(classes or {}).get(n) or sta_class(n, b) for n, b in zip(binding.names, binding.bones)]
    amp = np.array([amp_table[c] * sta_scale for c in cls])
    # angle variables: all the segments' neighbours, in a fixed order
    seg_dofs = {}
    dofs: list[tuple[str, int]] = []
    for b in binding.bones:
        seg = _segment_of(skeleton, heads, b)
        if seg not in seg_dofs:
            seg_dofs[seg] = _segment_dofs(skeleton, table, heads, seg)
            for d in seg_dofs[seg]:
                if d not in dofs:
                    dofs.append(d)
    K = len(dofs)
    centre = np.zeros(K)
    rng_deg = np.ones(K)
    for k, (name, comp) in enumerate(dofs):
        if name in table.forearms:
            centre[k], rng_deg[k] = 90.0, 90.0
        else:
            kind = table.joints[name].kind if name in table.joints else "pelvis"
            rng_deg[k] = _STA_RANGES[kind][comp]
    rigid = np.zeros((M, K, 2, 3))
    nonrigid = np.zeros((M, K, 2, 3))
    rho = np.zeros(M)

    def draw(bound: float, ks: list[int]) -> np.ndarray:
        """Coefficients (K, 2, 3) whose norms sum to ``bound`` over the variables ``ks``."""
        out = np.zeros((K, 2, 3))
        if bound <= 0 or not ks:
            return out
        w = rng.dirichlet(np.ones(len(ks)))
        lam = rng.uniform(0.4, 0.9, len(ks))
        for k, wk, lk in zip(ks, w, lam):
            out[k, 0] = bound * wk * lk * _unit(rng.normal(size=3))
            out[k, 1] = bound * wk * (1 - lk) * _unit(rng.normal(size=3))
        return out

    # Calibration poses: the standard trials' joint angles (no skeleton needed). Each part is
    # scaled so that its peak over these poses is its share of the amplitude, so the artefact
    # reaches its bound in the trial that moves the segment most (a worst-case normalisation
    # alone would leave it at a fraction of the bound in real motions). Angle variables that
    # never move get no coefficient.
    calib = [trial_motion(n, table) for n in ("static", "walk", "arm_raise", "pronation")]
    partial = SoftTissueModel(markers=[], bones=[], classes=[], amplitude_mm=np.zeros(0),
                              rigid_fraction=np.zeros(0), clusters=[], dofs=dofs, centre_deg=centre,
                              range_deg=rng_deg, rigid=np.zeros((0, K, 2, 3)), nonrigid=np.zeros((0, K, 2, 3)))
    q = np.concatenate([partial.dof_values(m) for m in calib])
    s_cal = np.sin(np.pi / 2 * np.clip((q - centre) / rng_deg, -1.0, 1.0))
    basis_cal = np.stack([s_cal, s_cal * s_cal], axis=-1)  # (Fc, K, 2)
    moving = np.abs(s_cal).max(axis=0) > 1e-3

    def peak(coef: np.ndarray) -> float:
        return float(np.linalg.norm(basis_cal.reshape(len(basis_cal), -1) @ coef.reshape(-1, 3), axis=1).max())

    cluster_keys = [(b, c) for b, c in zip(binding.bones, cls)]
    for key in dict.fromkeys(cluster_keys):
        members = [i for i, ck in enumerate(cluster_keys) if ck == key]
        seg = _segment_of(skeleton, heads, key[0])
        ks = [dofs.index(d) for d in seg_dofs[seg]]
        ks = [k for k in ks if moving[k]] or ks
        A = float(amp[members[0]])
        r = float(rng.uniform(*rigid_fraction))
        p = binding.local[members]
        centroid = p.mean(axis=0)
        rmax = float(np.linalg.norm(p - centroid, axis=1).max())
        beta = 0.4 if (len(members) > 1 and rmax >= 10.0) else 0.0
        tau = draw(r * A * (1 - beta), ks)
        omega = draw(r * A * beta / rmax, ks) if beta else np.zeros((K, 2, 3))
        rig = [tau + np.cross(omega, binding.local[i] - centroid) for i in members]
        top = max(peak(c) for c in rig)
        gain = min(r * A / top, _MAX_STA_GAIN) if top > 0 else 0.0
        for i, c in zip(members, rig):
            rigid[i] = gain * c
            nr = draw((1 - r) * A, ks)
            top = peak(nr)
            nonrigid[i] = nr * (min((1 - r) * A / top, _MAX_STA_GAIN) if top > 0 else 0.0)
            rho[i] = r
    return SoftTissueModel(markers=list(binding.names), bones=list(binding.bones), classes=cls, amplitude_mm=amp,
                           rigid_fraction=rho, clusters=cluster_keys, dofs=dofs, centre_deg=centre,
                           range_deg=rng_deg, rigid=rigid, nonrigid=nonrigid)


# ----------------------------------------------------------------------------------------------
# Trials
# ----------------------------------------------------------------------------------------------

@dataclass
class PhantomTrial:
    """One synthetic trial and its truth (everything in the lab frame, mm).

    Attributes
    ----------
    name : str
    times : ndarray (F,)
    bones : list of str
    transforms : ndarray (F, B, 4, 4)
        True ``bone_to_lab``.
    markers : list of str
    marker_truth : ndarray (F, M, 3)
        Markers rigidly carried by their bones (no artefact, no noise, no gaps).
    sta : ndarray (F, M, 3)
        Soft-tissue displacement added (lab frame).
    noise : ndarray (F, M, 3)
    points : ndarray (F, M, 3)
        What the C3D holds: ``marker_truth + sta + noise`` with NaN in the gaps.
    gaps : list of tuple (int, int, int)
        ``(marker index, first frame, length)``.
    joint_names, joint_child, joint_parent : list of str
    joint_centres : ndarray (F, J, 3)
        Centres of the joints, carried by the child bone.
    motion : TrialMotion
    info : dict
        From :func:`pose_trial`.
    """

    name: str
    times: np.ndarray
    bones: list[str]
    transforms: np.ndarray
    markers: list[str]
    marker_truth: np.ndarray
    sta: np.ndarray
    noise: np.ndarray
    points: np.ndarray
    gaps: list[tuple[int, int, int]]
    joint_names: list[str]
    joint_child: list[str]
    joint_parent: list[str]
    joint_centres: np.ndarray
    motion: TrialMotion
    info: dict[str, Any]


def _joint_list(skeleton: Skeleton) -> tuple[list[str], list[str], list[str], list[np.ndarray]]:
    """Every joint centre a bone shares with its parent: (labels, child, parent, centre in child).

    Labels are the joint names, suffixed ``:child`` where a name is used by several bones
    (the generic skeleton names both hips ``hip``)."""
    raw = []
    for n in skeleton.names:
        b = skeleton.bones[n]
        if b.parent is None:
            continue
        parent = skeleton.bones[b.parent]
        for j in sorted(set(b.joint_centres) & set(parent.joint_centres)):
            raw.append((j, n, b.parent, b.joint_centres[j]))
    counts: dict[str, int] = {}
    for j, *_ in raw:
        counts[j] = counts.get(j, 0) + 1
    names = [j if counts[j] == 1 else f"{j}:{child}" for j, child, _, _ in raw]
    return names, [r[1] for r in raw], [r[2] for r in raw], [r[3] for r in raw]


def _rng(seed: int, trial: str, purpose: str) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([int(seed), zlib.crc32(trial.encode()),
                                                         zlib.crc32(purpose.encode())]))


def _gaps_for(trial: str, n_gaps: int | Mapping[str, int], gap_frames: int, F: int, M: int, seed: int
              ) -> list[tuple[int, int, int]]:
    if isinstance(n_gaps, Mapping):
        n = int(n_gaps.get(trial, 0))
    else:
        n = 0 if trial == "static" else int(n_gaps)
    length = int(min(gap_frames, max(F - 2, 0)))
    if n <= 0 or length <= 0 or M == 0:
        return []
    rng = _rng(seed, trial, "gaps")
    markers = rng.choice(M, size=n, replace=n > M)
    # gaps start after the first frame and end before the last one
    starts = rng.integers(1, max(F - length, 2), size=n)
    return [(int(m), int(s), length) for m, s in zip(markers, starts)]


def synthesize_trials(skeleton: Skeleton, marker_set: MarkerSet, *, skin: Mesh | None = None, seed: int = 0,
                      trials: Sequence[str] = TRIAL_NAMES, duration_scale: float = 1.0, sta_scale: float = 1.0,
                      noise_mm: float = 0.5, gap_frames: int = 20, n_gaps: int | Mapping[str, int] = 3,
                      marker_radius_mm: float = 7.0, sta_amplitudes: Mapping[str, float] | None = None
                      ) -> tuple[list[PhantomTrial], MarkerBinding, SoftTissueModel, JointTable]:
    """The trials of :func:`make_trials`, in memory (same arguments, no files).

    Returns
    -------
    trials : list of PhantomTrial
    binding : MarkerBinding
    sta_model : SoftTissueModel
    table : JointTable
    """
    _check_trial_args(noise_mm, gap_frames)
    ctx = _TrialContext(skeleton, marker_set, skin=skin, seed=seed, trials=trials, sta_scale=sta_scale,
                        marker_radius_mm=marker_radius_mm, sta_amplitudes=sta_amplitudes)
    out = [ctx.trial(name, duration_scale=duration_scale, noise_mm=noise_mm, gap_frames=gap_frames, n_gaps=n_gaps)
           for name in trials]
    return out, ctx.binding, ctx.sta_model, ctx.table


class _TrialContext:
    """What every trial of one subject shares (joint table, marker binding, artefact model), and
    :meth:`trial` to make one trial: :func:`make_trials` makes, writes and drops them one at a
    time (all trials at the default preset hold ~100 MB of poses), :func:`synthesize_trials`
    keeps them. Each trial draws from its own seeded streams, so the two give the same trials."""

    def __init__(self, skeleton: Skeleton, marker_set: MarkerSet, *, skin: Mesh | None, seed: int,
                 trials: Sequence[str], sta_scale: float, marker_radius_mm: float,
                 sta_amplitudes: Mapping[str, float] | None) -> None:
        unknown = [t for t in trials if t not in TRIAL_NAMES]
        if unknown:
            raise InputError(f"unknown trials {unknown} (known: {', '.join(TRIAL_NAMES)})")
        self.skeleton, self.skin, self.seed = skeleton, skin, seed
        self.table = joint_table(skeleton)
        self.binding = place_phantom_markers(marker_set, skeleton, skin, marker_radius_mm=marker_radius_mm)
        self.sta_model = build_sta_model(self.binding, self.table, skeleton, seed, sta_scale=sta_scale,
                                         amplitudes=sta_amplitudes)
        self.names = skeleton.names
        index = {n: i for i, n in enumerate(self.names)}
        self.mb = np.array([index[b] for b in self.binding.bones], int)
        self.j_names, self.j_child, self.j_parent, j_local = _joint_list(skeleton)
        self.j_idx = np.array([index[c] for c in self.j_child], int)
        self.j_local = np.array(j_local).reshape(-1, 3)

    def trial(self, name: str, *, duration_scale: float, noise_mm: float, gap_frames: int,
              n_gaps: int | Mapping[str, int]) -> PhantomTrial:
        skeleton, skin, seed, binding = self.skeleton, self.skin, self.seed, self.binding
        motion = trial_motion(name, self.table, duration_scale=duration_scale, skeleton=skeleton, skin=skin)
        T, info = pose_trial(skeleton, self.table, motion, skin=skin)
        F, M = motion.n_frames, len(binding.names)
        Tm = T[:, self.mb]  # (F, M, 4, 4)
        truth = _apply(Tm, np.broadcast_to(binding.local, (F, M, 3)))
        d_local = self.sta_model.displacement(self.sta_model.dof_values(motion))
        sta = (Tm[..., :3, :3] @ d_local[..., None])[..., 0]
        del Tm
        noise = _rng(seed, name, "noise").normal(0.0, noise_mm, (F, M, 3)) if noise_mm > 0 else np.zeros((F, M, 3))
        points = truth + sta + noise
        gaps = _gaps_for(name, n_gaps, gap_frames, F, M, seed)
        for m, s, n in gaps:
            points[s:s + n, m] = np.nan
        j_idx = self.j_idx
        jc = (_apply(T[:, j_idx], np.broadcast_to(self.j_local, (F, len(j_idx), 3))) if len(j_idx)
              else np.zeros((F, 0, 3)))
        return PhantomTrial(name=name, times=motion.times, bones=list(self.names), transforms=T,
                            markers=list(binding.names), marker_truth=truth, sta=sta, noise=noise,
                            points=points, gaps=gaps, joint_names=self.j_names, joint_child=self.j_child,
                            joint_parent=self.j_parent, joint_centres=jc, motion=motion, info=info)


def _check_trial_args(noise_mm: float, gap_frames: int) -> None:
    if noise_mm < 0:
        raise InputError(f"noise_mm must be >= 0, got {noise_mm}")
    if gap_frames < 0:
        raise InputError(f"gap_frames must be >= 0, got {gap_frames}")


def _write_npz(path: Path, arrays: dict[str, Any]) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)


def _truth_arrays(tr: PhantomTrial, table: JointTable, binding: MarkerBinding) -> dict[str, Any]:
    F = len(tr.times)
    arrays: dict[str, Any] = {
        "bones": np.array(tr.bones), "times": tr.times, "first_frame": np.array(1),
        "transforms": tr.transforms, "valid": np.ones((F, len(tr.bones)), bool),
        "joint_names": np.array(tr.joint_names), "joint_child": np.array(tr.joint_child),
        "joint_parent": np.array(tr.joint_parent), "joint_centres": tr.joint_centres,
        "markers": np.array(tr.markers), "marker_bones": np.array(binding.bones), "marker_local": binding.local,
        "marker_truth": tr.marker_truth, "sta": tr.sta,
        "noise": tr.noise,
        "gaps": np.array(tr.gaps, dtype=int).reshape(-1, 3),
        "joint_angle_names": np.array(list(tr.motion.angles)),
        "joint_angles_deg": np.stack([tr.motion.angles[j] for j in tr.motion.angles], 1)
        if tr.motion.angles else np.zeros((F, 0, 3)),
        "pelvis_angles_deg": tr.motion.pelvis,
        "sliding_joints": np.array(_sliding_joints(tr, table)),
        "rate": np.array(RATE_HZ),
    }
    forearms = tr.info["forearms"]
    for name, d in forearms.items():
        s = name[-1]
        arrays[f"forearm_twist_deg_{s}"] = d["theta"]
        arrays[f"radioulnar_axis_lab_{s}"] = np.stack([d["A_lab"], d["B_lab"]], 1)
        arrays[f"radioulnar_axis_ulna_{s}"] = np.stack([d["A_ulna"], d["B_ulna"]], 1)
    main = "radioulnar_r" if "radioulnar_r" in forearms else next(iter(forearms), None)
    arrays["forearm_twist_deg"] = forearms[main]["theta"] if main else np.zeros(F)
    return arrays


def _sliding_joints(tr: PhantomTrial, table: JointTable) -> list[str]:
    """Joint centres that by design do not stay together: the radius's and the patella's joints."""
    moved = {f.radius for f in table.forearms.values()} | {p for p, _ in table.patellae.values()}
    return [n for n, c in zip(tr.joint_names, tr.joint_child) if c in moved]


#: A calliper's error on a joint width (mm, standard deviation): repeated knee and ankle widths by trained
#: examiners differ by 1-3 mm (McGinley et al. 2009 report the marker placement they feed as the largest
#: error of clinical gait analysis; Plug-in Gait's manual asks for the width to the millimetre).
WIDTH_ERROR_MM = 2.0


def measured_joint_widths(skeleton: Skeleton, skin: Mesh, marker_set: MarkerSet, *, seed: int = 0,
                          marker_radius_mm: float = 7.0, error_mm: float = WIDTH_ERROR_MM) -> dict[str, float]:
    """The joint widths a gait lab measures with callipers, as Nexus stores them (C3D ``PROCESSING``).

    For every marker whose set gives ``width: {parameter, joint}``
    (:attr:`bonecap.markers.MarkerDef.width`: Plug-in Gait's knee and ankle
    widths), the width of the skin across the joint along the joint's
    axis through its centre -- the line the Plug-in Gait manual tells the
    examiner to measure along -- plus a calliper's error (``error_mm``
    standard deviation, its own random stream of ``seed`` so the rest of
    the phantom does not change with it), rounded to the millimetre as
    examiners write it. ``MarkerDiameter`` is the markers'.

    Parameters
    ----------
    skeleton : Skeleton
        The subject at the reference pose (the skin's frame).
    skin : Mesh
        The skin at that pose.
    marker_set : MarkerSet
    seed : int
    marker_radius_mm : float
    error_mm : float

    Returns
    -------
    dict of str -> float
        ``{parameter: width_mm}`` plus ``MarkerDiameter``; a joint whose
        axis does not meet the skin on both sides within 150 mm is left out.
    """
    import trimesh

    from bonecap.markers import joint_centre_axis

    if not error_mm >= 0:
        raise ValueError(f"error_mm must be >= 0, got {error_mm}")
    rng = np.random.default_rng([int(seed), 0x77696474])        # "widt": a stream of its own
    V, F = np.asarray(skin.vertices, float), np.asarray(skin.faces)
    centroids = V[F].mean(axis=1)
    out: dict[str, float] = {}
    for name in sorted(marker_set.markers):
        m = marker_set.markers[name]
        if m.width is None or m.bone not in skeleton.bones:
            continue
        try:
            centre, axis = joint_centre_axis(skeleton, m.bone, m.width[1])
        except ValueError:
            continue
        near = np.linalg.norm(centroids - centre, axis=1) < 150.0
        if not near.any():
            continue
        local = trimesh.Trimesh(V, F[near], process=False)
        hits = []
        for d in (axis, -axis):
            loc, _, _ = local.ray.intersects_location(centre[None], d[None])
            t = (loc - centre) @ d
            t = t[t > 0]
            hits.append(float(t.min()) if t.size else np.nan)
        if not np.isfinite(hits).all():
            continue
        out[m.width[0]] = float(np.round(sum(hits) + rng.normal(0.0, error_mm)))
    if out:
        out["MarkerDiameter"] = 2.0 * float(marker_radius_mm)
    return out


def make_trials(skeleton: Skeleton, marker_set: MarkerSet, out_dir: str | os.PathLike, *,
                skin: Mesh | None = None, seed: int = 0, trials: Sequence[str] = TRIAL_NAMES,
                duration_scale: float = 1.0, sta_scale: float = 1.0, noise_mm: float = 0.5,
                gap_frames: int = 20, n_gaps: int | Mapping[str, int] = 3, subject: str = "Phantom",
                marker_radius_mm: float = 7.0, sta_amplitudes: Mapping[str, float] | None = None
                ) -> dict[str, Any]:
    """Make the phantom's motion-capture trials and their truth.

    Parameters
    ----------
    skeleton : Skeleton
        The subject at its reference (MRI) pose, any world frame (template convention: X anterior,
        Y up, Z right, mm).
    marker_set : MarkerSet
        E.g. ``load_marker_set("kojima_paper")`` for the generic skeleton, or an OpenSim model's
        MarkerSet (``template_marker_set(path)``): its physical markers are used (virtual ones
        are never written).
    out_dir : path-like
        Writes ``trials/<trial>.c3d``, ``truth/<trial>_poses.npz`` and ``truth/marker_binding.yaml``.
    skin : Mesh, optional
        Skin at the reference pose in the skeleton world frame (markers go on it).
    seed : int
        Seeds the artefact coefficients, the noise and the gaps (the same seed gives identical files).
    trials : sequence of str
        Any of :data:`TRIAL_NAMES`.
    duration_scale : float
        Shortens (< 1) or lengthens the trials, see :func:`trial_motion`.
    sta_scale : float
        Multiplies the artefact amplitudes (0: none).
    noise_mm : float
        Standard deviation of the Gaussian noise per coordinate.
    gap_frames : int
        Length of each occlusion gap (frames).
    n_gaps : int or mapping
        Gaps per trial: an int applies to every movement trial (the static trial, used for
        calibration, gets none); a mapping ``{trial: n}`` chooses per trial.
    subject : str
        Label prefix in the C3D (``Phantom:RASI``).
    marker_radius_mm : float
    sta_amplitudes : mapping, optional
        Class -> peak mm overriding :data:`STA_AMPLITUDE_MM`.

    Returns
    -------
    dict
        Summary: output paths, frames, markers, gaps, walking speed, peak artefact per class,
        joint table, timing.

    Notes
    -----
    ``truth/<trial>_poses.npz`` holds ``bones``, ``times`` (s from 0), ``first_frame``,
    ``transforms`` (F, B, 4, 4 bone->lab, mm), ``valid`` (F, B), ``joint_names`` /
    ``joint_child`` / ``joint_parent`` / ``joint_centres`` (F, J, 3, carried by the child),
    ``markers``, ``marker_bones`` / ``marker_local`` (the binding: bone and position in its
    frame, mm), ``marker_truth`` (F, M, 3), ``sta`` (F, M, 3, lab), ``noise``, ``gaps``
    (n, 3: marker index, first frame index, length), ``joint_angle_names`` /
    ``joint_angles_deg`` (F, K, 3), ``pelvis_angles_deg``, ``sliding_joints`` (joint centres that
    move apart by design), ``forearm_twist_deg`` (F,; the right forearm) and per side
    ``forearm_twist_deg_r``, ``radioulnar_axis_lab_r`` / ``radioulnar_axis_ulna_r`` (F, 2, 3:
    radial-head and ulnar-head ends).
    """
    from bonecap.io.c3d import write_c3d

    t0 = time.perf_counter()
    out = Path(out_dir)
    _check_trial_args(noise_mm, gap_frames)
    ctx = _TrialContext(skeleton, marker_set, skin=skin, seed=seed, trials=trials, sta_scale=sta_scale,
                        marker_radius_mm=marker_radius_mm, sta_amplitudes=sta_amplitudes)
    binding, sta_model, table = ctx.binding, ctx.sta_model, ctx.table
    # one trial at a time: made, written, dropped
    made = (ctx.trial(name, duration_scale=duration_scale, noise_mm=noise_mm, gap_frames=gap_frames,
                      n_gaps=n_gaps) for name in trials)
    summary: dict[str, Any] = {"subject": subject, "seed": int(seed), "rate_hz": RATE_HZ,
                               "markers": list(binding.names), "trials": {},
                               "joint_table": table.describe(),
                               "sta": {"scale": sta_scale, "noise_mm": noise_mm,
                                       "amplitude_mm": {c: round(float(max(a for k, a in zip(sta_model.classes,
                                                                                          sta_model.amplitude_mm)
                                                                          if k == c)), 3)
                                                        for c in sorted(set(sta_model.classes))}}}
    # the subject's measurements go with every trial, as Nexus writes them
    widths = measured_joint_widths(skeleton, skin, marker_set, seed=seed, marker_radius_mm=marker_radius_mm) \
        if skin is not None else {}
    summary["subject_parameters"] = widths
    for tr in made:
        c3d_path = out / "trials" / f"{tr.name}.c3d"
        trial = Trial(labels=tr.markers, points=tr.points, rate=RATE_HZ, first_frame=1,
                      prefixes=[subject] * len(tr.markers), events=tr.motion.events, subject_parameters=widths,
                      metadata={"source": "bonecap phantom", "trial": tr.name})
        write_c3d(trial, c3d_path)
        npz_path = out / "truth" / f"{tr.name}_poses.npz"
        _write_npz(npz_path, _truth_arrays(tr, table, binding))
        peak = {}
        mag = np.linalg.norm(tr.sta, axis=2)
        for c in sorted(set(sta_model.classes)):
            cols = [i for i, k in enumerate(sta_model.classes) if k == c]
            peak[c] = round(float(mag[:, cols].max()), 3) if len(mag) else 0.0
        summary["trials"][tr.name] = {
            "c3d": str(c3d_path), "truth": str(npz_path), "frames": len(tr.times),
            "seconds": round(float(tr.times[-1] + 1 / RATE_HZ), 3), "gaps": [list(g) for g in tr.gaps],
            "sta_peak_mm": peak, "walking_speed_mm_s": round(tr.info["speed_mm_s"], 1),
        }
        del tr, trial, mag          # before the next trial is made
    binding_path = out / "truth" / "marker_binding.yaml"
    doc = {"frame": "each marker's bone frame at the reference pose (mm)",
           "markers": {n: {"bone": b, "local_mm": [float(x) for x in p], "method": m,
                           "sta_class": c, "sta_amplitude_mm": round(float(a), 3),
                           "sta_rigid_fraction": round(float(r), 3)}
                       for n, b, p, m, c, a, r in zip(binding.names, binding.bones, binding.local, binding.method,
                                                      sta_model.classes, sta_model.amplitude_mm,
                                                      sta_model.rigid_fraction)}}
    with atomic_path(binding_path) as tmp:
        tmp.write_text(yaml.safe_dump(doc, sort_keys=False))
    summary["binding"] = str(binding_path)
    summary["elapsed_s"] = round(time.perf_counter() - t0, 3)
    json.dumps(summary)  # the summary must stay JSON-able for the CLI report
    return summary
