"""``bonecap build-subject``: from MRI (or a static trial alone) to a subject folder.

Two paths lead to the same :class:`~bonecap.subject.Subject`:

- **MRI** (Kojima et al.): stations registered into one frame, skin and bone
  contours slice by slice, meshes, the template warped onto them by an affine
  + Gaussian RBF transform, markers placed on the skin and bound to bones
  (:func:`build_from_mri`).
- **No MRI** (what labs without a scanner do, and what the real Vicon trials
  need): the template scaled bone by bone to a static trial
  (:func:`build_from_static`).

Either way, with a static trial the skeleton is posed to it and the markers'
measured positions are bound to their bones: markers are never exactly where
the manual says, which is the problem the paper set out to solve.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from bonecap.errors import DataError, InputError
from bonecap.io.c3d import read_c3d
from bonecap.markers import (MarkerSet, check_marker_set, joint_width_placement, load_marker_set, match_labels,
                             place_markers)
from bonecap.model import Skeleton, Trial
from bonecap.scaling import (fit_scale_factors, load_scaling_groups, scale_factors_from_pairs, scale_skeleton,
                              similarity_fit)
from bonecap.skeleton.template import load_template, template_marker_set
from bonecap.subject import MarkerBinding, Subject

__all__ = ["static_markers", "pose_to_static", "bind_static", "knee_flexion_twist", "turn_femurs",
           "functional_twists", "build_from_static"]


def parse_frames(spec: str | None, n_frames: int) -> slice:
    """``"START:STOP"`` (0-based, STOP exclusive, either may be empty) -> a slice, checked against the trial."""
    if not spec:
        return slice(None)
    try:
        a, b = (int(x) if x.strip() else None for x in spec.split(":"))
    except ValueError:
        raise InputError(f"--static-frames takes START:STOP (0-based frame indices), got {spec!r}") from None
    sl = slice(a, b)
    if len(range(n_frames)[sl]) == 0:
        raise InputError(f"--static-frames {spec} selects no frame of a {n_frames}-frame trial")
    return sl


def static_markers(trial: Trial, marker_set: MarkerSet, *, path: str | os.PathLike | None = None,
                   frames: slice = slice(None)) -> tuple[list[str], np.ndarray]:
    """The marker set's markers in a static trial, averaged over its frames.

    The median over frames (not the mean) so that a few mislabelled or
    swapped frames do not move a marker.

    Returns
    -------
    names : list of str
        Marker-set names found in the trial and seen in at least one frame.
    positions : ndarray (M, 3)
        Lab frame of the trial, mm.

    Raises
    ------
    DataError
        Fewer than 6 of the set's markers are in the trial.
    """
    found = match_labels(marker_set, trial.labels)
    names, cols = [], []
    for name in marker_set.markers:
        if name in found and not marker_set.markers[name].virtual:
            j = trial.labels.index(found[name])
            if np.isfinite(trial.points[frames, j]).all(axis=1).any():
                names.append(name)
                cols.append(j)
    if len(names) < 6:
        raise DataError(f"only {len(names)} markers of the set {marker_set.name!r} are seen in the static trial "
                        f"(labels: {', '.join(trial.labels[:12])}{'...' if len(trial.labels) > 12 else ''})",
                        path)
    pos = np.nanmedian(trial.points[frames][:, cols], axis=0)
    return names, pos


def _local(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    return (p - T[:3, 3]) @ T[:3, :3]


#: The static pose is solved to convergence (:func:`pose_to_static`): the markers are bound from it, so
#: whatever it has not settled every trial inherits. The block-coordinate sweeps settle the limbs' twist
#: slowly where the placed markers disagree (a thigh's two markers 40-50 mm off its axis, a shank's one):
#: on a phantom's static (seed 1, markers placed on its MRI) the six sweeps a trial gets left the femurs
#: 8.3 and 13.1 degrees turned about their long axes and the shanks 13.6 and 14.2, against -0.7, -6.3, 1.6
#: and -5.4 converged. A sweep of one frame costs ~2 ms; convergence took ~700 of them (~1.3 s).
STATIC_MAX_SWEEPS = 5000
#: Converged: no segment moved by more than this (mm, at its origin or 100 mm from it) in a sweep.
STATIC_TOL_MM = 1e-3
#: Rounds of reweighting (:func:`pose_to_static`'s ``robust_rounds``) when a personal skeleton is posed to
#: the static trial with its markers where the placement rule put them (the MRI path).
STATIC_ROBUST_ROUNDS = 3


def pose_to_static(skeleton: Skeleton, marker_bones: list[str], marker_local: np.ndarray,
                   static_lab: np.ndarray, *, converge: bool = True, robust_rounds: int = 0,
                   weights: np.ndarray | None = None, rhythm: bool = True) -> np.ndarray:
    """Pose every bone to one frame of static markers with the joint-coupled solver, to convergence.

    Parameters
    ----------
    skeleton : Skeleton
    marker_bones : list of str
    marker_local : ndarray (M, 3)
        Markers in their bones' frames (mm).
    static_lab : ndarray (M, 3)
        The same markers measured in the lab (mm).
    converge : bool, default True
        Solve to the minimum (:data:`STATIC_TOL_MM`; sweeps, then Gauss-Newton
        steps: ``solve_lsq(newton=True)``); False: the six sweeps a
        trial gets, which stop near the skeleton's reference pose -- what a
        template whose markers were only placed by the manual needs (see
        :func:`build_from_static`).
    robust_rounds : int, default 0
        Rounds of iteratively reweighted least squares after the first solve:
        each marker weighted by Cauchy's ``1 / (1 + (r / c)^2)`` of its
        residual ``r``, with ``c`` twice the median residual (at least 2 mm).
        Markers placed by rule on a personal skin miss their true places by
        a few millimetres, some by 10-25 (a surface normal at a spinous tip
        that is not the subject's); weighted down, the few do not tilt the
        segment that the others agree on.
    weights : ndarray (M,), optional
        Each marker's weight (default 1); the robust rounds multiply theirs into it.
    rhythm : bool, default True
        The scapulae turn on their clavicles with the arms (``solve_lsq(rhythm=...)``): a
        personal skeleton's (:meth:`bonecap.subject.Subject.follows_rhythm`).

    Returns
    -------
    ndarray (B, 4, 4)
        ``bone_to_lab`` of every bone of ``skeleton.names`` (NaN where unsolved).

    References
    ----------
    Holland, P. W. & Welsch, R. E. (1977). Robust regression using iteratively
    reweighted least-squares. Communications in Statistics 6(9), 813-827.
    """
    from bonecap.motion.lsq import solve_lsq

    if robust_rounds < 0:
        raise ValueError(f"robust_rounds must be >= 0, got {robust_rounds}")
    # converged by Gauss-Newton steps from where the sweeps slow down (a static took ~1 400 single-frame
    # fits a round to creep to 1e-3 mm, which left the femora 0.12 deg short of the minimum)
    sweeps = dict(n_sweeps=STATIC_MAX_SWEEPS, tol_mm=STATIC_TOL_MM, newton=True) if converge else {}
    given = None if weights is None else np.asarray(weights, float)
    if given is not None and (given.shape != (len(marker_bones),) or not (given >= 0).all()):
        raise ValueError(f"weights must be {len(marker_bones)} non-negative numbers, got shape {given.shape}")
    weights = given
    for _ in range(robust_rounds + 1):
        # (without the feet's axis hold: the static takes their roll from the shank by rule, neutral_twist)
        motion = solve_lsq(skeleton, marker_bones, marker_local, static_lab[None], weights=weights,
                           max_gap_frames=0, hold_axes=False, rhythm=rhythm, **sweeps)
        T = motion.transforms[0]
        if not robust_rounds:
            break
        r = motion.residuals[0]           # each marker's distance from its solved place (NaN: unsolved)
        ok = np.isfinite(r)
        if not ok.any():
            break
        c = max(2.0 * float(np.median(r[ok])), 2.0)
        weights = np.where(ok, 1.0 / (1.0 + (np.where(ok, r, 0.0) / c) ** 2), 1.0)
        if given is not None:
            weights = weights * given
    return T


#: The foot (talus, carrying calcaneus and foot in the solve): its roll about the long axis of the foot,
#: ankle centre -> head of the 2nd metatarsal (the toe marker's landmark), as Plug-in Gait defines it.
#: OpenSim's foot bodies (talus, calcn, toes) have no landmarks: there the axis ends at the
#: metatarsophalangeal joint centre of the calcaneus body (the toes' joint). Their static foot,
#: left to its heel, toe and 5th metatarsal markers (a toe marker 12 mm lower on the skin than the
#: model has it), was 3-5 degrees off on the Rajagopal phantoms, 1.8-2.5 with the roll from the shank.
FOOT_PREFIXES = ("talus", "calcaneus", "foot", "calcn", "toes")
FOOT_AXES: dict[str, list[tuple[str, str]] | None] = {
    "talus": [("foot", "metatarsal2_head"), ("calcn", "mtp")],
    "calcaneus": None, "foot": None, "calcn": None, "toes": None}


#: The hand: its twist about its long axis (wrist -> head of the 3rd metacarpal, Wu et al. 2005) is the
#: radius's. The wrist is ellipsoid (flexion and deviation, no axial rotation), while the finger markers
#: lie ~20 mm apart across the hand, so 10-20 mm of their placement turned a phantom's static hand by
#: 6-19 degrees. The rays ride on the carpals (the solver carries them as one segment).
HAND_PREFIXES = ("carpals", "ray")
HAND_AXES: dict[str, list[tuple[str, str]] | None] = {"carpals": [("ray3", "metacarpal_head")], "ray": None}


def neutral_twist(skeleton: Skeleton, poses: np.ndarray, prefixes=("femur", "tibia", "humerus"),
                  axes: dict[str, list[tuple[str, str]] | None] | None = None) -> np.ndarray:
    """Give the long bones of a static pose the reference twist relative to their parents.

    A femur, tibia or humerus carries two markers in Plug-in Gait (one of them
    on a wand or a soft shaft): with its joint centres they fix its direction
    well but its twist about the long axis poorly, and a template whose
    proportions differ from the subject's can turn it by tens of degrees.
    A static trial is taken standing in the anatomical posture, so the twist
    is taken as the template's (neutral) one relative to the parent, and only
    the direction comes from the solve. Plug-in Gait's static calibration
    rests on the same assumption. Bones are processed parent first, so a
    tibia's neutral twist is relative to its corrected femur.

    The foot has the same weakness about its long axis: heel and toe markers
    and the ankle centre lie within 2-3 cm of one line, so 15 mm of marker
    placement error rolled a phantom's foot by 60 degrees. Plug-in Gait
    takes the foot's roll from the shank; ``prefixes=FOOT_PREFIXES,
    axes=FOOT_AXES`` does so here (for an MRI subject the reference is the
    MRI pose: the foot's inversion relative to the shank, not its flexion).
    The hand likewise takes its twist from the radius (``HAND_PREFIXES``,
    ``HAND_AXES``): the wrist has no axial rotation of its own.

    Parameters
    ----------
    skeleton : Skeleton
    poses : ndarray (B, 4, 4)
        ``bone_to_lab`` of the static (parent-first order of ``skeleton.names``).
    prefixes : tuple of str
        Bones (name prefixes) to correct.
    axes : dict, optional
        Per bone prefix, a list of ``(bone prefix, point)`` of which the first the
        skeleton has ends its long axis (from its proximal joint centre, same side;
        the point a landmark, or a joint centre named with or without the side
        suffix), or ``None`` for a bone that rides on its parent at the reference
        relative pose (as the solver carried it); default: its farthest joint
        centre.

    Returns
    -------
    ndarray (B, 4, 4)
        The corrected poses (a copy).
    """
    from bonecap.motion.paper import minimal_rotation
    from bonecap.skeleton.kinematics import GIRDLE_JOINTS, proximal_joint

    out = poses.copy()
    idx = {n: i for i, n in enumerate(skeleton.names)}
    for n in skeleton.names:
        b = skeleton.bones[n]
        if not n.startswith(prefixes) or b.parent is None:
            continue
        Tp, Tc = out[idx[b.parent]], out[idx[n]]
        gp = skeleton.bones[b.parent].parent
        if gp is not None and any(j in skeleton.bones[gp].joint_centres for j in GIRDLE_JOINTS):
            # a scapula (on a clavicle): the solver turns it upward on the clavicle with the arm
            # (motion.lsq.rhythm_turns), but the arm's neutral twist is the thorax's, not turned with
            # it (the phantom's humerus keeps the orientation its shoulder angles give it in the
            # thorax): the scapula taken as the clavicle carries it at the reference
            Tp = out[idx[gp]] @ np.linalg.solve(skeleton.bones[gp].bone_to_world,
                                                skeleton.bones[b.parent].bone_to_world)
        if not (np.isfinite(Tp).all() and np.isfinite(Tc).all()):
            continue
        try:
            jname, _, prox = proximal_joint(skeleton, n)
        except ValueError:
            continue
        others = [c for k, c in b.joint_centres.items() if k != jname]
        key = next((k for k in (axes or {}) if n.startswith(k)), None)
        spec = axes[key] if key is not None else None
        if key is not None and spec is None:
            others = []                        # rides on its parent (calcaneus and foot on the talus)
        for bone_prefix, point in spec or []:
            suffix = n[-2:] if n.endswith(("_l", "_r")) else ""
            ob = skeleton.bones.get(bone_prefix + suffix)
            name = next((k for k in (point, point + suffix)
                         if ob is not None and (k in ob.landmarks or k in ob.joint_centres)), None)
            if name is not None:
                others = [np.linalg.solve(b.bone_to_world, np.r_[ob.landmark_in_world(name), 1.0])[:3]]
                break
        rel_ref = np.linalg.solve(skeleton.bones[b.parent].bone_to_world, b.bone_to_world)
        if not others:
            # a rider, or nothing to give it a long axis: it keeps its reference pose relative to its
            # corrected parent
            out[idx[n]] = Tp @ rel_ref
            continue
        dist = max(others, key=lambda c: np.linalg.norm(c - prox))
        Rn = (Tp @ rel_ref)[:3, :3]
        a_n, a_s = Rn @ (dist - prox), Tc[:3, :3] @ (dist - prox)
        R = minimal_rotation(a_n, a_s) @ Rn
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = Tc[:3, :3] @ prox + Tc[:3, 3] - R @ prox
        out[idx[n]] = T
    return out


#: The forearm's rotation axis, from the radial head's centre to the ulnar head's fovea (the landmarks
#: of :func:`pronate_on_ulna`; Hollister et al. 1994).
PRONATION_AXIS = (("radius", "radial_head_centre"), ("ulna", "ulnar_head_fovea"))


def pronate_on_ulna(skeleton: Skeleton, poses: np.ndarray, marker_bones: list[str], marker_local: np.ndarray,
                    static_lab: np.ndarray) -> tuple[np.ndarray, dict[str, float]]:
    """Each radius of a static pose re-placed on its solved ulna, turned about the forearm's axis to its markers.

    In the joint-coupled solve the radius hangs on a ball joint at its head
    with two markers (the radial styloid and a dorsal forearm marker over
    soft tissue), so its twist about its long axis rests on where the
    forearm marker was placed on the skin: on phantoms it came out 2-9 deg
    off, and the hand, which takes its twist from the radius (the wrist has
    no axial rotation), with it. But the radius does not move freely about
    its head: relative to the ulna it only turns about the forearm's
    rotation axis, from the radial head's centre to the ulnar head's fovea
    (pronation-supination; Hollister et al. 1994). Here each radius keeps
    its relative pose to the ulna from the skeleton (the MRI's), and is
    turned about that axis, carried with the solved ulna, by the angle that
    fits its markers best in the least-squares sense (closed form: for
    points turned about one axis the optimum angle is
    ``atan2(sum w . (a x v), sum w_perp . v_perp)``). The radial styloid
    marker, 20-25 mm from the axis at the wrist, then decides the angle; the
    ulna, with the olecranon and ulnar styloid markers and the elbow, is the
    better-held bone of the two. The hand (the radius's descendants, one
    segment in the solve) is carried to the re-placed wrist and turned about
    it onto its own markers (its direction had been fitted about the old
    wrist: left as it was, the finger markers were bound 3-9 mm farther off
    on phantoms); its twist is the radius's afterwards (:func:`neutral_twist`).

    Parameters
    ----------
    skeleton : Skeleton
        The subject's skeleton (its ``bone_to_world`` the reference pose: the
        MRI's, where the radius's pose relative to the ulna is measured).
    poses : ndarray (B, 4, 4)
        ``bone_to_lab`` of the static, in the order of ``skeleton.names``.
    marker_bones : list of str
        Each static marker's bone.
    marker_local : ndarray (M, 3)
        The markers in their bones' frames (mm).
    static_lab : ndarray (M, 3)
        The markers measured in the static, lab frame (mm; NaN where missing).

    Returns
    -------
    poses : ndarray (B, 4, 4)
        A copy with each radius and its hand re-placed (the others as they were).
    turns : dict of str -> float
        Per radius re-placed, its turn from the solved pose (deg, about the
        forearm axis as the solve had it).

    References
    ----------
    Hollister A, Giurintano DJ, Bertram A, et al. The axis of rotation of the
    forearm. Clin Orthop Relat Res 298:272-276, 1994.
    """
    from scipy.spatial.transform import Rotation

    from bonecap.skeleton.kinematics import subtree, turn_about

    poses = np.asarray(poses, float)
    marker_local = np.asarray(marker_local, float).reshape(-1, 3)
    static_lab = np.asarray(static_lab, float).reshape(-1, 3)
    if len(marker_bones) != len(marker_local) or len(marker_local) != len(static_lab):
        raise ValueError(f"marker_bones, marker_local and static_lab differ in length: {len(marker_bones)}, "
                         f"{len(marker_local)}, {len(static_lab)}")
    if poses.shape != (len(skeleton.names), 4, 4):
        raise ValueError(f"poses must be ({len(skeleton.names)}, 4, 4), got {poses.shape}")
    idx = {n: i for i, n in enumerate(skeleton.names)}
    out = poses.copy()
    turns: dict[str, float] = {}
    (rb, rl), (ub, ul) = PRONATION_AXIS
    for suffix in ("_r", "_l", ""):
        r, u = rb + suffix, ub + suffix
        if r not in skeleton.bones or u not in skeleton.bones:
            continue
        R0, U0 = skeleton.bones[r], skeleton.bones[u]
        if rl not in R0.landmarks or ul not in U0.landmarks:
            continue
        U = poses[idx[u]]
        sel = [k for k, b in enumerate(marker_bones) if b == r and np.isfinite(static_lab[k]).all()]
        if not sel or not (np.isfinite(U).all() and np.isfinite(poses[idx[r]]).all()):
            continue
        rel = np.linalg.solve(U0.bone_to_world, R0.bone_to_world)       # radius in the ulna's frame (MRI)
        start = U @ rel                                                  # the radius at that relative pose
        # the axis in the lab, carried with the solved ulna
        to_lab = U @ np.linalg.inv(U0.bone_to_world)
        c = (to_lab @ np.r_[R0.landmark_in_world(rl), 1.0])[:3]
        a = (to_lab @ np.r_[U0.landmark_in_world(ul), 1.0])[:3] - c
        if np.linalg.norm(a) < 1e-6:
            continue
        a /= np.linalg.norm(a)
        v = (marker_local[sel] @ start[:3, :3].T + start[:3, 3]) - c
        w = static_lab[sel] - c
        v_perp = v - np.outer(v @ a, a)
        w_perp = w - np.outer(w @ a, a)
        phi = float(np.arctan2(np.sum(w * np.cross(a, v)), np.sum(w_perp * v_perp)))
        if not np.isfinite(phi):
            continue
        new = turn_about(c, Rotation.from_rotvec(phi * a).as_matrix()) @ start
        # the change from the solved radius, as a turn about the axis (its sign along a)
        d = Rotation.from_matrix(new[:3, :3] @ poses[idx[r]][:3, :3].T).as_rotvec()
        turns[r] = float(np.degrees(d @ a))
        out[idx[r]] = new
        # the hand hangs on the radius's wrist: carried to the re-placed wrist and turned about it onto
        # its own markers (its solved direction had been fitted about the old wrist)
        ride = subtree(skeleton, r)[1:]
        if not ride or "wrist" not in R0.joint_centres:
            continue
        wrist = np.r_[R0.joint_centres["wrist"], 1.0]
        w_old, w_new = (poses[idx[r]] @ wrist)[:3], (new @ wrist)[:3]
        carry = np.eye(4)
        carry[:3, 3] = w_new - w_old
        hsel = [k for k, b in enumerate(marker_bones) if b in ride and np.isfinite(static_lab[k]).all()
                and np.isfinite(poses[idx[b]]).all()]
        if len(hsel) >= 2:
            q = np.array([(carry @ poses[idx[marker_bones[k]]] @ np.r_[marker_local[k], 1.0])[:3] for k in hsel])
            rot, _ = Rotation.align_vectors(static_lab[hsel] - w_new, q - w_new)
            carry = turn_about(w_new, rot.as_matrix()) @ carry
        for n in ride:
            if np.isfinite(poses[idx[n]]).all():
                out[idx[n]] = carry @ poses[idx[n]]
    return out, turns


#: Knee flexion (deg) from which a frame's hip-knee-ankle plane stands for the knee's flexion axis.
FUNCTIONAL_MIN_FLEXION_DEG = 25.0


def _knees(skeleton: Skeleton) -> list[tuple[str, str, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """``(femur, tibia, hip in femur, knee in femur, ankle in tibia, flexion axis in femur)`` per knee."""
    from bonecap.skeleton.kinematics import proximal_joint

    out = []
    for n in skeleton.names:
        t = skeleton.bones[n]
        if not n.startswith("tibia") or t.parent is None or not t.parent.startswith("femur"):
            continue
        try:
            knee, knee_f, knee_t = proximal_joint(skeleton, n)
            _, _, hip_f = proximal_joint(skeleton, t.parent)           # the hip centre in the femur frame
        except ValueError:
            continue
        axis = t.joint_axes.get(knee)
        others = [c for k, c in t.joint_centres.items() if k != knee]
        if axis is None or not others:
            continue
        ankle_t = max(others, key=lambda c: float(np.linalg.norm(c - knee_t)))
        rel = np.linalg.solve(skeleton.bones[t.parent].bone_to_world, t.bone_to_world)
        out.append((t.parent, n, np.asarray(hip_f, float), np.asarray(knee_f, float), np.asarray(ankle_t, float),
                    rel[:3, :3] @ np.asarray(axis, float)))
    return out


def knee_flexion_twist(skeleton: Skeleton, transforms: np.ndarray, *,
                       min_flexion_deg: float = FUNCTIONAL_MIN_FLEXION_DEG, min_frames: int = 20
                       ) -> dict[str, dict[str, float]]:
    """How far each femur's frame is turned about its long axis, read from a movement trial's knee flexion.

    The static trial fixes a femur's twist poorly: two markers (the thigh's,
    on a featureless shaft, and the lateral epicondyle's) lie 40-50 mm off
    its long axis, so 4-5 mm of error in where they were placed turns it by
    5-14 degrees (a phantom's placed markers, both within 5 mm of the
    truth: 13.6 degrees). Plug-in Gait has the same weakness and the
    field's answers are a knee alignment device or a functional
    calibration: the knee flexes about an axis fixed in the femur, and its
    direction in a flexing trial corrects the thigh's rotation (Baker et al.
    1999's DynaKAD; Schwartz & Rozumalski 2005). Here, in every frame whose
    knee is flexed by at least ``min_flexion_deg``, the normal of the
    plane through the hip, knee and ankle centres (the joint centres of the
    solved poses: set by the bones' ends, not by the thigh markers' spin)
    is the flexion axis; expressed in the solved femur frame, its angle
    about the femur's long axis (hip to knee) from the subject's anatomical
    knee axis (the tibia's ``joint_axes`` at the reference pose) is how far
    that frame is turned. The median over those frames is returned. The
    frames are flexed ones, where the thigh's soft-tissue artefact is
    largest (on the phantom the femur's spin error changes by up to 8
    degrees between extension and 60 degrees of flexion), so the turn is
    the femur's error in flexion, which the static's does not always share.

    Parameters
    ----------
    skeleton : Skeleton
        The subject (femur and tibia joint centres, the tibia's knee axis).
    transforms : ndarray (F, B, 4, 4)
        Solved ``bone_to_lab`` of a trial (any lab frame), NaN where invalid.
    min_flexion_deg : float
        Frames flexed less are left out (the plane is ill-defined near full extension).
    min_frames : int
        A knee with fewer such frames gets no estimate.

    Returns
    -------
    dict
        Per femur name: ``twist_deg`` (turn the femur frame by this much about
        its long axis, right-handed from hip to knee, to correct it),
        ``frames`` and ``spread_deg`` (median absolute deviation of the
        per-frame values).

    References
    ----------
    .. [1] Baker R, Finney L, Orr J (1999). A new approach to determine the hip rotations profile from
           clinical gait analysis data. Hum Mov Sci 18:655-667.
    .. [2] Schwartz MH, Rozumalski A (2005). A new method for estimating joint parameters from motion
           data. J Biomech 38(1):107-116.
    """
    T = np.asarray(transforms, float)
    if T.ndim != 4 or T.shape[1:] != (len(skeleton.names), 4, 4):
        raise ValueError(f"transforms must be (frames, {len(skeleton.names)}, 4, 4) for this skeleton, got {T.shape}")
    if not 0 < min_flexion_deg < 180:
        raise ValueError(f"min_flexion_deg must be in (0, 180), got {min_flexion_deg}")
    idx = {n: i for i, n in enumerate(skeleton.names)}
    out: dict[str, dict[str, float]] = {}
    for femur, tibia, hip_f, knee_f, ankle_t, axis_f in _knees(skeleton):
        Fm, Tb = T[:, idx[femur]], T[:, idx[tibia]]
        ok = np.isfinite(Fm).all(axis=(1, 2)) & np.isfinite(Tb).all(axis=(1, 2))
        if not ok.any():
            continue
        Fm, Tb = Fm[ok], Tb[ok]
        hip = Fm[:, :3, :3] @ hip_f + Fm[:, :3, 3]
        knee = Fm[:, :3, :3] @ knee_f + Fm[:, :3, 3]
        ankle = Tb[:, :3, :3] @ ankle_t + Tb[:, :3, 3]
        thigh, shank = knee - hip, ankle - knee
        cosf = np.einsum("ij,ij->i", thigh, shank) / (np.linalg.norm(thigh, axis=1) * np.linalg.norm(shank, axis=1))
        flexed = np.degrees(np.arccos(np.clip(cosf, -1.0, 1.0))) >= min_flexion_deg
        if flexed.sum() < min_frames:
            continue
        normal = np.cross(thigh[flexed], shank[flexed])
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        n_f = np.einsum("fji,fj->fi", Fm[flexed, :3, :3], normal)     # in the solved femur frame
        n_f *= np.sign(n_f @ axis_f)[:, None]
        u = (knee_f - hip_f) / np.linalg.norm(knee_f - hip_f)
        a = axis_f - (axis_f @ u) * u
        n_p = n_f - (n_f @ u)[:, None] * u
        angle = np.degrees(np.arctan2(np.cross(a, n_p) @ u, n_p @ a))
        med = float(np.median(angle))
        out[femur] = {"twist_deg": med, "frames": int(flexed.sum()),
                      "spread_deg": float(np.median(np.abs(angle - med)))}
    return out


def turn_femurs(skeleton: Skeleton, poses: np.ndarray, twists: dict[str, float]) -> np.ndarray:
    """Femurs of a pose (``bone_to_lab``, B x 4 x 4) turned about their long axes (hip to knee) by degrees."""
    from scipy.spatial.transform import Rotation

    out = np.array(poses, dtype=float, copy=True)
    idx = {n: i for i, n in enumerate(skeleton.names)}
    for femur, _, hip_f, knee_f, _, _ in _knees(skeleton):
        if femur not in twists or not np.isfinite(out[idx[femur]]).all():
            continue
        u = (knee_f - hip_f) / np.linalg.norm(knee_f - hip_f)
        P = out[idx[femur]]
        R = P[:3, :3] @ Rotation.from_rotvec(np.radians(twists[femur]) * u).as_matrix()
        P[:3, 3] = P[:3, :3] @ hip_f + P[:3, 3] - R @ hip_f            # the hip centre stays
        P[:3, :3] = R
    return out


def functional_twists(subject: Subject, trials: list[tuple[Trial, str]]) -> dict[str, dict[str, float]]:
    """:func:`knee_flexion_twist` over movement trials solved as ``animate`` solves them (its least squares).

    ``trials`` are ``(trial, path)``, matched to the subject's bound markers by
    name and alias; the frames of all trials are pooled. The solve is
    animate's own (:func:`bonecap.animate.solve_trial`, the same sweeps): the
    thigh's twist is a slow direction of its block-coordinate descent (seed
    1's walk: the left femur 11.2 deg off after animate's sweeps, 5.2 after
    100), so the turn read here is the one animate's poses need.
    """
    from bonecap.animate import solve_trial, trial_markers

    pooled = []
    for trial, path in trials:
        names, measured, _ = trial_markers(subject, trial, path=path)
        pooled.append(solve_trial(subject, names, measured, rate=trial.rate).transforms)
    if not pooled:
        return {}
    return knee_flexion_twist(subject.skeleton, np.concatenate(pooled))


def rhythm_consistent(skeleton: Skeleton, marker_bones: list[str], poses: np.ndarray) -> np.ndarray:
    """The static's scapulae turned on their clavicles as the solver's rhythm turns them for its arms.

    The solver turns each scapula upward on its clavicle with the arm's elevation
    (:func:`bonecap.motion.lsq.rhythm_turns`), taking the turn from the poses of its last sweep. A
    static not solved to convergence, or changed after the solve (twists set by rule), can hold a
    scapula at another turn than its final arm and clavicle give, and markers bound to it there
    would sit off where every trial's solve carries them. Call before :func:`joint_consistent`,
    which then hangs the arm from the turned shoulder centre. (The MRI path's static is converged:
    on the phantom of seed 1 its figures were the same with and without this.)

    Parameters
    ----------
    skeleton : Skeleton
    marker_bones : list of str
        The bones of the static's markers (the solver's segments).
    poses : ndarray (B, 4, 4)
        ``bone_to_lab`` of the static.

    Returns
    -------
    ndarray (B, 4, 4)
        A copy, each rhythm's scapula re-turned (NaN poses left alone).
    """
    from bonecap.motion.lsq import plan_rhythms, plan_segments, rhythm_turns

    plan = plan_segments(skeleton, marker_bones)
    idx = {n: i for i, n in enumerate(skeleton.names)}
    out = poses.copy()
    for rh in plan_rhythms(skeleton, plan):
        root = plan.segments[rh.segment].root

        def frame(s):
            return poses[idx[plan.segments[s].root]][None]

        if not all(np.isfinite(frame(s)).all() for s in (rh.parent, rh.segment, rh.child)):
            continue
        turn, _ = rhythm_turns(rh, frame(rh.parent), frame(rh.segment), frame(rh.child))
        rest = np.linalg.solve(skeleton.bones[root].bone_to_world, skeleton.bones[rh.scapula].bone_to_world)
        out[idx[rh.scapula]] = poses[idx[root]] @ turn[0] @ rest
    return out


def joint_consistent(skeleton: Skeleton, poses: np.ndarray) -> np.ndarray:
    """The solved static rebuilt as a chain of ball joints, so that every joint centre coincides.

    A coupled least-squares solve leaves small gaps at the joints where the
    template's proportions and the markers disagree. Binding markers to such
    a pose would bake the gaps in, and every later solve would fight them
    (a two-marker shank can flip to the wrong side of its axis doing so).
    Each bone keeps its solved orientation; its position follows its parent,
    turned about the shared joint centre from the reference relative pose as
    :func:`bonecap.skeleton.kinematics.pose_skeleton` turns it
    (:func:`bonecap.skeleton.kinematics.joint_pair`: a shoulder girdle's
    sternoclavicular joint too, which the sternum lists per side). Unsolved
    bones, and bones that meet their parent at no named joint, keep their
    reference pose relative to the parent.
    """
    from bonecap.skeleton.kinematics import PIVOT_JOINTS, joint_pair

    idx = {n: i for i, n in enumerate(skeleton.names)}
    out = np.zeros((len(skeleton.names), 4, 4))
    for n in skeleton.names:                    # parent before child
        b = skeleton.bones[n]
        solved = np.isfinite(poses[idx[n]]).all()
        if b.parent is None:
            out[idx[n]] = poses[idx[n]] if solved else b.bone_to_world
            continue
        Tp = out[idx[b.parent]]
        rest = np.linalg.solve(skeleton.bones[b.parent].bone_to_world, b.bone_to_world)    # child -> parent
        # the radius pivots on the ulna at the radial head: without naming that pivot it would fall
        # back to its reference twist and lose the solved pronation
        pair = joint_pair(skeleton, n, PIVOT_JOINTS)
        if pair is None or not solved:
            out[idx[n]] = Tp @ rest
            continue
        # turned about the parent's copy of the joint centre from the reference relative pose, as
        # pose_skeleton does: where the two copies of a joint centre do not meet at the reference (a
        # personal skeleton's acromioclavicular joint 12-13 mm apart, seed 3), the gap is kept, not
        # closed by moving the child (that moved the arm 12 mm from its markers before they were bound)
        c_parent = pair[0]
        J = np.eye(4)
        J[:3, :3] = Tp[:3, :3].T @ poses[idx[n]][:3, :3] @ rest[:3, :3].T
        J[:3, 3] = c_parent - J[:3, :3] @ c_parent
        out[idx[n]] = Tp @ J @ rest
    return out


#: Weight of a joint centre target (:func:`joint_centre_targets`, :func:`converge_limbs`) in the no-MRI
#: static fit, against 1 for a marker. Measured on the phantoms of seeds 0-3 and the Plug-in Gait subject
#: of ../shared (docs/benchmarks.md, "No-MRI static (build-subject --static) on phantoms").
JOINT_TARGET_WEIGHT = 10.0


def joint_centre_targets(skeleton: Skeleton, marker_set: MarkerSet, names: list[str], marker_local: np.ndarray,
                         static_lab: np.ndarray, poses: np.ndarray) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Where the static's lateral joint markers put their joints' centres (Plug-in Gait's rule).

    A marker over the side of a joint (one whose set gives ``width: {parameter,
    joint}``: Plug-in Gait's KNE and ANK) lies on the joint's axis, its
    depth from the centre known (the subject's measured width, set by
    :func:`bonecap.markers.joint_width_placement`, else the template's). The
    centre is then the measured marker moved in by that depth along the
    joint's axis -- Plug-in Gait's chord rule (Davis et al. 1991), with the
    axis taken from ``poses`` instead of the thigh and shank wands: a pose
    whose long bones carry the reference twist relative to their parents
    (:func:`neutral_twist`). Left to the markers alone, a converged fit turns
    a thigh about its long axis until the knee marker's 60-80 mm lever
    swings the knee centre 40-75 mm behind or beside the truth (the phantoms
    of seeds 0-3); these targets hold it (:func:`converge_limbs`).

    Parameters
    ----------
    skeleton : Skeleton
        The scaled template (reference pose).
    marker_set : MarkerSet
    names : list of str
        The static's markers.
    marker_local : ndarray (M, 3)
        Their places on ``skeleton`` in their bones' frames (mm), depths included.
    static_lab : ndarray (M, 3)
        The measured static markers (lab, mm).
    poses : ndarray (B, 4, 4)
        A first ``bone_to_lab`` pose of every bone (the axes' directions).

    Returns
    -------
    bones : list of str
        The marker's bone for each target.
    local : ndarray (K, 3)
        The joint centre in that bone's frame (mm).
    target : ndarray (K, 3)
        Where the static puts it (lab, mm).

    References
    ----------
    .. [1] Davis RB, Ounpuu S, Tyburski D, Gage JR (1991). A gait analysis data collection and reduction
           technique. Hum Mov Sci 10(5):575-587.
    """
    from bonecap.markers import joint_centre_axis

    idx = {n: i for i, n in enumerate(skeleton.names)}
    bones, local, target = [], [], []
    for n, m_loc, p in zip(names, np.asarray(marker_local, float), np.asarray(static_lab, float)):
        m = marker_set.markers.get(n)
        if m is None or m.width is None or not np.isfinite(p).all():
            continue
        T = poses[idx[m.bone]]
        if not np.isfinite(T).all():
            continue
        try:
            centre, axis = joint_centre_axis(skeleton, m.bone, m.width[1])
        except ValueError:
            continue
        # in the marker's bone frame, so the first pose carries centre and axis with the marker
        B = skeleton.bones[m.bone].bone_to_world
        c_loc = B[:3, :3].T @ (centre - B[:3, 3])
        a_loc = B[:3, :3].T @ axis
        along = float((m_loc - c_loc) @ a_loc)
        if along < 0:
            a_loc, along = -a_loc, -along
        bones.append(m.bone)
        local.append(c_loc)
        target.append(p - along * (T[:3, :3] @ a_loc))
    return bones, np.array(local, float).reshape(-1, 3), np.array(target, float).reshape(-1, 3)


def converge_limbs(skeleton: Skeleton, marker_set: MarkerSet, names: list[str], marker_bones: list[str],
                   marker_local: np.ndarray, static_lab: np.ndarray, first: np.ndarray, *,
                   weight: float = JOINT_TARGET_WEIGHT) -> tuple[np.ndarray, int]:
    """The limbs whose joint centres the static's lateral markers give, fitted to convergence with them held.

    The no-MRI static is first posed by the six sweeps a trial gets, which
    stop near the template's reference pose and keep the pelvis, trunk and
    arms where their markers and that prior agree. The legs they leave
    where the template stood them. Here the whole skeleton is solved again
    to convergence (:func:`pose_to_static`) with two kinds of extra targets,
    each weighted ``weight`` against a marker's 1: the knee and ankle
    centres of :func:`joint_centre_targets`, and four points of the root
    bone (the pelvis) at ``first``'s pose, so that the limbs' proximal joints
    stay where ``first`` has them. Only the limbs are taken from that
    solve: the subtree of each target's bone, from the highest bone that
    carries a target. Everything else keeps ``first``.

    Parameters
    ----------
    skeleton : Skeleton
    marker_set : MarkerSet
    names, marker_bones : list of str
        The static's markers and their bones.
    marker_local : ndarray (M, 3)
        The markers' places in their bones' frames (the template's, depths included).
    static_lab : ndarray (M, 3)
        The measured static markers (lab, mm).
    first : ndarray (B, 4, 4)
        The six sweeps' ``bone_to_lab``.
    weight : float
        A target's weight.

    Returns
    -------
    poses : ndarray (B, 4, 4)
        ``first`` with the held limbs replaced.
    n_targets : int
        Joint centre targets used (0: ``first`` unchanged, as for a marker
        set without lateral joint markers, e.g. an OpenSim model's).
    """
    from bonecap.skeleton.kinematics import subtree

    if not (np.isfinite(weight) and weight > 0):
        raise ValueError(f"weight must be a positive number, got {weight!r}")
    vb, vl, vt = joint_centre_targets(skeleton, marker_set, names, marker_local, static_lab,
                                      neutral_twist(skeleton, first))
    root = skeleton.names[0]
    idx = {n: i for i, n in enumerate(skeleton.names)}
    R0 = first[idx[root]]
    if not vb or not np.isfinite(R0).all():
        return first, 0
    corners = np.array([[0.0, 0.0, 0.0], [100.0, 0.0, 0.0], [0.0, 100.0, 0.0], [0.0, 0.0, 100.0]])
    held = [b for b in vb if b != root]
    bones = list(marker_bones) + vb + [root] * len(corners)
    local = np.vstack([marker_local, vl, corners])
    lab = np.vstack([static_lab, vt, corners @ R0[:3, :3].T + R0[:3, 3]])
    weights = np.r_[np.ones(len(marker_bones)), np.full(len(vb) + len(corners), float(weight))]
    # (a template scaled to the static: its scapulae ride on their clavicles, see Subject.follows_rhythm)
    second = pose_to_static(skeleton, bones, local, lab, converge=True, weights=weights, rhythm=False)
    limbs: set[str] = set()
    for b in held:
        top = b
        while skeleton.bones[top].parent in held:
            top = skeleton.bones[top].parent
        limbs.update(subtree(skeleton, top))
    out = np.array(first, dtype=float, copy=True)
    for n in limbs:
        if np.isfinite(second[idx[n]]).all():
            out[idx[n]] = second[idx[n]]
    return out, len(vb)


def bind_static(skeleton: Skeleton, names: list[str], marker_bones: list[str], static_lab: np.ndarray,
                bone_to_lab: np.ndarray) -> dict[str, MarkerBinding]:
    """Bind measured static markers to their bones (positions in the bone frames)."""
    index = {n: i for i, n in enumerate(skeleton.names)}
    out = {}
    for n, b, p in zip(names, marker_bones, static_lab):
        T = bone_to_lab[index[b]]
        if np.isfinite(T).all() and np.isfinite(p).all():
            out[n] = MarkerBinding(n, b, _local(T, p), "static")
    return out


#: A segment's capsule-measured markers are trusted while they fit the static trial to within this RMS
#: (mm): the capsule centre (~1 mm), the static's noise (0.5 mm) and the soft-tissue artefact of markers
#: over bony landmarks (2-3 mm, Leardini et al. 2005) between lying in the scanner and standing.
CAPSULE_STATIC_TOLERANCE_MM = 4.0


def capsule_static_disagreement(skeleton: Skeleton, names: list[str], marker_bones: list[str],
                                marker_local: np.ndarray, static_lab: np.ndarray, bone_to_lab: np.ndarray,
                                capsule_names, *, tolerance_mm: float = CAPSULE_STATIC_TOLERANCE_MM,
                                scanned_bones=()) -> tuple[dict[str, float], list[str]]:
    """Per rigid segment, how far its capsule-measured markers sit from the posed static.

    A capsule gives a marker's position in the MRI to about a millimetre, but
    it binds the marker to the bone as that bone lies in the MRI. Where the
    scan did not measure the bone (a hand or a foot carried from its
    neighbours at the template's wrist or ankle angle) a wrong MRI pose moves
    every capsule binding of the segment together; the static trial then sees
    the segment's markers as a rigid pattern its joints do not let fit. Such
    a segment is better bound from the static, as markers without capsules are.
    A segment the scan measured (one of its bones in ``scanned_bones``) cannot
    carry such an error: there the static's misfit is the model's (a rigid
    trunk, a girdle that cannot turn its scapula; a phantom's trunk capsules
    4.4 mm RMS from the static, bound within 0.6-1.0 mm of the truth), and it
    is not flagged.

    Parameters
    ----------
    skeleton : Skeleton
        The subject (MRI world).
    names, marker_bones : list of str
        The static's markers and their bones.
    marker_local : ndarray (M, 3)
        The bindings the static was solved with (bone frames, mm).
    static_lab : ndarray (M, 3)
        The measured static markers (lab, mm).
    bone_to_lab : ndarray (B, 4, 4)
        The solved static pose of every bone of ``skeleton.names`` (lab, mm).
    capsule_names : collection of str
        The markers whose bindings came from capsules.
    tolerance_mm : float
        A segment whose capsule markers' RMS residual exceeds it is flagged.
    scanned_bones : collection of str
        Bones the scan measured; a segment with one of them is never flagged.

    Returns
    -------
    rms : dict of str -> float
        Segment root bone -> RMS residual (mm) of its capsule markers.
    flagged : list of str
        The segment roots over ``tolerance_mm`` that the scan did not measure.
    """
    from bonecap.motion.lsq import plan_segments

    if not (np.isfinite(tolerance_mm) and tolerance_mm > 0):
        raise ValueError(f"tolerance_mm must be a positive number of millimetres, got {tolerance_mm!r}")
    plan = plan_segments(skeleton, marker_bones)
    index = {n: i for i, n in enumerate(skeleton.names)}
    sq: dict[str, list[float]] = {}
    for n, b, loc, p in zip(names, marker_bones, np.asarray(marker_local, float), np.asarray(static_lab, float)):
        T = bone_to_lab[index[b]]
        if n not in capsule_names or not (np.isfinite(T).all() and np.isfinite(p).all()):
            continue
        root = plan.segments[plan.segment_of[b]].root
        sq.setdefault(root, []).append(float(np.sum((T[:3, :3] @ loc + T[:3, 3] - p) ** 2)))
    rms = {r: float(np.sqrt(np.mean(v))) for r, v in sq.items()}
    scanned = {seg.root for seg in plan.segments if any(m in scanned_bones for m in seg.members)}
    return rms, sorted(r for r, v in rms.items() if v > tolerance_mm and r not in scanned)


def build_from_static(static: str | os.PathLike, *, generic: str | os.PathLike = "default",
                      marker_set: str | os.PathLike | None = None, subject_name: str | None = None,
                      iterations: int = 3, static_frames: str | None = None) -> tuple[Subject, dict[str, Any]]:
    """Scale the template to a static trial and bind its markers (no MRI).

    The template's markers are placed by the marker set's manual rules
    (:func:`bonecap.markers.place_markers`), except where the static trial
    carries the subject's measured joint widths (Plug-in Gait's
    ``LKneeWidth``, ``LAnkleWidth`` in the C3D's ``PROCESSING`` group, as
    Nexus writes them): there the lateral knee and ankle markers are set
    out to half the width plus a marker radius from the joint centre
    (:func:`bonecap.markers.joint_width_placement`), as Plug-in Gait places
    its joint centres. The static is posed by six sweeps of the
    joint-coupled solver, then its legs are solved to convergence with the
    knee and ankle centres held where those markers put them
    (:func:`converge_limbs`).

    Parameters
    ----------
    static : path-like
        The static C3D trial (any lab frame and units; read with POINT:UNITS).
    generic : str or path-like
        ``"default"`` or an OpenSim ``.osim`` model.
    marker_set : str or path-like, optional
        Marker set name or YAML; default: the template's (Plug-in Gait for the
        embedded skeleton, the model's MarkerSet for an OpenSim model).
    subject_name : str, optional
        C3D subject prefix to keep.
    iterations : int
        Rounds of pose → per-bone scale (3 settle to < 0.5 %).
    static_frames : str, optional
        ``START:STOP`` frames of the static to use.

    Returns
    -------
    subject : Subject
        Skeleton in the template's world frame (``model``), scaled per bone;
        markers bound from the static trial (``source: static``).
    report : dict
        Scale factors, the static fit's marker residuals (mm), the joint widths
        used (``measured_joint_widths``: per marker the width, the depth it set
        and how far the marker moved, mm), timings.
    """
    t0 = time.perf_counter()
    template = load_template(generic)
    mset = load_marker_set(marker_set) if marker_set else template_marker_set(generic)
    check_marker_set(mset, template)
    trial = read_c3d(static, subject=subject_name)
    names, lab = static_markers(trial, mset, path=static, frames=parse_frames(static_frames, trial.n_frames))
    bones = [mset.markers[n].bone for n in names]

    params = trial.subject_parameters

    def place(sk: Skeleton) -> tuple[dict[str, np.ndarray], dict[str, dict]]:
        # the template's tissue depth, except where the lab measured the joint's width
        try:
            return joint_width_placement(mset, sk, place_markers(mset, sk, names), params)
        except ValueError as exc:
            raise DataError(f"subject measurements: {exc}", static) from exc

    # A global similarity first: the lab's scale and the subject's stature.
    placed0 = place(template)[0]
    s0, _ = similarity_fit(np.array([placed0[n] for n in names]), lab)
    scales = {b: s0 for b in template.names}
    history = []
    groups = load_scaling_groups(mset)
    group_factors: dict[str, float] = {}
    if groups:
        # the marker set says which distances scale which bones (OpenSim's way)
        scales, group_factors = scale_factors_from_pairs(template, groups, placed0, dict(zip(names, lab)),
                                                         default=s0)
    else:
        # no table (an OpenSim MarkerSet): fit the factors, pose by pose
        for _ in range(max(1, iterations)):
            sk = scale_skeleton(template, scales)
            placed = place(sk)[0]
            local = np.array([_local(sk.bones[b].bone_to_world, placed[n]) for n, b in zip(names, bones)])
            poses = pose_to_static(sk, bones, local, lab, converge=False, rhythm=False)
            index = {n: i for i, n in enumerate(sk.names)}
            measured_local = np.array([_local(poses[index[b]], p) if np.isfinite(poses[index[b]]).all()
                                       else np.full(3, np.nan) for b, p in zip(bones, lab)])
            # a bone whose markers the pose cannot explain (a wrong label, a
            # marker that slipped) must not rescale it: only well-fitted markers vote
            err = np.linalg.norm(measured_local - local, axis=1)
            trusted = np.where((err < 40.0)[:, None], measured_local, np.nan)
            ratio = fit_scale_factors(sk, bones, local, trusted, fallback=1.0, limits=(0.85, 1.18))
            scales = {b: float(np.clip(scales[b] * ratio[b], 0.75 * s0, 1.3 * s0)) for b in template.names}
            history.append(float(np.max(np.abs(np.log(list(ratio.values()))))))
    sk = scale_skeleton(template, scales)
    placed, widths = place(sk)
    local = np.array([_local(sk.bones[b].bone_to_world, placed[n]) for n, b in zip(names, bones)])
    # The six sweeps a trial gets, which stop near the template's upright reference pose: a converged fit
    # to the manual's marker places follows their misplacement into the joints (phantoms of seeds 1-3,
    # median over bones 4.6 / 9.7 / 7.6 -> 7.6 / 14.6 / 13.3 deg; the Plug-in Gait subject of ../shared: its
    # left femur adducted by 34 deg; docs/benchmarks.md, "The no-MRI path keeps six sweeps"). The six
    # sweeps leave the legs where the template stood them, though (knee centres 35-46 mm, ankles 42-63 mm
    # off on the phantoms of seeds 0-3): the legs are then converged with their knee and ankle centres held
    # where the lateral markers put them (converge_limbs).
    # (the scapulae on their clavicles as the template has them: see Subject.follows_rhythm)
    first = pose_to_static(sk, bones, local, lab, converge=False, rhythm=False)
    poses, n_targets = converge_limbs(sk, mset, names, bones, local, lab, first)
    poses = neutral_twist(sk, poses)
    poses = neutral_twist(sk, poses, HAND_PREFIXES, HAND_AXES)
    poses = joint_consistent(sk, neutral_twist(sk, poses, FOOT_PREFIXES, FOOT_AXES))
    markers = bind_static(sk, names, bones, lab, poses)
    # residual of the placed (template) markers at the static pose: how far the
    # manual's positions are from where the markers really were
    index = {n: i for i, n in enumerate(sk.names)}
    resid = {}
    for (n, b), p_local, p_lab in zip(zip(names, bones), local, lab):
        T = poses[index[b]]
        resid[n] = float(np.linalg.norm(T[:3, :3] @ p_local + T[:3, 3] - p_lab))
    missing = [n for n in mset.physical if n not in names]
    static_doc = {"trial": str(static), "markers_lab": {n: p for n, p in zip(names, lab)},
                  "bone_to_lab": {b: poses[i] for i, b in enumerate(sk.names) if np.isfinite(poses[i]).all()}}
    subject = Subject(static=static_doc,
        skeleton=sk, markers=markers, marker_set=mset.name,
        provenance={"command": "build-subject", "mode": "static", "girdle_rhythm": False, "generic": str(generic),
                    "marker_set": mset.source or mset.name, "static": str(static),
                    "subject_prefix": subject_name, "scale_iterations": iterations},
    )
    report = {
        "mode": "static",
        "markers_bound": len(markers), "markers_missing_in_static": missing,
        "global_scale": s0,
        "scale_factors": {b: round(float(v), 4) for b, v in scales.items()},
        "scale_change_per_iteration": history,
        "scale_groups": {g: round(f, 4) for g, f in group_factors.items()},
        "placed_vs_measured_mm": {k: round(v, 2) for k, v in resid.items()},
        "measured_joint_widths": widths,
        "joint_centre_targets": n_targets,
        "seconds": round(time.perf_counter() - t0, 2),
    }
    return subject, report


def _summary(report: dict[str, Any], out_dir: Path) -> str:
    lines = [f"subject ({report['mode']}): {report.get('bones', '?')} bones, "
             f"{report.get('markers_bound', 0)} markers bound -> {out_dir}/subject.yaml"]
    if report.get("markers_missing_in_static"):
        lines.append(f"  not in the static trial: {', '.join(report['markers_missing_in_static'])}")
    if "placed_vs_measured_mm" in report and report["placed_vs_measured_mm"]:
        v = np.array(list(report["placed_vs_measured_mm"].values()))
        lines.append(f"  markers vs their manual placement: median {np.median(v):.1f} mm, max {v.max():.1f} mm")
    if "scale_factors" in report:
        s = np.array(list(report["scale_factors"].values()))
        lines.append(f"  bone scale factors {s.min():.3f} .. {s.max():.3f}")
    lines.append(f"  took {report.get('seconds', 0):.1f} s")
    return "\n".join(lines)


def run_build_subject(mri: list[str] | None, out_dir: str | os.PathLike, *, generic: str | os.PathLike = "default",
                      marker_set: str | os.PathLike | None = None, static: str | os.PathLike | None = None,
                      forearm_poses: list[str] | None = None, seeds: str | os.PathLike | None = None,
                      labels: str | os.PathLike | None = None, subject_name: str | None = None,
                      static_frames: str | None = None, functional: list[str] | None = None) -> dict[str, Any]:
    """The ``build-subject`` command: build and write a subject folder.

    The folder is assembled in a temporary folder beside ``out_dir`` and
    renamed at the end, so a failure leaves no half-written subject.

    Returns
    -------
    dict
        The report (also ``out_dir/report.json``) with a ``summary`` text.
    """
    import json

    from bonecap.io.atomic import atomic_path
    from bonecap.subject import _plain, write_subject

    out_dir = Path(out_dir)
    if not mri and not labels:
        if static is None:
            raise InputError("build-subject needs MRI_PATH(s), --labels, or --static STATIC.c3d "
                             "(the template scaled to a static trial)", out_dir)
        if forearm_poses:
            raise InputError("--forearm-poses needs the MRI stations too", out_dir)
        if functional:
            # measured on the phantoms: the scaled template's knee axis and joint centres read the femur's
            # twist 5-11 deg off, where the template's neutral twist was within 0.5 (femur 2.2 -> 7.3 deg)
            raise InputError("--functional needs the MRI stations (the subject's own knee axis): with the "
                             "template alone the knee's axis is not known well enough to correct the femur",
                             functional[0])
        subject, report = build_from_static(static, generic=generic, marker_set=marker_set,
                                            subject_name=subject_name, static_frames=static_frames)
        qc = None
    else:
        from bonecap.build_mri import build_from_mri

        subject, report, qc = build_from_mri(mri or [], generic=generic, marker_set=marker_set, static=static,
                                             forearm_poses=forearm_poses, seeds=seeds, labels=labels,
                                             subject_name=subject_name, functional=functional)
    report["bones"] = len(subject.skeleton.bones)
    with atomic_path(out_dir, directory=True) as tmp:
        write_subject(subject, tmp, extra={"report_file": "report.json"})
        if qc is not None:
            qc(tmp)
        (tmp / "report.json").write_text(json.dumps(_plain(report), indent=2, default=str))
    report["summary"] = _summary(report, out_dir)
    return report
